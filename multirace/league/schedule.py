"""The deterministic schedule: time trials and head-to-head heats of every entrant, kept in the store."""
from __future__ import annotations

import hashlib
import itertools
import json

from .config import TIME_TRIAL_FORMAT, LeagueConfig
from .store import _Tx


def entrants(folder, config: LeagueConfig, conn) -> list[dict]:
    """Every entrant, in a deterministic order: the league's bots, then submissions by name."""
    out = [{"name": bot, "spec": bot, "sha256": None, "step_budget": None} for bot in config.bots]
    for name, sha, file, budget in conn.execute(
            "SELECT name, sha256, file, step_budget FROM submissions ORDER BY name"):
        out.append({"name": name, "spec": file, "sha256": sha, "step_budget": budget})
    return out


def _match_id(spec: dict) -> str:
    canonical = json.dumps(spec, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def _heat_offset(names: list[str]) -> int:
    """A grid rotation offset that depends only on who is in the heat (stable as entrants join)."""
    return int(hashlib.sha256("\n".join(sorted(names)).encode()).hexdigest()[:8], 16)


def build_schedule(config: LeagueConfig, entries: list[dict]) -> list[dict]:
    """The full deterministic schedule: a list of {"match_id", "kind", "round", "spec"} in schedule order.

    Time trials: every entrant, per track, direction, seed and trial. Head-to-head:
    every K-subset of entrants (so every pair meets equally often) per track,
    direction, seed and trial; a heat's grid order is the subset rotated by
    (block + trial + an offset drawn from its entrants' names) mod K, so over
    blocks each entrant starts from each slot, and a heat's id does not change
    when another entrant joins (a new entrant or version adds only its own matches).
    A round is one (track, direction, seed, trial) block of heats.
    """
    schedule = []
    blocks = [(t.name, d == "reverse", seed) for t in config.tracks for d in t.directions for seed in config.seeds]

    def entrant_spec(e):
        budget = e["step_budget"] if e["step_budget"] is not None else config.step_budget
        return {"name": e["name"], "spec": e["spec"], "sha256": e["sha256"], "step_budget": budget}

    if config.time_trial:
        tt = config.time_trial
        for b, (track, reverse, seed) in enumerate(blocks):
            for trial in range(tt["trials"]):
                for e in entries:
                    spec = {"kind": "time_trial", "race": TIME_TRIAL_FORMAT, "track": track, "reverse": reverse,
                            "seed": seed, "trial": trial, "laps": tt["laps"], "max_steps": tt["max_steps"],
                            "entrants": [entrant_spec(e)]}
                    schedule.append({"kind": "time_trial", "round": b * tt["trials"] + trial, "spec": spec})
    if config.head_to_head and len(entries) >= 2:
        h = config.head_to_head
        k = min(h["cars"], len(entries))
        heats = list(itertools.combinations(range(len(entries)), k))
        round_no = 0
        for b, (track, reverse, seed) in enumerate(blocks):
            for trial in range(h["trials"]):
                for heat in heats:
                    shift = (b * h["trials"] + trial + _heat_offset([entries[i]["name"] for i in heat])) % k
                    grid = heat[shift:] + heat[:shift]
                    spec = {"kind": "head_to_head", "race": "head_to_head", "track": track, "reverse": reverse,
                            "seed": seed, "trial": trial, "laps": h["laps"], "max_steps": h["max_steps"],
                            "entrants": [entrant_spec(entries[i]) for i in grid]}
                    schedule.append({"kind": "head_to_head", "round": round_no, "spec": spec})
                round_no += 1
    for row in schedule:
        row["match_id"] = _match_id(row["spec"])
        row["spec"]["match_id"] = row["match_id"]
    return schedule


def sync_schedule(folder, config: LeagueConfig, conn) -> list[dict]:
    """Insert the schedule's new rows (existing rows keep their seq); returns the current schedule."""
    schedule = build_schedule(config, entrants(folder, config, conn))
    with _Tx(conn):
        known = {row[0] for row in conn.execute("SELECT match_id FROM schedule")}
        seq = conn.execute("SELECT COALESCE(MAX(seq), -1) FROM schedule").fetchone()[0]
        for row in schedule:
            if row["match_id"] in known:
                continue
            seq += 1
            conn.execute("INSERT INTO schedule (match_id, seq, kind, round, spec) VALUES (?, ?, ?, ?, ?)",
                         (row["match_id"], seq, row["kind"], row["round"], json.dumps(row["spec"], sort_keys=True)))
    return schedule
