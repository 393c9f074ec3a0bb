"""Race formats and scoring, driven by scripted cars in the real env."""
import math

import pytest

import multirace
from multirace.environment.bots import PurePursuit
from multirace.environment.formats import make_rules
from multirace.environment.rules import CarRace, StepMeasure
from helpers import CONTINUOUS, drive_expert


def _leave_track_repeatedly(env, max_steps=3000):
    """Steer hard left at speed until the episode ends; returns car_0's infos."""
    history = []
    while env.agents and len(history) < max_steps:
        _, _, _, _, infos = env.step({"car_0": [30.0, 2.0]})
        history.append(infos["car_0"])
    return history


def test_reset_rule_allows_three_resets_and_the_fourth_off_track_ends_the_run():
    env = multirace.parallel_env(num_cars=1, race="reset_rule", action_space=CONTINUOUS)
    env.reset(seed=0)
    history = _leave_track_repeatedly(env)
    off_tracks = [k for k, info in enumerate(history) if "off_track" in info["events"]]
    assert len(off_tracks) == 4
    assert [history[k]["resets"] for k in off_tracks] == [1, 2, 3, 3]
    race = env.races[0]
    assert race.status == "out_of_resets" and race.resets == 3 and race.off_tracks == 4
    assert race.finish_time == pytest.approx(len(history) / 15, abs=1e-4)  # records keep 0.1 ms
    assert env.agents == []  # its run is over, and it was the only car


def test_reset_rule_window_ends_a_crawling_car_at_240_seconds():
    # at DeepRacer's slowest command (0.1 m/s) 240 s cover 24 m: not a lap of the 89 m track
    env = multirace.parallel_env(track="penbay_pro", num_cars=1, race="reset_rule", action_space=CONTINUOUS)
    env.reset(seed=0)
    driver = PurePursuit(speed=0.1)
    steps = 0
    while env.agents:
        steer, speed = driver.command(env.track, env.car_spec, env.world.poses[0], env.race_state.cars[0].segment)
        env.step({"car_0": [steer, speed]})
        steps += 1
    race = env.races[0]
    assert race.status == "timed_out" and race.finish_time == pytest.approx(240.0)
    assert steps == 3600 and race.laps == 0


def test_time_trial_penalties_add_their_seconds_to_the_total():
    env = multirace.parallel_env(num_cars=1, laps=1, action_space=CONTINUOUS)
    env.reset(seed=0)
    for _ in range(40):  # leave the track twice with hard steering
        _, _, _, _, infos = env.step({"car_0": [30.0, 2.0]})
        if infos["car_0"]["resets"] == 2:
            break
    assert infos["car_0"]["resets"] == 2 and infos["car_0"]["penalties"] == 2
    history = drive_expert(env, speed=1.0)
    race = env.races[0]
    assert race.status == "finished"
    driven = env.sim_time  # the run ended on this step
    assert race.finish_time == pytest.approx(race.lap_times[0]) == pytest.approx(driven + 4.0, abs=1 / 15)
    assert history[-1]["race_time"] == race.finish_time


def test_best_lap_is_scored_under_the_reset_rule():
    rules = make_rules("reset_rule")
    fast_once = CarRace("a", laps=1, lap_times=[20.0], distance=30.0)
    steady = CarRace("b", laps=3, lap_times=[22.0, 21.0, 21.5], distance=60.0)
    no_lap = CarRace("c", laps=0, distance=15.0)
    order = rules.ranking([steady, no_lap, fast_once], track_length=17.7)
    assert order == [2, 0, 1]  # best lap first, then laps, then progress
    env = multirace.parallel_env(num_cars=1, race="reset_rule", laps=2)
    env.reset(seed=1)
    drive_expert(env, speed=1.0)
    race = env.races[0]
    assert race.laps == 2 and race.best_lap == min(race.lap_times)


@pytest.mark.parametrize("moved", [False, True])
def test_object_avoidance_crash_resets_behind_the_box_in_the_other_lane(moved):
    env = multirace.parallel_env(num_cars=1, race="object_avoidance", action_space=CONTINUOUS)
    env.reset(seed=4)
    track = env.track
    if moved:  # a box put in the other lane, nearer the start: its slot follows it
        s_moved, lane_moved = 4.0, 1 - env.obstacle_slots[0][1]
        env.core.place_obstacle(0, s_moved, track.lane_offset(lane_moved, s_moved))
        assert env.obstacle_slots[0] == (s_moved, lane_moved)
    s_box, lane = env.obstacle_slots[0]
    driver = PurePursuit(speed=1.0, lateral=track.lane_offset(lane, s_box))  # drive in the box's lane
    crash = None
    for _ in range(600):
        steer, speed = driver.command(track, env.car_spec, env.world.poses[0], env.race_state.cars[0].segment)
        _, _, _, _, infos = env.step({"car_0": [steer, speed]})
        if "crashed" in infos["car_0"]["events"]:
            crash = infos["car_0"]
            break
    assert crash is not None, "never reached the box"
    assert crash["penalty_time"] == pytest.approx(5.0) and crash["collisions"] == ["obstacle_0"]
    x, y, yaw = env.world.poses[0]
    offset = env.car_spec.reported_point_offset
    proj = track.project(x + offset * math.cos(yaw), y + offset * math.sin(yaw))
    behind = track.wrap_ds(s_box - proj.s)
    assert behind == pytest.approx(1.0, abs=0.1)
    box_side = track.lane_offset(lane, s_box)
    assert proj.lateral * box_side < 0  # the other lane


