"""PettingZoo's own conformance tests, beyond the API and seed tests in test_env_api.py."""
import numpy as np
from PIL import Image
from pettingzoo.test import max_cycles_test, render_test
from pettingzoo.test.save_obs_test import check_save_obs

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


def test_observations_pass_pettingzoos_save_check_and_save_as_png(tmp_path):
    # PettingZoo's save_observation hands (H, W, 1) arrays to PIL, which refuses one-channel 3-D arrays,
    # so the image is written here from the same observation, squeezed, after PettingZoo's own check.
    env = small_env()
    env.reset(seed=0)
    check_save_obs(env)  # Box 0-255, (H, W, 1): saveable as an image
    for agent in env.agents:
        Image.fromarray(env.observe(agent)[:, :, 0]).save(tmp_path / f"{agent}.png")
    image = np.asarray(Image.open(tmp_path / "car_0.png"))
    assert image.shape == (120, 160) and image.std() > 5  # the camera's view of the track
    env.close()


def test_module_idiom():
    assert multirace_v0.raw_env is multirace.RaceEnv
    assert multirace_v0.metadata["name"] == "multirace_v0"
    assert set(multirace_v0.metadata["render_modes"]) == {"human", "rgb_array"}
    env = multirace_v0.env(num_cars=1, max_cycles=3)
    env.reset(seed=0)
    assert env.unwrapped.max_steps == 3
