"""Actors (`TrainConfig.actors`, the default): the env workers drive their own cars with a copy of the policy
for a whole rollout. What they record must be what that policy did: each stored action's log-probability
and value are the learner's net's on the stored input, with the weights of that rollout. Real worker
processes, real PyBullet envs, real nets.
"""
import math

import numpy as np
import pytest
import torch

from multirace.environment.actions import load_action_space
from multirace.racing.nets import build_net
from multirace.train.actors import Actors, flat_weights, load_flat_weights
from multirace.train.config import make_config
from multirace.train.policy import Policy, forward
from multirace.train.ppo import input_pooling, make_vector_env, observation_shapes, train
from multirace.train.rollout import Rollout


def test_flat_weights_load_into_a_net_of_the_same_architecture():
    torch.manual_seed(0)
    a, b = build_net(value_head=True), build_net(value_head=True)
    load_flat_weights(b, flat_weights(a).numpy())
    for (key, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), key


@pytest.mark.parametrize("action_space", [None, "agents/action_space_racer.json"])
def test_actor_rollouts_record_what_the_policy_did_with_each_rollouts_weights(action_space):
    config = make_config("fast", tracks=("Oval_track",), num_envs=2, cars_per_env=2, action_space=action_space,
                         deepracer_log=False)
    pool = input_pooling(config)
    vec = make_vector_env(config, pool=pool)
    try:
        obs, _ = vec.reset(seeds=[5, 6])
        obs_shape, image_shape, vectors = observation_shapes(obs, pool)
        space = load_action_space(action_space)
        policy = Policy(space)
        torch.manual_seed(1)
        net = build_net(config.network, image_shape, space, value_head=True).eval()
        T, N = 6, 4
        rollout = Rollout(T, N, obs_shape, vectors, space, obs_dtype=np.int16)
        actors = Actors(vec, net, space, rollout, pooled=pool > 1, seed=0)
        for weights in range(2):  # the second rollout with other weights: the actors must take them
            if weights:
                with torch.no_grad():
                    net.head.bias.add_(0.5)
            blocks, infos = actors.run(net)
            x = torch.from_numpy(blocks["obs"].reshape(T * N, *obs_shape).copy())
            actions = torch.from_numpy(blocks["act"].reshape(T * N, *rollout.act_shape).copy())
            with torch.no_grad():
                out, value = forward(net, x, pooled=True)
                logp = policy.log_prob(policy.dist(out), actions)
            assert np.allclose(blocks["logp"].reshape(-1), logp.numpy(), atol=1e-4)
            assert np.allclose(blocks["val"][:T].reshape(-1), value.numpy(), atol=1e-4)
            assert np.isfinite(blocks["val"][T]).all() and np.isfinite(blocks["rew"]).all()
            if space.discrete:
                assert set(np.unique(blocks["act"])) <= set(range(len(space.actions)))
            assert len(infos) == T and all(len(step) == 2 and len(step[0]) == 2 for step in infos)
            assert all("train_done" in info and "time_limit" in info for step in infos for env in step for info in env)
    finally:
        vec.close()


def test_a_seed_gives_the_same_first_rollout_and_training_runs_with_actors(tmp_path):
    def run(seed, name):
        config = make_config("tiny", tracks=("Oval_track",), minutes=10, max_iterations=2, seed=seed,
                             progress=False, deepracer_log=False)
        assert config.actors
        return train(config, tmp_path / f"{name}.pt", log=None)

    first, again, other = run(3, "a"), run(3, "b"), run(4, "c")
    assert first["agent_steps"] == 2 * 128 * 4 and first["iterations"] == 2
    # before any update the rollout depends on the seed alone: its weights, the envs, the actors' draws
    assert first["history"][0]["mean_reward"] == again["history"][0]["mean_reward"]
    assert first["history"][0]["mean_reward"] != other["history"][0]["mean_reward"]
    assert all(math.isfinite(row["policy_loss"]) for row in first["history"])
