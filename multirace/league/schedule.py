"""The schedule, kept in the store: each league stage's matches (`config.STAGES`): a solo stage's time trials,
a heat stage's heats, a round robin built at once or the uncertainty schedule's pairings planned batch by
batch from the results so far."""
from __future__ import annotations

import hashlib
import itertools
import json

from .config import STAGES, LeagueConfig, Stage
from .store import _Tx
from .uncertainty import next_pairs


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


def _blocks(config: LeagueConfig) -> list[tuple[str, bool, int]]:
    return [(t.name, d == "reverse", seed) for t in config.tracks for d in t.directions for seed in config.seeds]


def _entrant_spec(config: LeagueConfig, e: dict) -> dict:
    budget = e["step_budget"] if e["step_budget"] is not None else config.step_budget
    return {"name": e["name"], "spec": e["spec"], "sha256": e["sha256"], "step_budget": budget}


def _heat_matches(config: LeagueConfig, stage: Stage, heat: list[dict]) -> list[tuple[int, dict]]:
    """Every match of one heat's entrants, (block * trials + trial, spec) per (track, direction, seed) block
    and trial; the grid is the heat rotated by (block + trial + an offset drawn from its entrants' names)."""
    h, out = config.stages[stage.name], []
    for b, (track, reverse, seed) in enumerate(_blocks(config)):
        for trial in range(h["trials"]):
            shift = (b * h["trials"] + trial + _heat_offset([e["name"] for e in heat])) % len(heat)
            grid = heat[shift:] + heat[:shift]
            out.append((b * h["trials"] + trial,
                        {"kind": stage.name, "race": stage.race, "track": track, "reverse": reverse,
                         "seed": seed, "trial": trial, "laps": h["laps"], "max_steps": h["max_steps"],
                         "entrants": [_entrant_spec(config, e) for e in grid]}))
    return out


def _row(kind: str, round_no: int, spec: dict) -> dict:
    match_id = _match_id(spec)
    return {"kind": kind, "round": round_no, "spec": {**spec, "match_id": match_id}, "match_id": match_id}


def _solo_matches(config: LeagueConfig, stage: Stage, entries: list[dict]) -> list[dict]:
    """A solo stage's time trials: every entrant alone, per track, direction, seed and trial."""
    tt, rows = config.stages[stage.name], []
    for b, (track, reverse, seed) in enumerate(_blocks(config)):
        for trial in range(tt["trials"]):
            for e in entries:
                spec = {"kind": stage.name, "race": stage.race, "track": track, "reverse": reverse, "seed": seed,
                        "trial": trial, "laps": tt["laps"], "max_steps": tt["max_steps"],
                        "entrants": [_entrant_spec(config, e)]}
                rows.append(_row(stage.name, b * tt["trials"] + trial, spec))
    return rows


def _round_robin(config: LeagueConfig, stage: Stage, entries: list[dict]) -> list[dict]:
    """A heat stage's round robin: every K-subset of the entrants, block by block."""
    k = min(config.stages[stage.name]["cars"], len(entries))
    heats = [(i, match) for i, heat in enumerate(itertools.combinations(entries, k))
             for match in _heat_matches(config, stage, list(heat))]
    heats.sort(key=lambda item: item[1][0])  # block by block, heats in the same order within each
    return [_row(stage.name, round_no, spec) for _, (round_no, spec) in heats]


def _stages(config: LeagueConfig, schedule: str | None = None) -> list[Stage]:
    """The league's enabled stages, in `STAGES` order; with `schedule`, only the heat stages scheduled so."""
    return [stage for name, stage in STAGES.items() if name in config.stages
            and (schedule is None or not stage.solo and config.stages[name]["schedule"] == schedule)]


