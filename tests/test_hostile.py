"""Hostile and careless input: every probe ends in a clear error, a forfeit with a reason, or correct
behaviour; none hangs, none crashes with a raw traceback, nothing reaches what it must not."""
import time

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
