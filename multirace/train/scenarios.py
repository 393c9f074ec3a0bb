"""Overtake scenarios: can an agent pass slower cars cleanly, from set-up starts?

Each scenario puts the agent (car 0) and one or two scripted cars at rest at
seeded spots of a track's features (a straight, a corner entry, a chicane
entry) and races them head-to-head for `TIME_LIMIT` seconds. The scripted
cars (`LaneController`) hold a lane (or the centre line) at a set, slower
speed and slow behind a car in their way, as the bots do. Success: the agent
gets ahead of every scripted car by at least a car length on the road and is
still that far ahead when the time is up, with no incident it was at fault
for (the race rules: `rules.at_fault`) and none of them off track (a pass
through their off-track is none).

Scenarios (`SCENARIOS`): a slower car ahead on a straight; a slower car
ahead into a chicane; a car alongside into a corner at 1 m/s (each in a
lane, the agent's side seeded); two slower cars side by side ahead on a
straight, one of them a little faster (a gap opens).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..environment.bots import PurePursuit, speed_in_traffic
from ..environment.drivers import car_pose
from ..racing.entrant import Controller

TIME_LIMIT = 12.0  # seconds of race time a scenario lasts
SLOW = 0.5  # m/s: the slower cars' speed
STRAIGHT_RUN = 3.0  # m of nearly straight road ahead of a straight's start spot
STRAIGHT_CURVATURE = 0.15  # 1/m: road this straight or straighter is a straight
CORNER_CURVATURE = 0.6  # 1/m: road this curved is a corner
RUN_IN = 1.5  # m before a corner's (or a chicane's) entry where the cars start
CHICANE_RUN = 4.0  # m: a corner one way, then one the other way within this, is a chicane
SAMPLE = 0.25  # m between the curvature samples


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A set-up start: where (`site`) and who: the scripted cars as (metres ahead of the agent, lane, speed),
    lane +1 / -1 for the side the agent's lane is on / the other one, 0 for the centre line."""

    name: str
    site: str  # "straight", "corner" or "chicane"
    agent_lane: int  # +1: a seeded side; 0: the centre line
    others: tuple


SCENARIOS = (
    Scenario("slower car ahead on a straight", "straight", 0, ((1.0, 0, SLOW),)),
    Scenario("slower car ahead in a chicane", "chicane", 0, ((1.0, 0, SLOW),)),
    Scenario("car alongside into a corner", "corner", 1, ((0.0, -1, 1.0),)),
    Scenario("two cars side by side ahead", "straight", 0, ((1.0, 1, SLOW), (1.0, -1, SLOW + 0.3))),
)


class LaneController(Controller):
    """A scripted car that holds a lateral offset at a speed, slowing behind a car in its way."""

    def __init__(self, speed: float, lateral: float):
        self.speed, self.lateral = speed, lateral
        self.name = f"scenario:lane@{speed:g}"

    def drive(self, state, car, observation=None):
        me, spec = state.cars[car], state.car_spec
        speed = speed_in_traffic(self.speed, state.traffic(car), spec)
        return PurePursuit(speed=speed, lateral=self.lateral).command(state.track, spec, car_pose(me), me.segment)


def track_sites(track) -> dict[str, list[float]]:
    """Start spots (arc lengths) of each site kind on `track`: where a straight begins, `RUN_IN` metres before
    the entry of a corner after a straight, and before a chicane's (a corner one way, then the other within
    `CHICANE_RUN`)."""
    ss = np.arange(0.0, track.length, SAMPLE)
    yaw = np.array([track.point_at(s)[2] for s in ss])
    turn = np.angle(np.exp(1j * (np.roll(yaw, -1) - np.roll(yaw, 1)))) / (2 * SAMPLE)  # signed curvature
    n, ahead = len(ss), int(STRAIGHT_RUN / SAMPLE)
    window = lambda k, count: turn[(k + np.arange(count)) % n]  # noqa: E731 - the samples from k on
    straights = [float(ss[k]) for k in range(n) if np.abs(window(k, ahead)).max() < STRAIGHT_CURVATURE]
    entries = [k for k in range(n) if abs(turn[k]) >= CORNER_CURVATURE > abs(turn[k - 1])]
    run_in, bend = int(RUN_IN / SAMPLE), int(CHICANE_RUN / SAMPLE)
    corners = [k for k in entries if np.abs(window(k - run_in, run_in)).max() < 2 * STRAIGHT_CURVATURE]
    chicanes = [k for k in entries if (np.sign(turn[k]) * window(k, bend)).min() <= -CORNER_CURVATURE]
    before = lambda ks: [float((ss[k] - RUN_IN) % track.length) for k in ks]  # noqa: E731
    return {"straight": straights, "corner": before(corners), "chicane": before(chicanes)}


