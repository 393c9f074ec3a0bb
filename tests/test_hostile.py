"""Hostile and careless input: every probe ends in a clear error, a forfeit with a reason, or correct
behaviour; none hangs, none crashes with a raw traceback, nothing reaches what it must not."""
import time

import numpy as np
import pytest

import multirace
from multirace.environment.rewards import RewardFunctionError

# ------------------------------------------------------------------ reward functions
BAD_REWARDS = {
    "loops_forever": ("def reward_function(params):\n    while True:\n        pass\n", "did not return within"),
    "exits": ("import sys\ndef reward_function(params):\n    sys.exit(0)\n", "sys.exit(0)"),
    "huge_int": ("def reward_function(params):\n    return 10**400\n", "too large for a float"),
    "string": ("def reward_function(params):\n    return '0.5'\n", "not a str"),
    "bool": ("def reward_function(params):\n    return True\n", "not a bool"),
    "recursion": ("def reward_function(params):\n    return reward_function(params)\n", "RecursionError"),
}


def _env_with(tmp_path, source, name="reward.py"):
    path = tmp_path / name
    path.write_text(source)
    return multirace.parallel_env(num_cars=1, reward_function=str(path), max_steps=20)


@pytest.mark.parametrize("case", sorted(BAD_REWARDS))
def test_a_bad_reward_function_is_a_clear_error_naming_the_file_and_step(tmp_path, case):
    source, words = BAD_REWARDS[case]
    env = _env_with(tmp_path, source, f"{case}.py")
    env.reset(seed=0)
    start = time.monotonic()
    with pytest.raises(RewardFunctionError) as err:
        env.step({"car_0": 0})
    assert f"{case}.py" in str(err.value) and "step 1" in str(err.value) and words in str(err.value)
    assert time.monotonic() - start < 10


@pytest.mark.parametrize("source, words", [
    ("while True:\n    pass\n", "did not finish within"),
    ("import sys\nsys.exit(3)\n", r"sys\.exit\(3\)"),
])
def test_a_reward_file_that_hangs_or_exits_when_loaded_is_a_clear_error(tmp_path, source, words):
    path = tmp_path / "load.py"
    path.write_text(source + "def reward_function(params):\n    return 1.0\n")
    with pytest.raises(RewardFunctionError, match=words):
        multirace.parallel_env(num_cars=1, reward_function=str(path))


def test_what_a_reward_function_does_to_its_params_reaches_nothing(tmp_path):
    env = _env_with(tmp_path, "def reward_function(params):\n"
                              "    del params['is_offtrack']\n"
                              "    params['x'] = 12345\n"
                              "    params['waypoints'][0] = (999, 999)\n"
                              "    params['closest_waypoints'].append(7)\n"
                              "    return 1.0\n")
    waypoints = list(env.track.waypoints)
    env.reset(seed=0)
    for _ in range(3):
        _, rewards, _, _, infos = env.step({"car_0": 0})
    assert rewards["car_0"] == 1.0
    info = infos["car_0"]
    assert "is_offtrack" in info and info["x"] != 12345 and len(info["closest_waypoints"]) == 2
    assert env.track.waypoints == waypoints and info["waypoints"][0] == waypoints[0]


# ------------------------------------------------------------------ env arguments and actions
CONTINUOUS = {"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.1, "high": 4}},
              "action_space_type": "continuous"}


@pytest.mark.parametrize("action, words", [(-1, "out of range"), (10, "out of range"), (3.7, "integer index"),
                                           ("2", "integer index"), (True, "integer index"), (None, "integer index")])
def test_a_bad_discrete_action_names_the_car_and_step(action, words):
    env = multirace.parallel_env(num_cars=2)
    env.reset(seed=0)
    env.step({"car_0": 1, "car_1": 1})
    with pytest.raises(ValueError, match=f"step 2, car_1: .*{words}"):
        env.step({"car_0": 1, "car_1": action})


@pytest.mark.parametrize("action", [[float("nan"), 1.0], [0.0, float("inf")], [1.0], "fast"])
def test_a_bad_continuous_action_names_the_car_and_step(action):
    env = multirace.parallel_env(num_cars=1, action_space=CONTINUOUS)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="step 1, car_0"):
        env.step({"car_0": action})
    assert np.all(np.isfinite(env.world.poses))  # no NaN reached the world


@pytest.mark.parametrize("kwargs, words", [({"max_steps": -1}, "max_steps"), ({"max_steps": 0}, "max_steps"),
                                           ({"max_steps": 2.5}, "max_steps"), ({"laps": 1.7}, "laps"),
                                           ({"laps": 0}, "laps")])
def test_bad_env_arguments_are_refused_up_front(kwargs, words):
    with pytest.raises(ValueError, match=words):
        multirace.parallel_env(num_cars=1, **kwargs)


def test_cli_refuses_a_zero_step_limit_before_racing(capsys):
    from multirace.cli import main

    assert main(["race", "bot:follow@1.0", "--max-steps", "0"]) == 2
    assert "max_steps" in capsys.readouterr().err
