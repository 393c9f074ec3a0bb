"""Sensors as DeepRacer's model_metadata declares them: mono or stereo cameras, LIDAR or SECTOR_LIDAR."""
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import multirace
from multirace.sensors.lidar import sector_lidar
from multirace.sensors.suite import SensorSuite, parse_sensors, race_suite


def test_sensor_lists_parse_and_unknown_names_are_errors():
    assert parse_sensors(["FRONT_FACING_CAMERA"]) == SensorSuite()
    assert parse_sensors(["observation"]) == SensorSuite()  # DeepRacer's older name of the camera
    assert parse_sensors(["STEREO_CAMERAS", "SECTOR_LIDAR"]) == SensorSuite("stereo", "sector")
    assert parse_sensors(["LIDAR", "FRONT_FACING_CAMERA"]).names == ["FRONT_FACING_CAMERA", "LIDAR"]
    for bad, words in ((["RADAR"], "unknown sensor 'RADAR'"), (["LIDAR"], "no camera"),
                       (["LIDAR", "SECTOR_LIDAR", "STEREO_CAMERAS"], "more than one"), ([], "non-empty"),
                       ([3], "non-empty")):
        with pytest.raises(ValueError, match=words):
            parse_sensors(bad, "model_metadata.json sensor")
    with pytest.raises(ValueError, match="sensor: unknown sensor"):
        multirace.parallel_env(sensor=["FRONT_FACING_CAMERA", "THERMAL"])
    with pytest.raises(ValueError, match="grey"):
        multirace.parallel_env(sensor=["STEREO_CAMERAS"], grayscale=False)


def test_a_race_provides_what_every_entrant_reads():
    mono, stereo, sector = SensorSuite(), SensorSuite("stereo"), SensorSuite("mono", "sector")
    assert race_suite([mono, mono]) == mono
    assert race_suite([mono, stereo, sector]) == SensorSuite("stereo", "sector")
    assert race_suite([sector, SensorSuite("mono", "lidar")]) == SensorSuite("mono", "lidar")


def test_sector_lidar_is_deepracers_binary_sectors_of_the_scan():
    ranges = np.full(64, 1.0, np.float32)
    ranges[3] = 0.3  # sector 0 (beams 0-7)
    ranges[17] = 0.49  # sector 2
    ranges[40] = 0.51  # sector 5: not near enough
    assert sector_lidar(ranges).tolist() == [1, 0, 1, 0, 0, 0, 0, 0]
    assert sector_lidar(np.stack([ranges, np.ones(64)])).shape == (2, 8)


def test_stereo_pair_sees_a_car_ahead_with_disparity():
    # car_1 (a bot) starts 0.75 m ahead in the other lane; look at it from car_0's two cameras
    env = multirace.parallel_env(num_cars=1, race="head_to_head", bots=("follow@0.1",), sensor=["STEREO_CAMERAS"],
                                 obstacles=0)
    obs, _ = env.reset(seed=0)
    image = obs["car_0"]
    assert image.shape == (120, 160, 2) and image.dtype == np.uint8
    left, right = image[:, :, 0].astype(int), image[:, :, 1].astype(int)
    assert np.abs(left - right).mean() > 1.0  # two viewpoints, not one image twice
    mono = multirace.parallel_env(num_cars=1, race="head_to_head", bots=("follow@0.1",), obstacles=0)
    single = mono.reset(seed=0)[0]["car_0"].astype(int)
    # the centre camera sits between the two: its image lies between theirs
    assert np.abs(single - left).mean() < np.abs(right - left).mean()
    # horizontal disparity: the best shift of the left image onto the right one is to the left (positive)
    errors = {dx: np.abs(left[60:, dx:] - right[60:, :160 - dx]).mean() if dx >= 0 else
              np.abs(left[60:, :dx] - right[60:, -dx:]).mean() for dx in range(-4, 5)}
    assert min(errors, key=errors.get) > 0
    env.close()
    mono.close()


@pytest.mark.parametrize("sensor", [["STEREO_CAMERAS"], ["FRONT_FACING_CAMERA", "SECTOR_LIDAR"],
                                    ["STEREO_CAMERAS", "LIDAR"]])
def test_parallel_api_with_declared_sensors(sensor):
    env = multirace.parallel_env(num_cars=2, sensor=sensor, max_steps=30)
    parallel_api_test(env, num_cycles=40)


def test_lidar_keyword_still_adds_the_lidar():
    env = multirace.parallel_env(num_cars=1, lidar=True)
    assert env.sensors == SensorSuite("mono", "lidar")
    obs, _ = env.reset(seed=0)
    assert obs["car_0"]["lidar"].shape == (64,)
