"""PyBullet is stepped only where bodies can touch; races are the same as with it stepped every step."""
import math

import numpy as np
import pytest

import multirace
from multirace.sim.broadphase import may_touch
from multirace.sim.car import CarSpec
from multirace.sim.world import World

from helpers import drive_expert


def _race(shortcut: bool, seed: int, **config):
    """Race results and the world's state after a seeded race with random actions."""
    env = multirace.parallel_env(**config)
    env.world.contact_shortcut = shortcut
    env.reset(seed=seed)
    rng = np.random.default_rng(11)
    while env.agents:
        env.step({a: int(rng.integers(env.action_space(a).n)) for a in env.agents})
    results = [(r.status, r.lap_times, r.resets, r.penalties, round(r.distance, 6), r.collisions) for r in env.races]
    return results, env.ranks(), env.world.poses.copy(), env.world.bullet_steps, env.steps


def test_a_time_trial_never_steps_pybullet_and_laps_as_with_it():
    laps = {}
    for shortcut in (True, False):
        env = multirace.parallel_env(num_cars=1, laps=1)
        env.world.contact_shortcut = shortcut
        env.reset(seed=3)
        history = drive_expert(env, speed=1.5)
        laps[shortcut] = (history[-1]["lap_times"], env.world.poses.copy(), env.world.bullet_steps, env.steps)
    (times_on, poses_on, bullet_on, steps_on), (times_off, poses_off, bullet_off, steps_off) = laps[True], laps[False]
    assert times_on == times_off and len(times_on) == 1
    np.testing.assert_allclose(poses_on, poses_off, atol=1e-9)  # the same moves, to rounding
    assert bullet_on == 0 and bullet_off == steps_off == steps_on


def test_a_traffic_race_has_the_same_contacts_and_results_as_with_pybullet_every_step():
    """Six cars, 6 incidents in 200 steps (14 contacts before the race rules counted a touch once per incident;
    with a broad phase as tight as PyBullet's own contact range, this race
    parted from the full physics' after its first contact: a body put back while PyBullet holds a pair for it)."""
    config = dict(num_cars=4, bots=("racingline", "follow@1.5"), race="head_to_head", laps=1, max_steps=200, seed=2)
    on, off = _race(True, **config), _race(False, **config)
    results_on, ranks_on, poses_on, bullet_on, steps = on
    results_off, ranks_off, poses_off, _, _ = off
    assert results_on == results_off and ranks_on == ranks_off
    assert sum(len(r[5]) for r in results_on) >= 5  # the race had incidents to compare
    np.testing.assert_allclose(poses_on, poses_off, atol=1e-6)
    assert 0 < bullet_on < steps  # PyBullet ran near the contacts only


@pytest.mark.parametrize("obstacle", [False, True])
def test_a_head_on_contact_within_one_step_is_not_missed(obstacle):
    """Two cars closing at 8 m/s from 0.8 m apart meet within the step (a broad phase without the speeds would
    skip PyBullet, and they would pass through each other); a car 0.5 m from a box meets it within the step (one
    that left the boxes out would let it through)."""
    runs = []
    for shortcut in (True, False):
        world = World(CarSpec(), 2, 1, 60, 15, contact_shortcut=shortcut)
        world.place_car(0, 0.0, 0.0, 0.0, speed=4.0)
        if obstacle:
            world.place_obstacle(0, 0.5, 0.0, 0.0)
            world.place_car(1, 0.0, 5.0, 0.0)  # far away, at rest
        else:
            world.place_obstacle(0, 0.0, 5.0, 0.0)  # far away
            world.place_car(1, 0.8, 0.0, math.pi, speed=4.0)
        commands = np.array([[0.0, 4.0], [0.0, 0.0 if obstacle else 4.0]])
        steps = [world.step(commands) for _ in range(3)]
        runs.append((steps, world.poses.copy()))
    (steps_on, poses_on), (steps_off, poses_off) = runs
    other = ("obstacle", 0) if obstacle else ("car", 1)
    assert {(c.a, c.b) for step in steps_on[:2] for c in step} == {(("car", 0), other)}  # met at once
    assert steps_on == steps_off
    np.testing.assert_allclose(poses_on, poses_off, atol=1e-9)
    assert poses_on[0, 0] < 0.3 and (obstacle or poses_on[1, 0] > poses_on[0, 0])  # neither got through


def test_the_broad_phase_counts_the_closing_speed_the_heading_and_the_pad():
    car, box, step, pad = np.array([0.32, 0.2]), np.array([0.3, 0.3]), 1 / 15, 0.1
    apart = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])  # 0.68 m between the bumpers
    still, closing = np.zeros((2, 2)), np.array([[4.0, 0.0], [-4.0, 0.0]])
    no_boxes = np.zeros((0, 3))
    assert not may_touch(apart, still, no_boxes, car, box, step, pad)
    assert may_touch(apart, closing, no_boxes, car, box, step, pad)
    assert may_touch(np.array([[0.0, 0.0, 0.0], [0.32 + 2 * pad, 0.0, 0.0]]), still, no_boxes, car, box, step, pad)
    turned = np.array([[0.0, 0.0, 0.0], [0.34 + 2 * pad, 0.0, math.pi / 2]])  # across: 0.1 m half size along x
    assert not may_touch(turned, still, no_boxes, car, box, step, pad)
    same_way = np.array([[4.0, 0.0], [4.0, 0.0]])  # one behind the other at the same speed: no closing
    assert not may_touch(apart, same_way, no_boxes, car, box, step, pad)
    box_ahead = np.array([[0.7, 0.0, 0.0]])
    assert not may_touch(apart[:1], still[:1], box_ahead, car, box, step, pad)
    assert may_touch(apart[:1], closing[:1], box_ahead, car, box, step, pad)
