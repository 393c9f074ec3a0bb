"""Worker-process vector env: the same observations and rewards as the env stepped in-process."""
import functools
import os

import numpy as np
import pytest

from multirace.environment.race_env import RaceEnv
from multirace.environment.vector import SubprocVectorEnv
from helpers import TorchThreadsEnv


def test_vector_env_matches_the_env_and_auto_resets():
    make = functools.partial(RaceEnv, num_cars=2, obstacles=1, max_steps=30)
    vec = SubprocVectorEnv([make, make], info_keys=("progress", "status"))
    try:
        obs, infos = vec.reset(seeds=[5, 6])
        env = make()
        expected, _ = env.reset(seed=5)
        assert obs.shape == (2, 2, 120, 160) and obs.dtype == np.uint8
        assert np.array_equal(obs[0, 1], expected["car_1"]) and set(infos[0][0]) == {"progress", "status"}
        dones = 0
        for k in range(40):
            actions = np.array([[k % 10, (3 * k) % 10]] * 2)
            obs, rewards, done, truncated, infos = vec.step(actions)
            expected, reward, _, truncs, _ = env.step({"car_0": actions[0, 0], "car_1": actions[0, 1]})
            assert rewards[0, 0] == np.float32(reward["car_0"])
            if done[0]:
                dones += 1
                assert truncated[0] and all(truncs.values())
                assert infos[0][0]["status"] == "not_finished"
                expected, _ = env.reset(seed=1005)  # the worker's next episode seed
            assert np.array_equal(obs[0, 0], expected["car_0"]), k
        assert dones == 1
    finally:
        vec.close()


def test_continuous_actions_reach_the_workers_unchanged():
    space = {"action_space_type": "continuous",
             "action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 2.0}}}
    make = functools.partial(RaceEnv, num_cars=2, action_space=space, max_steps=30)
    vec = SubprocVectorEnv([make], info_keys=("progress",))
    try:
        env = make()
        obs, _ = vec.reset(seeds=[3])
        env.reset(seed=3)
        for k in range(10):
            actions = np.array([[[10.0 - 2 * k, 1.5], [-5.0, 1.0 + k / 10]]], np.float32)
            obs, rewards, _, _, infos = vec.step(actions)
            expected, reward, _, _, info = env.step({"car_0": actions[0, 0], "car_1": actions[0, 1]})
            assert np.array_equal(obs[0, 0], expected["car_0"]) and np.array_equal(obs[0, 1], expected["car_1"]), k
            assert rewards[0, 1] == np.float32(reward["car_1"]) and infos[0][1]["progress"] == info["car_1"]["progress"]
    finally:
        vec.close()


def test_vector_sensors_reach_the_learner_as_the_env_observes_them():
    make = functools.partial(RaceEnv, num_cars=2, sensor=["FRONT_FACING_CAMERA", "SECTOR_LIDAR", "SPEED"],
                             max_steps=30)
    vec = SubprocVectorEnv([make], info_keys=("progress",))
    try:
        env = make()
        obs, _ = vec.reset(seeds=[4])
        env.reset(seed=4)
        assert set(obs) == {"camera", "lidar", "speed"} and obs["speed"].shape == (1, 2, 1)
        for k in range(8):
            actions = np.array([[k % 10, (k + 5) % 10]])
            obs, _, _, _, _ = vec.step(actions)
            expected, _, _, _, _ = env.step({"car_0": actions[0, 0], "car_1": actions[0, 1]})
            for key in ("camera", "lidar", "speed"):
                assert np.array_equal(obs[key][0, 1], expected["car_1"][key]), (k, key)
        assert obs["speed"][0, 0, 0] > 0.1  # the cars drive
    finally:
        vec.close()


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: torch would use one thread anyway")
def test_a_worker_that_loads_torch_computes_on_its_own_core():
    # a teacher's net in a training worker: torch's second thread would spin on the core the other worker needs
    vec = SubprocVectorEnv([functools.partial(TorchThreadsEnv, track="Oval_track", num_cars=1)],
                           info_keys=("torch_threads",))
    try:
        vec.reset(seeds=[0])
        *_, infos = vec.step(np.zeros((1, 1), np.int64))
        assert infos[0][0]["torch_threads"] == 1
    finally:
        vec.close()