def build_schedule(config: LeagueConfig, entries: list[dict]) -> list[dict]:
    """The deterministic schedule: a list of {"match_id", "kind", "round", "spec"} in schedule order, stage
    by stage.

    A solo stage (time trials): every entrant, per track, direction, seed and trial. A heat stage with the
    round robin: every K-subset of entrants (so every pair meets equally often) per track, direction, seed
    and trial (`_heat_matches`), so over blocks each entrant starts from each slot, and a heat's id does not
    change when another entrant joins (a new entrant or version adds only its own matches). A round is one
    (track, direction, seed, trial) block of heats. The uncertainty schedule's heats are planned as
    results arrive (`sync_schedule`), not here.
    """
    schedule = []
    for stage in _stages(config):
        if stage.solo:
            schedule += _solo_matches(config, stage, entries)
        elif len(entries) >= 2 and config.stages[stage.name]["schedule"] == "round_robin":
            schedule += _round_robin(config, stage, entries)
    return schedule


def _planned_heats(config: LeagueConfig, stage: Stage, entries: list[dict], conn) -> list[dict]:
    """The uncertainty schedule's heats of a heat stage among the current entrants: those planned so far
    (stored), and the next batch (`uncertainty.next_pairs`) once every planned heat has a result. Heats of
    earlier versions or another league definition are not current: their ids differ."""
    from openskill.models import PlackettLuce

    by_name = {e["name"]: e for e in entries}
    stored = conn.execute("SELECT s.match_id, s.round, s.spec, r.status, r.result FROM schedule s LEFT JOIN "
                          "results r USING (match_id) WHERE s.kind = ? ORDER BY s.seq", (stage.name,)).fetchall()
    pairs, ids, orders, waiting = {}, {}, [], False
    for match_id, round_no, spec, status, result in stored:
        names = tuple(sorted(e["name"] for e in json.loads(spec)["entrants"]))
        if len(names) != 2 or not all(n in by_name for n in names):
            continue
        if names not in ids:
            ids[names] = {_match_id(spec) for _, spec in _heat_matches(config, stage, [by_name[n] for n in names])}
        if match_id in ids[names]:
            pairs.setdefault(names, round_no)
            waiting |= status is None
            if status == "ok":
                cars = sorted(json.loads(result)["cars"], key=lambda c: c["position"])
                orders.append([(c["name"], c["position"]) for c in cars if c["name"] in by_name])
    rows = [_row(stage.name, round_no, spec) for names, round_no in pairs.items()
            for _, spec in _heat_matches(config, stage, [by_name[n] for n in names])]
    stored_ids = {row[0] for row in stored}
    if waiting or any(row["match_id"] not in stored_ids for row in rows):
        return rows  # a batch is still running: the next one is planned from its results
    next_round = 1 + max((row[1] for row in stored), default=-1)
    for a, b in next_pairs(PlackettLuce(), sorted(by_name), orders, {frozenset(p) for p in pairs},
                           config.stages[stage.name]):
        rows += [_row(stage.name, next_round, spec)
                 for _, spec in _heat_matches(config, stage, [by_name[a], by_name[b]])]
    return rows


def current_schedule(config: LeagueConfig, entries: list[dict], conn) -> list[dict]:
    """The schedule of the current entrants: `build_schedule`, and for each heat stage with the uncertainty
    schedule the heats planned so far plus the next batch when it is due (reads the store only)."""
    schedule = build_schedule(config, entries)
    for stage in _stages(config, schedule="uncertainty"):
        schedule += _planned_heats(config, stage, entries, conn)
    return schedule


def sync_schedule(folder, config: LeagueConfig, conn) -> list[dict]:
    """Insert the schedule's new rows (existing rows keep their seq); returns the current schedule."""
    with _Tx(conn):
        schedule = current_schedule(config, entrants(folder, config, conn), conn)
        known = {row[0] for row in conn.execute("SELECT match_id FROM schedule")}
        seq = conn.execute("SELECT COALESCE(MAX(seq), -1) FROM schedule").fetchone()[0]
        for row in schedule:
            if row["match_id"] in known:
                continue
            seq += 1
            conn.execute("INSERT INTO schedule (match_id, seq, kind, round, spec) VALUES (?, ?, ?, ?, ?)",
                         (row["match_id"], seq, row["kind"], row["round"], json.dumps(row["spec"], sort_keys=True)))
    return schedule
