"""Head-to-head heats of an agent against a field: does it finish ahead, and how many collisions does it cause?

The field defaults to the other shipped agents and `bot:follow@1.0`, the scripted
car that keeps to the centre line and slows behind a car in its lane. Every
heat is a `head_to_head` race (3 laps by default) with the agent on the pole
and the field behind it in a fixed order, run once per seed on each track. A
collision is *caused* by the car at fault under the race rules
(`rules.at_fault`: the README's "Race rules"), once per incident.

Per entrant: first places, mean position, laps driven, at-fault collisions
per lap driven and by kind (`caused_kinds`: rear_end, push_off, side_swipe,
cut_across, ... as the stewards judged each), penalties, and overtakes (`racing.overtakes`: passes for
position on track, attempted and completed): a racer should take most of the
first places and cause no more collisions per lap than `bot:follow`.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from ..environment.race_env import MAX_CARS
from ..racing.entrant import TEACHER_PREFIX, teacher_spec
from ..racing.overtakes import FIELDS, OvertakeRecorder
from ..resources import agents_dir, list_agents

FIELD_BOT = "bot:follow@1.0"
HEAT_LAPS = 3
FIELD_ROOM = MAX_CARS - 2  # shipped agents a default heat has room for beside the agent and FIELD_BOT
STEP_BUDGET = 30.0  # seconds of CPU time per inference step: heats judge driving, not inference speed


def default_field(agent_path) -> list[str]:
    """The other shipped agents (by content, so a copy of a shipped file is not raced against itself) and
    `bot:follow@1.0`. A heat holds at most `MAX_CARS` cars: where the agent, the bot and the other shipped
    agents would be more, the first of those agents by name race (`left_out` names the others)."""
    return _rivals(agent_path)[:FIELD_ROOM] + [FIELD_BOT]


def left_out(agent_path) -> list[str]:
    """The other shipped agents the default field has no room for (see `default_field`)."""
    return _rivals(agent_path)[FIELD_ROOM:]


def _rivals(agent_path) -> list[str]:
    """The shipped agents that are not `agent_path` (by content), by name."""
    spec = str(agent_path)
    own = hashlib.sha256(Path(teacher_spec(spec)[0] if spec.startswith(TEACHER_PREFIX) else spec).read_bytes()).digest()
    return [name for name in list_agents()
            if hashlib.sha256((agents_dir() / f"{name}.pt").read_bytes()).digest() != own]


def check_heats(tracks, field) -> None:
    """Refuse, before any race runs, a heat track or an entrant that cannot race (naming the option)."""
    from ..environment.bots import parse_bot
    from ..resources import resolve_agent_path
    from ..sim.tracks import TrackError, resolve_track_path

    for track in tracks or ():
        try:
            resolve_track_path(track)
        except TrackError as exc:
            raise ValueError(f"--heat-tracks: {exc}") from None
    if field is not None and len(field) + 1 > MAX_CARS:
        raise ValueError(f"--field: {len(field)} entrants and the agent make {len(field) + 1} cars; a heat holds "
                         f"at most {MAX_CARS}")
    for spec in field or ():
        if spec.startswith("bot:"):
            try:
                parse_bot(spec)
            except ValueError as exc:
                raise ValueError(f"--field: {exc}") from None
        elif spec.startswith(TEACHER_PREFIX):
            if not Path(teacher_spec(spec)[0]).is_file():
                raise ValueError(f"--field: {spec}: no such teacher file")
        elif not resolve_agent_path(spec).is_file():
            raise ValueError(f"--field: {spec}: no such agent file or shipped agent")


class FaultRecorder:
    """A `run_race` recorder that adds to every result car its at-fault incidents by kind (`caused_kinds`:
    {kind: count})."""

    def start(self, env) -> None:
        pass

    def step(self, env, observations=None, rewards=None, infos=None) -> None:
        pass

    def finish(self, env, result: dict) -> None:
        for car in result["cars"]:
            kinds: dict[str, int] = {}
            for record in env.races[int(car["car"].split("_")[1])].collisions:
                if record["caused"]:
                    kinds[record["kind"]] = kinds.get(record["kind"], 0) + 1
            car["caused_kinds"] = kinds


def run_heats(agent_path, tracks, seeds, field=None, laps=HEAT_LAPS, progress=None) -> list[dict]:
    """One row per heat: the track, seed and every car's place, laps driven and collisions caused (and their
    kinds)."""
    from ..racing.runner import RaceConfig, make_controller, run_race

    field = default_field(agent_path) if field is None else list(field)
    say = progress or (lambda line: None)
    rows = []
    for track in tracks:
        for seed in seeds:
            entrants = [make_controller(spec, **({} if spec.startswith("bot:") else {"step_budget": STEP_BUDGET}))
                        for spec in [str(agent_path), *field]]
            result = run_race(entrants, RaceConfig(track=track, race="head_to_head", laps=laps, seed=seed),
                              recorders=[OvertakeRecorder(), FaultRecorder()])
            cars = sorted(result["cars"], key=lambda c: int(c["car"].split("_")[1]))
            row = {"track": result["track"], "seed": seed, "laps": laps, "cars": [
                {"entrant": spec, "position": car["position"], "laps": car["laps"],
                 "laps_driven": round(car["progress"] * laps / 100.0, 3), "resets": car["resets"],
                 "penalties": car["penalties"], "collisions": car["collisions"],
                 "collisions_caused": car["collisions_caused"], "caused_kinds": car["caused_kinds"],
                 "status": car["status"],
                 **{name: car[name] for name in FIELDS}}
                for spec, car in zip([Path(str(agent_path)).stem] + field, cars)]}
            rows.append(row)
            agent = row["cars"][0]
            say(f"heat {track} seed {seed}: P{agent['position']}, {agent['laps']}/{laps} laps, "
                f"{agent['collisions_caused']} collisions caused, {agent['overtakes']} overtakes")
    return rows


def summarise_heats(rows: list[dict]) -> dict:
    """Per track and over all heats, per entrant: heats, first places, mean position, at-fault collisions per
    lap driven and by kind, penalties, overtakes (and per lap), overtakes attempted and completed."""
    def figures(selected):
        out = {}
        for k, name in enumerate(c["entrant"] for c in selected[0]["cars"]):
            cars = [r["cars"][k] for r in selected]
            driven = sum(c["laps_driven"] for c in cars)
            total = {key: sum(c.get(key, 0) for c in cars) for key in ("collisions_caused", "penalties", *FIELDS)}
            kinds: dict[str, int] = {}
            for c in cars:
                for kind, count in c.get("caused_kinds", {}).items():
                    kinds[kind] = kinds.get(kind, 0) + count
            out[name] = {"heats": len(cars), "first": sum(c["position"] == 1 for c in cars),
                         "mean_position": sum(c["position"] for c in cars) / len(cars),
                         "laps_driven": round(driven, 2), **total,
                         "caused_kinds": dict(sorted(kinds.items(), key=lambda item: -item[1])),
                         "caused_per_lap": total["collisions_caused"] / max(driven, 0.25),
                         "overtakes_per_lap": total["overtakes"] / max(driven, 0.25)}
        return out

    if not rows:
        return {}
    tracks = list(dict.fromkeys(r["track"] for r in rows))
    return {"all": figures(rows), **{t: figures([r for r in rows if r["track"] == t]) for t in tracks}}
