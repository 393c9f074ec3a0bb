"""The scripted centre-line driver completes laps; reward params match the geometry."""
import math

import pytest

import multirace

from helpers import drive_expert, place


@pytest.mark.parametrize("track,reverse", [("reinvent_base", False), ("reInvent2019_track", False),
                                           ("reinvent_base", True)])
def test_scripted_driver_laps_without_leaving_the_track(track, reverse):
    env = multirace.parallel_env(track=track, reverse=reverse, num_cars=1, laps=1)
    env.reset(seed=3)
    history = drive_expert(env, speed=1.0)
    last = history[-1]
    assert last["status"] == "finished" and last["laps_completed"] == 1
    assert last["resets"] == 0
    assert all(info["all_wheels_on_track"] for info in history[:-1])
    # one lap at about 1 m/s takes about track length / speed seconds
    assert last["lap_times"][0] == pytest.approx(env.track.length / 1.0, rel=0.25)
    progress = [info["progress"] for info in history[:-1]]
    assert progress == sorted(progress) and progress[-1] > 95


def test_params_at_known_poses():
    env = multirace.parallel_env(track="reinvent_base", num_cars=1)
    env.reset(seed=0)
    track = env.track
    offset = env.car_spec.reported_point_offset
    # centred on the line at s = 5 m, facing along the track: the reported point is 5 m + offset along
    x, y, heading = track.point_at(5.0)
    place(env, 0, x - offset * math.cos(heading), y - offset * math.sin(heading), heading)
    params = env._reward_params([set()] * env.num_cars)[0]
    assert params["x"] == pytest.approx(x, abs=1e-6) and params["y"] == pytest.approx(y, abs=1e-6)
    assert params["distance_from_center"] == pytest.approx(0.0, abs=1e-6)
    assert params["heading"] == pytest.approx(math.degrees(heading), abs=1e-6)
    assert params["projection_distance"] == pytest.approx(5.0, abs=1e-6)
    assert params["progress"] == pytest.approx(100 * 5.0 / track.length, abs=0.01)
    i, j = params["closest_waypoints"]
    assert j == i + 1 and track.cum_s[i] <= 5.0 <= track.cum_s[j]
    assert params["all_wheels_on_track"] and not params["is_offtrack"]
    assert params["track_width"] == pytest.approx(0.762, abs=0.01)
    assert params["track_length"] == pytest.approx(17.709, abs=0.01)
    assert len(params["waypoints"]) == 119 and params["is_reversed"] is False
    # 0.2 m to the left of the centre line
    x, y, _ = track.point_at(5.0, lateral=0.2)
    place(env, 0, x - offset * math.cos(heading), y - offset * math.sin(heading), heading)
    params = env._reward_params([set()] * env.num_cars)[0]
    assert params["distance_from_center"] == pytest.approx(0.2, abs=1e-3)
    assert params["is_left_of_center"] is True
    # half a car off the right border: some wheels off, still not off track
    half = track.project(x, y).right_width
    x, y, _ = track.point_at(5.0, lateral=-half)
    place(env, 0, x - offset * math.cos(heading), y - offset * math.sin(heading), heading)
    params = env._reward_params([set()] * env.num_cars)[0]
    assert not params["all_wheels_on_track"] and not params["is_offtrack"]
    assert params["is_left_of_center"] is False
    # a metre outside: off track
    x, y, _ = track.point_at(5.0, lateral=-1.0)
    place(env, 0, x, y, heading + 0.5)
    params = env._reward_params([set()] * env.num_cars)[0]
    assert params["is_offtrack"] and not params["all_wheels_on_track"]
    assert params["heading"] == pytest.approx(math.degrees(heading + 0.5), abs=1e-6)


def test_all_27_deepracer_params_are_passed():
    from multirace.environment.rewards import PARAM_KEYS

    seen = {}

    def record(params):
        seen.update(params)
        return 1.0

    env = multirace.parallel_env(num_cars=2, obstacles=2, reward_function=record)
    env.reset(seed=0)
    env.step({a: 2 for a in env.agents})
    assert set(PARAM_KEYS) <= set(seen) and len(PARAM_KEYS) == 27
    assert len(seen["objects_location"]) == 3  # two boxes and the other car
    assert isinstance(seen["closest_objects"], list) and len(seen["closest_objects"]) == 2


def test_off_track_resets_on_the_centre_line_with_a_penalty():
    env = multirace.parallel_env(num_cars=1, max_steps=200)
    env.reset(seed=0)
    for _ in range(200):  # hard left at full speed leaves the track
        _, _, _, _, infos = env.step({"car_0": 9})
        if infos["car_0"]["resets"]:
            break
    info = infos["car_0"]
    assert info["is_offtrack"] and "off_track" in info["events"]
    assert info["resets"] == 1 and info["penalty_time"] == pytest.approx(2.0)
    proj = env.track.project(*env.world.poses[0][:2])
    assert abs(proj.lateral) < 0.1  # back on the centre line
    assert env.world.drive_speed[0] == 0.0


def test_object_params_list_boxes_and_cars_on_track_and_point_at_the_nearest():
    env = multirace.parallel_env(track="reinvent_base", num_cars=3, obstacles=1, max_steps=50)
    env.reset(seed=0)
    length = env.track.length
    env.core.place_obstacle(0, 3.0, 0.0)  # on the centre line, 3 m past the start line
    env.forfeit(2, "test: parked")  # a parked car is no longer an object on the track
    _, _, _, _, infos = env.step({"car_0": 2, "car_1": 2})
    first, second, parked = infos["car_0"], infos["car_1"], infos["car_2"]
    # car_0 (on the line) sees the box and car_1 (0.75 m behind it); the parked car_2 is not listed
    assert first["objects_distance"] == [3.0, pytest.approx(second["projection_distance"])]
    assert first["objects_location"] == [pytest.approx(env.track.point_at(3.0)[:2]),
                                         (second["x"], second["y"])]
    assert first["closest_objects"] == [1, 0]  # behind: car_1; ahead: the box
    assert first["object_in_camera"]  # the box, 3 m ahead
    # the box on the centre line, at rest along the track; car_1 as its own params and the world have it
    box_heading = math.degrees(env.track.point_at(3.0)[2])
    assert first["objects_heading"] == [pytest.approx(box_heading), pytest.approx(second["heading"])]
    assert first["objects_speed"] == [0.0, pytest.approx(float(env.world.drive_speed[1]))]
    assert first["objects_distance_from_center"] == [pytest.approx(0.0, abs=1e-9),
                                                     pytest.approx(second["distance_from_center"])]
    assert first["objects_left_of_center"] == [False, second["is_left_of_center"]]
    # car_1 has car_0 just ahead, and the box farther ahead is the nearest behind going round the lap
    assert second["objects_distance"] == [3.0, pytest.approx(first["projection_distance"])]
    assert second["closest_objects"] == [0, 1]
    # the parked car reads where its run ended, the objects on track around it
    assert len(parked["objects_location"]) == 3 and parked["objects_location"][1:] == [
        (first["x"], first["y"]), (second["x"], second["y"])]
    assert 0 < first["projection_distance"] < 3.0 < length - 1.0 < second["projection_distance"]
