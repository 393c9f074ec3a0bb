"""The race core (environment/core.py) and the `RaceState` it publishes: what readers see agrees with what the
env reports, a parked car stays where it stopped, and nothing outside the core reads its private attributes."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

import multirace
from multirace.environment.race_state import RaceState

PACKAGE = Path(multirace.__file__).parent
OWNERS = {"environment/core.py", "environment/race_env.py"}  # the core and its adapter
PRIVATE_ACCESS = re.compile(r"\w*env\._\w|\bcore\._\w|race_state\._\w|_topdown_state")


def _drive(env, steps: int):
    """Step `env` with every car at a moderate straight-ahead action; yields each step's infos."""
    action = env.actions.nearest(0.0, 1.5)
    for _ in range(steps):
        if not env.agents:
            return
        _, _, _, _, infos = env.step({agent: action for agent in env.agents})
        yield infos


def test_the_race_state_agrees_with_the_infos_and_the_traffic():
    env = multirace.parallel_env(num_cars=3, race="head_to_head", laps=1, bots=("follow@1.0",), max_steps=120)
    try:
        _, infos = env.reset(seed=0)
        checked = 0
        for infos in _drive(env, 120):
            state = env.race_state
            assert isinstance(state, RaceState) and state.step == env.steps and state.time == env.sim_time
            assert [car.rank for car in state.cars] == env.ranks()
            assert env.core._hints.tolist() == [car.segment for car in state.cars]  # the next step's search hints
            length = env.track.length
            for i, agent in enumerate(env.possible_agents):
                car, info = state.cars[i], infos[agent]
                assert (info["rank"], info["laps_completed"], info["status"]) == (car.rank, car.race.laps,
                                                                                  car.race.status)
                if car.racing and not car.events:  # not put back by the rules after the params were taken
                    assert (info["x"], info["y"], info["projection_distance"]) == (car.point_x, car.point_y, car.s)
                    assert info["progress"] == car.race.lap_progress(length)
                    checked += 1
            for i, car in enumerate(state.cars):
                others = [c for c in state.cars if c.located and c.index != i]
                expected = [((c.s - car.s) % length, c.lateral - car.lateral, c.speed) for c in others]
                assert env.traffic(i) == (expected if car.located else [])
        assert checked > 100
    finally:
        env.close()


def test_a_parked_car_keeps_where_it_stopped():
    env = multirace.parallel_env(num_cars=2, race="head_to_head", laps=1, max_steps=100)
    try:
        env.reset(seed=0)
        for _ in _drive(env, 10):
            pass
        env.forfeit(0, "test")
        stopped = env.race_state.cars[0]
        assert stopped.race.status == "forfeit"
        for infos in _drive(env, 10):
            car = env.race_state.cars[0]
            assert not car.located and not car.racing
            assert (car.point_x, car.point_y, car.s, car.lateral, car.segment) == (
                stopped.point_x, stopped.point_y, stopped.s, stopped.lateral, stopped.segment)
            assert (infos["car_0"]["x"], infos["car_0"]["y"]) == (stopped.point_x, stopped.point_y)
            assert env.core._hints[0] == stopped.segment
            racing = env.race_state.cars[1]  # located alone now, its segment the next step's search hint
            assert racing.racing and racing.s != stopped.s and env.core._hints[1] == racing.segment
            assert env.traffic(0) == [] and env.traffic(1) == []  # the parked car is in nobody's traffic
    finally:
        env.close()


def test_moving_cars_publishes_where_they_now_are():
    env = multirace.parallel_env(num_cars=2, race="head_to_head", laps=1, max_steps=50)
    try:
        env.reset(seed=0)
        env.move_cars({1: (5.0, 0.0)})
        car = env.race_state.cars[1]
        assert car.s == pytest.approx(5.0 + env.car_spec.reported_point_offset, abs=0.05)
        assert env.core._hints[1] == car.segment
        assert env.traffic(0)[0][0] == pytest.approx((car.s - env.race_state.cars[0].s) % env.track.length)
    finally:
        env.close()


def test_nothing_outside_the_core_reads_its_private_attributes():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        name = path.relative_to(PACKAGE).as_posix()
        if name in OWNERS:
            continue
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if PRIVATE_ACCESS.search(line):
                found.append(f"{name}:{number}: {line.strip()}")
    assert not found, "private attributes of the env or its core read from outside:\n" + "\n".join(found)


def test_the_private_access_check_catches_what_it_is_for():
    for line in ("geo = env._geometry[i]", "probe = train_env._env_for(0)", "env._topdown_state = state",
                 "self.env._renderer", "env.core._stopped"):
        assert PRIVATE_ACCESS.search(line), line
    for line in ("env.race_state.cars", "env.core.place_cars({})", "self._env = env"):
        assert not PRIVATE_ACCESS.search(line), line
