"""PettingZoo's own conformance tests, beyond the API and seed tests in test_env_api.py."""
from pathlib import Path

import numpy as np
from PIL import Image
from pettingzoo.test import max_cycles_test, render_test
from pettingzoo.test.save_obs_test import check_save_obs
from pettingzoo.test.save_obs_test import test_save_obs as pettingzoo_save_obs_test
from pettingzoo.utils import save_observation

import multirace
from multirace import multirace_v0


def small_env(**kwargs):
    return multirace_v0.env(num_cars=2, **kwargs)


def test_render_test_human_and_rgb_array():
    render_test(small_env)


def test_rgb_array_frames_show_the_race():
    env = multirace.parallel_env(num_cars=2, render_mode="rgb_array", max_steps=5)
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 10  # a picture, not a blank
    env.close()


def test_max_cycles_test():
    max_cycles_test(multirace_v0)


def test_max_cycles_and_max_steps_are_one_limit():
    env = multirace.parallel_env(num_cars=1, max_cycles=7)
    assert env.max_steps == 7
    try:
        multirace.parallel_env(num_cars=1, max_cycles=7, max_steps=8)
    except ValueError as exc:
        assert "max_cycles" in str(exc)
    else:
        raise AssertionError("conflicting step limits were accepted")


def test_default_grey_observations_save_with_pettingzoos_save_observation(tmp_path, monkeypatch):
    env = small_env()
    env.reset(seed=0)
    assert env.observation_space("car_0").shape == (120, 160)  # one grey channel: (H, W), as PIL takes it
    check_save_obs(env)
    for agent in env.agents:
        save_observation(env=env, agent=agent, all_agents=False, save_dir=str(tmp_path))
    saved = sorted(tmp_path.glob("*/*.png"))
    assert [path.name for path in saved] == ["car_0.png", "car_1.png"]
    for path in saved:
        image = np.asarray(Image.open(path))
        assert image.shape == (120, 160) and image.std() > 5  # the camera's view of the track
    monkeypatch.chdir(tmp_path)  # PettingZoo's whole save test writes to ./saved_observations
    pettingzoo_save_obs_test(env)
    assert len(list(Path("saved_observations").glob("*/car_*.png"))) == 2
    env.close()


def test_module_idiom():
    assert multirace_v0.raw_env is multirace.RaceEnv
    assert multirace_v0.metadata["name"] == "multirace_v0"
    assert set(multirace_v0.metadata["render_modes"]) == {"human", "rgb_array"}
    env = multirace_v0.env(num_cars=1, max_cycles=3)
    env.reset(seed=0)
    assert env.unwrapped.max_steps == 3
