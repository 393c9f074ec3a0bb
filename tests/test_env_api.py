"""PettingZoo conformance, seeding and determinism of the race env."""
import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test

import multirace


@pytest.mark.parametrize("num_cars", [1, 2, 4])
def test_parallel_api(num_cars):
    env = multirace.parallel_env(num_cars=num_cars, obstacles=2, max_steps=120)
    parallel_api_test(env, num_cycles=150)


def test_parallel_api_with_pybullet_renderer():
    env = multirace.parallel_env(num_cars=2, obstacles=1, max_steps=30, renderer="pybullet")
    parallel_api_test(env, num_cycles=40)


def test_aec_api():
    env = multirace.env(num_cars=2, obstacles=2, max_steps=60)
    api_test(env, num_cycles=80)


def _rollout(seed, steps=200, **config):
    env = multirace.parallel_env(**config)
    obs, infos = env.reset(seed=seed)
    rng = np.random.default_rng(1234)
    trace = [obs]
    for _ in range(steps):
        if not env.agents:
            obs, infos = env.reset()
        actions = {a: int(rng.integers(env.action_space(a).n)) for a in env.agents}
        obs, rewards, terms, truncs, infos = env.step(actions)
        trace.append((obs, rewards, {a: {k: infos[a][k] for k in ("x", "y", "progress", "resets")} for a in infos}))
    env.close()
    return trace


def _equal(a, b):
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b


def test_same_seed_same_actions_identical_over_200_steps():
    config = dict(num_cars=3, obstacles=3, race="object_avoidance", max_steps=500)
    first, second = _rollout(7, **config), _rollout(7, **config)
    assert all(_equal(a, b) for a, b in zip(first, second))
    other = _rollout(8, **config)
    assert not all(_equal(a, b) for a, b in zip(first, other))


def test_env_pickles_before_and_after_use():
    import pickle

    env = multirace.parallel_env(num_cars=2)
    clone = pickle.loads(pickle.dumps(env))
    obs, _ = clone.reset(seed=1)
    env.reset(seed=1)
    again = pickle.loads(pickle.dumps(env))
    obs2, _ = again.reset(seed=1)
    assert np.array_equal(obs["car_0"], obs2["car_0"])


def test_agents_stay_until_the_episode_ends():
    env = multirace.parallel_env(num_cars=2, max_steps=50)
    env.reset(seed=0)
    for step in range(50):
        assert env.agents == ["car_0", "car_1"]
        _, _, terms, truncs, _ = env.step({a: 4 for a in env.agents})  # hard right: leaves the track often
    assert all(truncs.values()) and env.agents == []


def test_bad_config_errors_name_the_keyword():
    with pytest.raises(ValueError, match="num_cars"):
        multirace.parallel_env(num_cars=9)
    with pytest.raises(ValueError, match="race"):
        multirace.parallel_env(race="drag_race")
    with pytest.raises(ValueError, match="renderer"):
        multirace.parallel_env(renderer="vulkan")
    with pytest.raises(ValueError, match="camera"):
        multirace.parallel_env(camera=(5, 5))
    with pytest.raises(ValueError, match="obstacles"):
        multirace.parallel_env(obstacles=7)
    with pytest.raises(ValueError, match="bot"):
        multirace.parallel_env(bots=("flying@2",))


def test_parallel_api_with_randomisation():
    env = multirace.parallel_env(num_cars=2, obstacles=2, max_steps=60, randomize="strong")
    parallel_api_test(env, num_cycles=80)


def test_randomised_images_follow_the_seed():
    def first_frames(seed):
        env = multirace.parallel_env(num_cars=2, randomize="strong", grayscale=False)
        obs, _ = env.reset(seed=seed)
        frames = [obs["car_0"]]
        for _ in range(3):
            obs, *_ = env.step({"car_0": 7, "car_1": 7})
            frames.append(obs["car_0"])
        return np.stack(frames)

    plain = multirace.parallel_env(num_cars=2, grayscale=False).reset(seed=5)[0]["car_0"]
    a, b, c = first_frames(5), first_frames(5), first_frames(6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a[0], plain)


def test_bad_randomisation_config_names_the_key():
    with pytest.raises(ValueError, match="brightnes"):
        multirace.parallel_env(randomize={"brightnes": (0, 10)})
    with pytest.raises(ValueError, match="wild"):
        multirace.parallel_env(randomize="wild")


def test_switching_randomisation_off_restores_the_plain_track():
    from multirace.environment.randomize import Randomization

    plain = multirace.parallel_env(num_cars=1).reset(seed=2)[0]["car_0"]
    env = multirace.parallel_env(num_cars=1, randomize={"texture_tint": 0.5})
    tinted = env.reset(seed=2)[0]["car_0"]
    env.randomization = Randomization.from_config(None)
    again = env.reset(seed=2)[0]["car_0"]
    assert not np.array_equal(tinted, plain) and np.array_equal(again, plain)


def test_a_discrete_action_is_an_index_given_as_an_int_a_numpy_integer_or_a_one_element_array():
    from multirace.environment.actions import load_action_space

    space = load_action_space(None)
    assert space.command(3) == space.command(np.int64(3)) == space.command(np.array([3])) == space.actions[3]
    for bad in (True, np.bool_(False), 2.0, "3", np.array([1, 2])):
        with pytest.raises(ValueError, match="expected an integer index"):
            space.command(bad)
    for bad in (-1, 10, np.int64(10)):
        with pytest.raises(ValueError, match="out of range"):
            space.command(bad)


def test_a_driver_command_is_taken_as_given_inside_the_range_and_refused_if_not_finite():
    from multirace.environment.actions import DRIVER_COMMANDS, Command

    assert DRIVER_COMMANDS.command(Command((12.5, 2.0))) == (12.5, 2.0)
    assert DRIVER_COMMANDS.command(Command((45.0, 9.0))) == (30.0, 4.0)  # outside the range: clipped
    for bad in ((float("nan"), 1.0), (1.0, float("inf")), (-float("inf"), 1.0)):
        with pytest.raises(ValueError, match="finite"):
            DRIVER_COMMANDS.command(Command(bad))
