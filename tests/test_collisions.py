"""Cars are solid: they touch, push and report who hit whom; boxes stop them."""
import math

import numpy as np

import multirace
from multirace.sim.car import CarSpec
from multirace.sim.world import World
from helpers import CONTINUOUS, place


def _gap(env, i, j):
    return float(np.hypot(*(env.world.poses[i][:2] - env.world.poses[j][:2])))


def test_car_driven_into_a_car_reports_contact_and_pushes_it():
    env = multirace.parallel_env(num_cars=2, action_space=CONTINUOUS, race="head_to_head", max_steps=200)
    env.reset(seed=0)
    track = env.track
    for i, s in ((0, 1.0), (1, 2.0)):
        place(env, i, *track.point_at(s))
    start_1 = env.world.poses[1][:2].copy()
    crashed, gaps = [], []
    for _ in range(25):  # along the straight
        _, _, _, _, infos = env.step({"car_0": [0.0, 2.0], "car_1": [0.0, 0.1]})
        gaps.append(_gap(env, 0, 1))
        if infos["car_0"]["is_crashed"]:
            crashed.append((infos["car_0"]["collisions"], infos["car_1"]["collisions"], infos["car_1"]["is_crashed"]))
    assert crashed, "no contact reported"
    assert crashed[0] == (["car_1"], ["car_0"], True)
    assert min(gaps) > 0.9 * env.car_spec.length  # never passes through
    pushed = np.hypot(*(env.world.poses[1][:2] - start_1))
    assert pushed > 1.0  # its own 0.1 m/s crawl would take it 0.17 m
    # the rear car ran into the front one: it caused the collision and pays in head-to-head
    assert env.races[0].collisions[0]["caused"] and not env.races[1].collisions[0]["caused"]
    assert env.races[0].penalties == 1 and env.races[0].penalty_time == env.rules.crash_penalty
    assert env.races[1].penalties == 0


def test_car_driven_into_a_box_stops_and_reports_it():
    env = multirace.parallel_env(num_cars=1, obstacles=1, action_space=CONTINUOUS, max_steps=200)
    env.reset(seed=0)
    track = env.track
    place(env, 0, *track.point_at(1.0))
    env.core.place_obstacle(0, 2.5, 0.0)
    bx, by, byaw = track.point_at(2.5)
    hits = []
    for _ in range(40):
        _, _, _, _, infos = env.step({"car_0": [0.0, 1.5]})
        if infos["car_0"]["is_crashed"]:
            hits.append(infos["car_0"]["collisions"])
    assert hits and hits[0] == ["obstacle_0"]
    x, y, yaw = env.world.poses[0]
    ahead = (bx - x) * math.cos(byaw) + (by - y) * math.sin(byaw)
    assert ahead >= 0.5 * (env.car_spec.length + 0.30) - 0.03  # stopped at the box's face
    assert env.races[0].collisions[0] == {"time": env.races[0].collisions[0]["time"], "with": "obstacle_0",
                                          "caused": True, "kind": "obstacle"}


def test_a_car_passing_close_by_a_crawling_car_grazes_it_and_is_the_striker():
    world = World(CarSpec(), 2, 0, 60, 15)
    world.connect()
    world.place_car(0, 0.0, 0.0, 0.3, speed=0.3)  # edging left at a crawl
    world.place_car(1, -0.1, 0.24, 0.0, speed=3.0)  # passing on its left, straight, 3 m/s
    strikers = [c.striker for _ in range(3) for c in world.step(np.array([[0.0, 0.3], [0.0, 3.0]]))]
    assert strikers and set(strikers) == {("car", 1)}  # not the crawler, though it edged toward the passer


def test_a_car_pushed_into_the_car_ahead_by_a_third_causes_nothing():
    world = World(CarSpec(), 3, 0, 60, 15)
    world.connect()
    world.place_car(0, 0.0, 0.0, 0.0, speed=0.3)
    world.place_car(1, -0.36, 0.0, 0.0, speed=0.3)  # queued 4 cm behind car 0 at the same pace
    world.place_car(2, -1.2, 0.0, 0.0, speed=3.0)  # runs into the queue
    contacts = [c for _ in range(8) for c in world.step(np.array([[0.0, 0.3], [0.0, 0.3], [0.0, 3.0]]))]
    pairs = {(c.a[1], c.b[1]) for c in contacts}
    assert pairs == {(0, 1), (1, 2)}  # car 1 is shoved into car 0
    assert {c.striker for c in contacts if (c.a[1], c.b[1]) == (1, 2)} == {("car", 2)}
    assert {c.striker for c in contacts if (c.a[1], c.b[1]) == (0, 1)} == {None}
