"""The README's "Race rules": who is at fault in a contact, with scripted cars in the real env (real PyBullet).

Two cars on the start straight of re:Invent 2018 (lanes at +-0.19 m, the road 0.38 m each side), each driven
by pure pursuit at a scripted speed and lateral offset; the stewards judge what happens.
"""
import pytest

import multirace
from multirace.environment.bots import PurePursuit
from multirace.environment.rules import INCIDENT_GAP, OVERLAP_SHARE
from helpers import CONTINUOUS

LANE = 0.19  # m, the middle of a lane on reinvent_base


def _race(slots):
    """A head-to-head env with its cars placed at {car: (metres past the line, lateral offset)} side by side
    (`move_cars` would move a car off a spot next to another)."""
    env = multirace.parallel_env(num_cars=len(slots), race="head_to_head", action_space=CONTINUOUS, max_steps=2000)
    env.reset(seed=0)
    env.core.place_cars({i: env.track.point_at(s - env.car_spec.reported_point_offset, lateral)
                         for i, (s, lateral) in slots.items()})
    return env


def _drive(env, plan, steps):
    """Step `env` with plan(k) -> [(speed, lateral target), ...] per car; returns car_0's contact flags per step."""
    touching = []
    for k in range(steps):
        actions = {}
        for i, (speed, lateral) in enumerate(plan(k)):
            steer, command = PurePursuit(speed=speed, lateral=lateral).command(
                env.track, env.car_spec, env.world.poses[i], env.race_state.cars[i].segment)
            actions[f"car_{i}"] = [steer, command]
        _, _, _, _, infos = env.step(actions)
        touching.append(bool(infos["car_0"]["collisions"]))
    return touching


def _one_incident(env, culprit, kind):
    """Both cars recorded one incident of `kind`, `culprit` at fault and paying 5 s; the other pays nothing."""
    victim = 1 - culprit
    for race in env.races:
        assert [c["kind"] for c in race.collisions] == [kind], race.collisions
    assert env.races[culprit].collisions[0]["caused"] and not env.races[victim].collisions[0]["caused"]
    assert env.races[culprit].penalty_time == pytest.approx(env.rules.crash_penalty)
    assert env.races[culprit].penalties == 1 and env.races[victim].penalty_time == 0.0


def test_a_car_that_rear_ends_a_slower_car_is_at_fault():
    env = _race({0: (0.0, 0.0), 1: (1.0, 0.0)})
    touching = _drive(env, lambda k: [(1.5, 0.0), (0.3, 0.0)], 40)
    assert any(touching)
    _one_incident(env, culprit=0, kind="rear_end")


def test_a_car_that_swerves_into_the_car_beside_it_is_at_fault():
    env = _race({0: (0.5, -LANE), 1: (0.5, LANE)})  # level, a lane each
    _drive(env, lambda k: [(1.0, -LANE if k < 10 else LANE), (1.0, LANE)], 40)
    _one_incident(env, culprit=0, kind="side_swipe")


def test_the_car_ahead_that_cuts_across_a_car_with_overlap_is_at_fault():
    env = _race({0: (0.62, -LANE), 1: (0.5, LANE)})  # car 1 alongside by 0.2 m of car 0's 0.32 m
    assert 1 - 0.12 / env.car_spec.length >= OVERLAP_SHARE
    _drive(env, lambda k: [(1.0, -LANE if k < 10 else LANE), (1.0, LANE)], 40)
    _one_incident(env, culprit=0, kind="cut_across")


def test_without_overlap_the_car_ahead_may_take_the_line_and_the_car_behind_must_yield():
    env = _race({0: (0.75, -LANE), 1: (0.0, LANE)})  # car 1 three quarters of a metre back, faster
    _drive(env, lambda k: [(1.0, LANE), (1.5, LANE)], 40)  # car 0 moves across into car 1's lane at once
    _one_incident(env, culprit=1, kind="rear_end")


def test_a_car_pushed_off_track_pays_no_penalty_and_the_pusher_is_at_fault():
    env = _race({0: (0.3, 0.05), 1: (0.3, -0.24)})  # car 1 beside it, near the right edge
    _drive(env, lambda k: [(1.0, 0.05 if k < 8 else -0.8), (1.0, -0.24)], 50)  # car 0 leans on it to the right
    pushed = env.races[1]
    assert pushed.off_tracks == 1 and pushed.resets == 1  # it was put back on the road...
    _one_incident(env, culprit=0, kind="push_off")  # ...without the 2 s off-track penalty


def test_a_contact_that_flickers_counts_once_per_incident():
    env = _race({0: (0.0, 0.0), 1: (0.8, 0.0)})
    touching, back_off = [False], 0

    def plan(k):
        nonlocal back_off
        if touching[-1]:
            back_off = 2  # lift for two steps after each touch, then drive into it again: a flickering contact
        fast = 1.0 if (k < 40 or k >= 60) and back_off == 0 else 0.1  # steps 40-59: fall back for over 0.5 s
        back_off = max(0, back_off - 1)
        return [(fast, 0.0), (0.3, 0.0)]

    for k in range(90):
        touching += _drive(env, lambda _: plan(k), 1)
    steps = [k for k, touch in enumerate(touching) if touch]
    starts = [k for k in steps if not touching[k - 1]]
    incidents = 1 + sum((b - a) * env.dt > INCIDENT_GAP for a, b in zip(steps, steps[1:]))
    assert len(starts) >= 4 and incidents == 2  # many touches, two incidents: the flickers, then a new bump
    assert [c["caused"] for c in env.races[0].collisions] == [True, True]
    assert [c["caused"] for c in env.races[1].collisions] == [False, False]
    assert env.races[0].penalty_time == pytest.approx(2 * env.rules.crash_penalty)
