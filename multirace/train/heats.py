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
first places and cause no more collisions per lap than `bot:follow`. Each
heat's row also holds the agent's at-fault incidents with the steps that led
to them (`incidents`: both cars' gap, road position, speed and commanded
speed), to tell a car that never braked from one cut up, and whether the other car
had just been stopped by a crash of its own (`into_crash`: a pile-up the agent ran into).
"""
from __future__ import annotations

import hashlib
from collections import deque
from pathlib import Path

from ..environment.race_env import MAX_CARS
from ..racing.entrant import TEACHER_PREFIX, teacher_spec
from ..racing.overtakes import FIELDS, OvertakeRecorder
from ..resources import agents_dir, list_agents

FIELD_BOT = "bot:follow@1.0"
HEAT_LAPS = 3
FIELD_ROOM = MAX_CARS - 2  # shipped agents a default heat has room for beside the agent and FIELD_BOT
STEP_BUDGET = 30.0  # seconds of CPU time per inference step: heats judge driving, not inference speed
INCIDENT_STEPS = 8  # steps before (and with) an at-fault incident kept in its record (about half a second)
CRASH_DROP = 2.0  # a speed lost in one step beyond this many times what brakes shed: a crash stopped the car


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
    {kind: count}), and keeps car 0's at-fault incidents with another car, each with the `INCIDENT_STEPS`
    steps up to it (`incidents`)."""

    def start(self, env) -> None:
        self.incidents, self._seen = [], 0
        self._pending: list[tuple[dict, list]] = []  # car 0's new contact records, with the steps up to each
        self._history: deque = deque(maxlen=INCIDENT_STEPS)

    def step(self, env, observations=None, rewards=None, infos=None) -> None:
        state = env.race_state
        self._history.append([(car.race.distance, car.lateral, car.speed, car.command[1]) for car in state.cars])
        records = env.races[0].collisions
        for record in records[self._seen:]:  # (the fault may be found later in the incident: judged at the end)
            if record["with"] in env.car_names:
                self._pending.append((record, list(self._history)))
        self._seen = len(records)

    def finish(self, env, result: dict) -> None:
        for car in result["cars"]:
            kinds: dict[str, int] = {}
            for record in env.races[int(car["car"].split("_")[1])].collisions:
                if record["caused"]:
                    kinds[record["kind"]] = kinds.get(record["kind"], 0) + 1
            car["caused_kinds"] = kinds
        for record, steps in self._pending:
            if record["caused"]:
                other = env.car_names.index(record["with"])
                self.incidents.append({"time": record["time"], "kind": record["kind"], "with": record["with"],
                                       "steps": [_incident_step(row[0], row[other], env.track) for row in steps],
                                       "into_crash": stopped_by_crash([row[other][2] for row in steps[:-1]],
                                                                      env.car_spec.brake, env.dt)})


def _incident_step(me: tuple, other: tuple, track) -> dict:
    """One step of an incident record: how far `other` was ahead of `me` along the track (m, negative: behind),
    and [me, other]'s lateral offsets (m, + left of centre), speeds and commanded speeds (m/s); `me` and
    `other` are (race distance, lateral, speed, commanded speed)."""
    return {"gap": round(track.wrap_ds(other[0] - me[0]), 3), "lateral": [round(me[1], 3), round(other[1], 3)],
            "speed": [round(me[2], 3), round(other[2], 3)], "command_speed": [round(me[3], 3), round(other[3], 3)]}


def stopped_by_crash(speeds: list[float], brake: float, dt: float) -> bool:
    """Whether a car whose speed (m/s) over consecutive steps of `dt` s was `speeds` lost more in one step than
    `CRASH_DROP` x what its brakes (`brake` m/s^2) shed: a crash of its own stopped it."""
    limit = CRASH_DROP * brake * dt
    return any(before - after > limit for before, after in zip(speeds, speeds[1:]))


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
            faults = FaultRecorder()
            result = run_race(entrants, RaceConfig(track=track, race="head_to_head", laps=laps, seed=seed),
                              recorders=[OvertakeRecorder(), faults])
            cars = sorted(result["cars"], key=lambda c: int(c["car"].split("_")[1]))
            row = {"track": result["track"], "seed": seed, "laps": laps, "cars": [
                {"entrant": spec, "position": car["position"], "laps": car["laps"],
                 "laps_driven": round(car["progress"] * laps / 100.0, 3), "resets": car["resets"],
                 "penalties": car["penalties"], "collisions": car["collisions"],
                 "collisions_caused": car["collisions_caused"], "caused_kinds": car["caused_kinds"],
                 "status": car["status"],
                 **{name: car[name] for name in FIELDS}}
                for spec, car in zip([Path(str(agent_path)).stem] + field, cars)], "incidents": faults.incidents}
            rows.append(row)
            agent = row["cars"][0]
            say(f"heat {track} seed {seed}: P{agent['position']}, {agent['laps']}/{laps} laps, "
                f"{agent['collisions_caused']} collisions caused, {agent['overtakes']} overtakes")
    return rows


def summarise_heats(rows: list[dict]) -> dict:
    """Per track and over all heats, per entrant: heats, first places, mean position, at-fault collisions per
    lap driven and by kind, penalties, overtakes (and per lap), overtakes attempted and completed; for the
    agent, how many of its at-fault incidents were into a car a crash had just stopped."""
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
        agent = out[selected[0]["cars"][0]["entrant"]]  # its incidents are kept: how many were into a crash
        agent["caused_into_crash"] = sum(i.get("into_crash", False) for r in selected for i in r["incidents"])
        return out

    if not rows:
        return {}
    tracks = list(dict.fromkeys(r["track"] for r in rows))
    return {"all": figures(rows), **{t: figures([r for r in rows if r["track"] == t]) for t in tracks}}