def placements(scenario: Scenario, track, sites: dict, seed: int) -> dict | None:
    """{car: (arc length, lateral offset)} of the agent (car 0) and the scripted cars for this seed; None where
    the track has no site of the kind."""
    candidates = sites[scenario.site]
    if not candidates:
        return None
    rng = np.random.default_rng([seed, SCENARIOS.index(scenario)])
    s0 = float(rng.choice(candidates)) + float(rng.uniform(-0.2, 0.2))
    side = int(rng.choice([-1, 1]))
    gap = float(rng.uniform(0.0, 0.3))

    def lateral(lane: int, s: float) -> float:
        return 0.0 if lane == 0 else track.lane_offset(0 if lane * side > 0 else 1, s)

    slots = {0: (s0 % track.length, lateral(scenario.agent_lane, s0))}
    for k, (ahead, lane, _) in enumerate(scenario.others):
        s = s0 + ahead + (gap if ahead else 0.0)
        slots[k + 1] = (s % track.length, lateral(lane, s))
    return slots


class ScenarioJudge:
    """A `run_race` recorder: when (race time) the agent first led every other car by a car length on the road
    (`passed`, None if it never did), whether it still did at the end (`ahead_at_end`), whether it was at
    fault in an incident (`fouled`) and whether one of them left the track (`void`)."""

    def start(self, env) -> None:
        self.passed, self.ahead_at_end, self.fouled, self.void = None, False, False, False
        races = _races(env)
        length, me = env.track.length, races[0].distance
        # race distances of cars moved to their spots may differ by a lap: the gaps start from the road's
        self._offsets = [(me - race.distance + length / 2) % length - length / 2 - (me - race.distance)
                         for race in races[1:]]

    def step(self, env, observations=None, rewards=None, infos=None) -> None:
        races = _races(env)
        self.fouled |= races[0].collisions_caused() > 0
        self.void |= any(race.off_tracks for race in races[1:])
        if self.passed is None and self._ahead(env):
            self.passed = env.race_state.time

    def finish(self, env, result=None) -> None:
        self.ahead_at_end = self._ahead(env)

    def _ahead(self, env) -> bool:
        """Does car 0 lead every other car by a car length on the road (or by a lap and more)?"""
        races = _races(env)
        me = races[0].distance
        gaps = [me - race.distance + offset for race, offset in zip(races[1:], self._offsets)]
        return min(gaps) >= env.car_spec.length


def _races(env) -> list:
    """Every car's race record from the env's published `RaceState`."""
    return [car.race for car in env.race_state.cars]


def run_scenario(agent, scenario: Scenario, track: str = "reinvent_base", seed: int = 0, step_budget=30.0) -> dict:
    """One scenario run of an agent file (or bot spec): whether it passed cleanly, and when."""
    from ..racing.runner import RaceConfig, make_controller, run_race
    from ..sim.tracks import load_track

    loaded = load_track(track)
    slots = placements(scenario, loaded, track_sites(loaded), seed)
    row = {"scenario": scenario.name, "track": loaded.name, "seed": seed}
    if slots is None:
        return {**row, "success": None, "reason": f"no {scenario.site} on {loaded.name}"}
    agent = str(agent)
    entrant = make_controller(agent, **({} if agent.startswith("bot:") else {"step_budget": step_budget}))
    others = [LaneController(speed, slots[k + 1][1]) for k, (_, _, speed) in enumerate(scenario.others)]
    judge = ScenarioJudge()
    config = RaceConfig(track=track, race="head_to_head", laps=10, seed=seed,
                        max_steps=int(math.ceil(TIME_LIMIT * 15)), start=tuple(slots.items()))
    result = run_race([entrant, *others], config, recorders=[judge])
    car = next(c for c in result["cars"] if c["car"] == "car_0")
    success = judge.passed is not None and judge.ahead_at_end and not (judge.fouled or judge.void)
    return {**row, "success": success, "passed_at": judge.passed, "ahead_at_end": judge.ahead_at_end,
            "fouled": judge.fouled, "void": judge.void,
            "caused": car["collisions_caused"], "off_tracks": car["off_tracks"]}


def run_scenarios(agent, seeds, track: str = "reinvent_base", progress=None) -> list[dict]:
    """Every scenario once per seed: the rows of `run_scenario`."""
    say = progress or (lambda line: None)
    rows = []
    for scenario in SCENARIOS:
        for seed in seeds:
            row = run_scenario(agent, scenario, track, seed)
            rows.append(row)
            say(f"scenario {scenario.name} seed {seed}: "
                f"{'passed cleanly' if row['success'] else row.get('reason') or 'not passed cleanly'}")
    return rows


def summarise_scenarios(rows: list[dict]) -> dict:
    """Per scenario: runs, runs that got past and stayed ahead (cleanly or not), clean passes and their share,
    the success rate (runs on a track without the scenario's site left out)."""
    out = {}
    for name in dict.fromkeys(r["scenario"] for r in rows):
        runs = [r for r in rows if r["scenario"] == name and r["success"] is not None]
        clean = sum(r["success"] for r in runs)
        out[name] = {"runs": len(runs), "passed": sum(r["passed_at"] is not None and r["ahead_at_end"] for r in runs),
                     "passed_cleanly": clean, "success_rate": clean / len(runs) if runs else None}
    return out