def test_head_to_head_finish_order_follows_laps_then_time():
    env = multirace.parallel_env(num_cars=3, race="head_to_head", laps=1, action_space=CONTINUOUS)
    env.reset(seed=2)
    speeds = [1.6, 0.7, 1.1]
    while env.agents:
        actions = {}
        for i, agent in enumerate(env.possible_agents):
            lateral = env.track.lane_offset(i % 2, env.races[i].distance)
            steer, speed = PurePursuit(speed=speeds[i], lateral=lateral).command(
                env.track, env.car_spec, env.world.poses[i], env.race_state.cars[i].segment)
            actions[agent] = [steer, speed]
        env.step(actions)
    ranks = env.ranks()
    finished = [race.status == "finished" for race in env.races]
    assert all(finished)
    times = [race.finish_time for race in env.races]
    assert sorted(range(3), key=lambda i: ranks[i]) == sorted(range(3), key=lambda i: times[i])
    assert ranks[0] == 1 and ranks[1] == 3


def test_unknown_format_and_bad_laps():
    with pytest.raises(ValueError, match="race: unknown format"):
        make_rules("drift")
    with pytest.raises(ValueError, match="laps"):
        make_rules("time_trial", laps=0)


def test_a_car_that_leaves_the_track_right_after_every_reset_ends_its_run_in_a_time_trial():
    # a time trial allows unlimited resets; full lock at 2 m/s leaves the track within a second of each one
    env = multirace.parallel_env(num_cars=1, race="time_trial", action_space=CONTINUOUS)
    env.reset(seed=0)
    history = _leave_track_repeatedly(env)
    race = env.races[0]
    assert race.status == "out_of_resets" and race.reason.startswith("reset loop")
    rules = env.rules
    assert race.off_tracks == race.resets + 1 and race.resets <= rules.reset_loop_count + 1
    assert len(history) < 200  # the run ended long before the step limit
    assert env.agents == []


def test_reset_cap_ends_a_run_with_unlimited_resets():
    rules = make_rules("time_trial", reset_cap=7, reset_loop_count=1000)
    race = CarRace(name="car")
    off = StepMeasure(prev_distance=0.0, dt=1 / 15, track_length=20.0, wheels_on=0, s=1.0)
    rulings = [rules.judge(race, off, sim_time=10.0 * k) for k in range(1, 10)]
    assert [r.reset is not None for r in rulings[:7]] == [True] * 7
    assert rulings[7].end == ("out_of_resets", "reset cap: off track after 7 resets", None)
    assert race.resets == 7 and race.penalties == 7 and race.penalty_time == pytest.approx(14.0)


def test_driving_on_between_off_tracks_is_not_a_reset_loop():
    rules = make_rules("time_trial")
    race = CarRace(name="car")
    off = StepMeasure(prev_distance=0.0, dt=1 / 15, track_length=20.0, wheels_on=0, s=1.0)
    for k in range(20):  # an off-track every 3 s: each long after the reset before it
        ruling = rules.judge(race, off, sim_time=3.0 * (k + 1))
        assert ruling.end is None and ruling.reset == (0.0, None)
    assert race.resets == 20 and race.quick_off_tracks == 0


@pytest.mark.parametrize("race", ["time_trial", "object_avoidance"])
def test_uneventful_steps_are_exactly_those_judge_rules_nothing_on(race):
    """The race core skips `judge` where `uneventful` says so: it must agree with the full rules (`judge` without
    that fast path) on every kind of step."""
    rules, full, length = make_rules(race, laps=2), make_rules(race, laps=2), 20.0
    full.uneventful = lambda *args: False  # judge's own fast path off: every step through the full rules
    steps = [(wheels_on, distance, box) for wheels_on in (0, 2, 4) for distance in (5.0, 19.99, 20.0, 25.0, 40.5)
             for box in (None, (3.0, 1))]
    for wheels_on, distance, box in steps:
        measure = StepMeasure(prev_distance=distance - 0.1, dt=1 / 15, track_length=length, wheels_on=wheels_on,
                              s=distance % length, obstacle_hit=box)
        judged, quick = CarRace("a", distance=distance), CarRace("a", distance=distance)
        ruling = full.judge(judged, measure, sim_time=4.0)
        uneventful = rules.uneventful(quick, wheels_on, measure.s, box is not None, length)
        nothing = not ruling.events and ruling.reset is None and ruling.end is None
        assert uneventful == nothing, (wheels_on, distance, box)
        if uneventful:
            assert quick == judged


@pytest.mark.parametrize("race", ["head_to_head", "time_trial"])
def test_standings_count_penalties_while_racing_and_equal_the_ranking_once_over(race):
    rules, length = make_rules(race, laps=2), 20.0
    leader = CarRace("leader", distance=12.0, penalty_time=10.0)  # ahead on the road with 10 s of penalties
    chaser = CarRace("chaser", distance=10.0)
    assert rules.ranking([leader, chaser], length) == [0, 1]
    assert rules.standings([leader, chaser], length, sim_time=6.0) == [1, 0]  # 10 + 20 s projected against 24 s
    assert rules.standings([CarRace("a", distance=1.0, penalty_time=10.0), CarRace("b", distance=0.5)],
                           length, sim_time=1.0) == [0, 1]  # the first metres: the road order
    for car, finish in ((leader, 30.0), (chaser, 26.0)):
        car.status, car.laps, car.finish_time, car.distance = "finished", 2, finish, 40.0
    assert rules.standings([leader, chaser], length, 30.0) == rules.ranking([leader, chaser], length) == [1, 0]


def test_standings_under_the_reset_rule_are_its_ranking():
    rules = make_rules("reset_rule", laps=3)
    cars = [CarRace("slow", distance=30.0, lap_times=[9.0]), CarRace("fast", distance=25.0, lap_times=[8.0])]
    assert rules.standings(cars, 20.0, 20.0) == rules.ranking(cars, 20.0) == [1, 0]
