"""DeepRacer reward files run unchanged; bad reward functions stop with a clear error."""
from pathlib import Path

import pytest

import multirace
from multirace.environment.reward_process import load_reward_function
from multirace.environment.rewards import RewardFunctionError

FILES = Path(__file__).parent / "reward_files"


@pytest.mark.parametrize("name", ["centerline", "follow_waypoints", "no_zigzag", "object_avoidance"])
def test_deepracer_reward_files_run_unchanged(name):
    env = multirace.parallel_env(num_cars=2, obstacles=3, race="object_avoidance",
                                 reward_function=FILES / f"{name}.py", max_steps=40)
    env.reset(seed=1)
    total = 0.0
    while env.agents:
        _, rewards, _, _, _ = env.step({a: 7 for a in env.agents})
        total += sum(rewards.values())
    assert total > 0


def test_default_reward_is_the_console_centre_line_example():
    env = multirace.parallel_env(num_cars=1)
    env.reset(seed=0)
    _, rewards, _, _, infos = env.step({"car_0": 7})  # straight on, from the centre line
    assert infos["car_0"]["distance_from_center"] < 0.1 * infos["car_0"]["track_width"]
    assert rewards["car_0"] == 1.0


@pytest.mark.parametrize("name,message", [
    ("bad_raises", "raised at step 1 for car_0: KeyError"),
    ("bad_nan", "returned nan at step 3"),
    ("bad_huge", "returned 1000000.0 at step 1"),
    ("bad_type", "returned 'fast' at step 1"),
])
def test_bad_reward_functions_stop_the_step_naming_file_and_step(name, message):
    path = FILES / f"{name}.py"
    env = multirace.parallel_env(num_cars=1, reward_function=path)
    env.reset(seed=0)
    with pytest.raises(RewardFunctionError) as err:
        for _ in range(5):
            env.step({"car_0": 7})
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)


@pytest.mark.parametrize("name,message", [("bad_syntax", "cannot be loaded: SyntaxError"),
                                          ("bad_missing", "defines no reward_function"),
                                          ("absent", "no such file")])
def test_unloadable_reward_files(name, message):
    with pytest.raises(RewardFunctionError, match=message) as err:
        load_reward_function(FILES / f"{name}.py")
    assert f"{name}.py" in str(err.value)


def test_reward_function_from_file_survives_pickling():
    import pickle

    env = multirace.parallel_env(num_cars=1, reward_function=FILES / "centerline.py")
    clone = pickle.loads(pickle.dumps(env))
    clone.reset(seed=0)
    _, rewards, _, _, _ = clone.step({"car_0": 7})
    assert rewards["car_0"] == 1.0



@pytest.mark.parametrize("value, ok", [("np.float32(0.5)", True), ("np.int64(2)", True), ("7", True),
                                       ("np.bool_(True)", False), ("[1.0]", False), ("None", False),
                                       ("float('nan')", False)])
def test_a_reward_must_be_a_finite_number(tmp_path, value, ok):
    path = tmp_path / "returns.py"
    path.write_text(f"import numpy as np\ndef reward_function(params):\n    return {value}\n")
    env = multirace.parallel_env(num_cars=1, reward_function=path, max_steps=5)
    env.reset(seed=0)
    if ok:
        assert isinstance(env.step({"car_0": 7})[1]["car_0"], float)
    else:
        with pytest.raises(RewardFunctionError, match="returns.py"):
            env.step({"car_0": 7})


def test_named_training_rewards_and_their_weights_in_one_place():
    import dataclasses

    from multirace.environment.rewards import (NAMED_REWARDS, NO_REWARD, RewardWeights, follow_centre_line,
                                               progress_reward)
    from multirace.train.config import TrainConfig, make_config

    assert NAMED_REWARDS["progress"].trainer is progress_reward and NAMED_REWARDS["progress"].env_reward() is NO_REWARD
    assert NAMED_REWARDS["centre"].env_reward() is follow_centre_line
    weights = RewardWeights()
    assert (weights.progress_weight, weights.centre_weight, weights.off_track_penalty) == (1.0, 0.1, 1.0)
    assert {f.name for f in dataclasses.fields(RewardWeights)} <= {f.name for f in dataclasses.fields(TrainConfig)}
    assert RewardWeights.of(make_config("fast", progress_weight=2.0)) == RewardWeights(progress_weight=2.0)
    params = {"track_width": 1.0, "distance_from_center": 0.25, "is_offtrack": False}
    assert progress_reward(params, 0.1, 0.05, weights) == pytest.approx(2.0 + 0.1 * 0.5)
    assert progress_reward({**params, "is_offtrack": True}, 0.0, 0.05, weights) == pytest.approx(0.05 - 1.0)


def test_the_train_env_runs_no_reward_in_the_race_env_when_it_computes_its_own():
    from multirace.environment.rewards import NO_REWARD
    from multirace.train.envs import TrainEnv

    for reward, runs_none in (("progress", True), ("centre", False)):
        env = TrainEnv([("reinvent_base", False)], num_cars=1, camera=(30, 40), reward=reward, progress_weight=2.0)
        env.reset(seed=0)
        assert (env.env.reward_function is NO_REWARD) == runs_none
        train_rewards = []
        for _ in range(15):
            _, rewards, _, _, _ = env.step({"car_0": 7})
            train_rewards.append(rewards["car_0"])
        env.close()
        assert all(r > 0 for r in train_rewards)
        if reward == "centre":  # the env's DeepRacer reward, unchanged
            assert set(train_rewards) <= {1.0, 0.5, 0.1, 1e-3}
    race = multirace.parallel_env(num_cars=1)  # a PettingZoo user's default: the console's centre-line reward
    assert race.reward_function.function.__name__ == "follow_centre_line"
    race.close()
