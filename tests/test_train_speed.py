"""The faster PPO loop: images pooled in the workers give the net's own outputs, and the overlapped update
(the next rollout sampled while the last one trains) keeps every sample, learns finite losses and writes
an agent file that loads as before. Real nets, real PyBullet envs, a real worker process.
"""
import math

import numpy as np
import pytest
import torch

from multirace.racing.agentfile import load_agent
from multirace.racing.nets import SHALLOW, SMALL, TINY, build_net, input_pool, pool_image
from multirace.train.config import make_config
from multirace.train.envs import TrainEnv
from multirace.train.ppo import Policy, Updater, input_pooling, train


@pytest.mark.parametrize("network,shape,lidar", [(TINY, (120, 160, 1), 0), (SMALL, (120, 160, 1), 0),
                                                 (TINY, (120, 160, 2), 0), (TINY, (120, 160, 3), 0),
                                                 (TINY, (120, 160, 1), 64)])
def test_pooled_images_give_the_nets_own_outputs(network, shape, lidar):
    torch.manual_seed(0)
    net = build_net(network, shape, None, value_head=True, lidar_samples=lidar)
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (6, *(shape[:2] if shape[2] == 1 else shape)), dtype=np.uint8)
    k = input_pool(network)
    pooled = np.stack([pool_image(image, k) for image in images])
    assert pooled.shape[1:3] == (shape[0] // k, shape[1] // k) and pooled.dtype == np.int16
    full_in, pooled_in = torch.from_numpy(images), torch.from_numpy(pooled)
    if lidar:
        ranges = torch.rand(6, lidar)
        full_in, pooled_in = {"camera": full_in, "lidar": ranges}, {"camera": pooled_in, "lidar": ranges}
    with torch.no_grad():
        out, value = net.forward_all(full_in)
        out_pooled, value_pooled = net.forward_all(pooled_in, pooled=True)
    assert torch.allclose(out, out_pooled, atol=1e-5) and torch.allclose(value, value_pooled, atol=1e-5)


def test_input_pool_follows_the_networks_first_layer_and_stays_off_for_the_opponent_pool():
    assert (input_pool(TINY), input_pool(SMALL), input_pool(SHALLOW)) == (4, 2, 1)
    assert input_pooling(make_config("fast")) == 4
    assert input_pooling(make_config("fast", pool_inputs=False)) == 1
    assert input_pooling(make_config("fast", opponent_pool=True)) == 1  # the pool's agents read full images
    assert input_pooling(make_config("fast", camera=(120, 162))) == 1  # not whole 4x4 blocks


def test_a_pooling_train_env_sends_the_block_sums_of_the_same_images():
    envs = [TrainEnv([("Oval_track", False)], num_cars=2, pool=k) for k in (1, 4)]
    try:
        obs = [env.reset(seed=3)[0] for env in envs]
        for _ in range(3):
            obs = [env.step({"car_0": 3, "car_1": 5})[0] for env in envs]
        for car in ("car_0", "car_1"):
            assert obs[1][car].shape == (30, 40) and obs[1][car].dtype == np.int16
            assert np.array_equal(obs[1][car], pool_image(obs[0][car], 4))
    finally:
        for env in envs:
            env.close()


@pytest.mark.parametrize("overlap", [True, False])
def test_overlapped_and_waiting_updates_train_on_every_sample(overlap, tmp_path):
    out = tmp_path / "agent.pt"
    config = make_config("tiny", tracks=("Oval_track",), minutes=10, max_iterations=3, seed=4, progress=False,
                         deepracer_log=False, overlap_update=overlap)
    summary = train(config, out, log=None)
    history = summary["history"]
    assert summary["iterations"] == len(history) == 3
    assert summary["agent_steps"] == 3 * config.rollout_steps * config.cars_per_env
    # the overlapped loop's first iteration has no update yet (its rollout trains during the second)
    trained = history[1:] if overlap else history
    assert all(math.isfinite(h["policy_loss"]) and math.isfinite(h["value_loss"]) for h in trained)
    assert ("policy_loss" in history[0]) is not overlap
    agent = load_agent(out, step_budget=None)  # the file is the full-resolution net, as before
    assert agent.metadata["image"] == {"height": 120, "width": 160, "channels": 1}
    assert agent.metadata["neural_network"] == TINY


def test_an_update_that_fails_on_its_thread_raises_in_the_learner():
    config = make_config("tiny", overlap_update=True)
    net = build_net(TINY, (120, 160, 1), None, value_head=True)
    from multirace.environment.actions import load_action_space

    space = load_action_space(None)
    updater = Updater(net, Policy(space), torch.optim.Adam(net.parameters()), config, space,
                      pooled=False)
    assert updater.behaviour is not net
    updater.start({"obs": torch.zeros(4, 120, 160, dtype=torch.uint8)}, 0.0, False)  # no actions: a KeyError
    with pytest.raises(KeyError):
        updater.finish()


@pytest.mark.slow
def test_training_throughput_reports_rate_shares_and_cpu_cost():
    from multirace.train.throughput import training_throughput

    figures = training_throughput(seconds=600, max_iterations=3)  # the iteration budget ends it
    assert figures["iterations"] == 3 and figures["num_envs"] == 2 and figures["network"] == TINY
    assert figures["agent_steps_per_s"] > 0 and figures["cpu_us_per_agent_step"] > 0
    assert 0 < figures["sampling_share"] < 1 and 0 < figures["update_share"] < 1


def test_recentre_moves_the_clip_to_the_current_policy_and_weights_samples_by_the_behaviours_odds():
    from multirace.environment.actions import load_action_space
    from multirace.train.ppo import BEHAVIOUR_WEIGHT_CAP, recentre

    torch.manual_seed(1)
    space = load_action_space(None)
    policy, net = Policy(space), build_net(TINY, (120, 160, 1), None, value_head=True)
    obs = torch.randint(0, 4081, (10, 30, 40), dtype=torch.int16)
    act = torch.randint(0, 10, (10,))
    with torch.no_grad():
        current = policy.log_prob(policy.dist(net.forward_all(obs, pooled=True)[0]), act)
    behaviour = current + torch.linspace(-1.0, 1.0, 10)  # an older policy: likelier and less likely choices
    batch = {"obs": obs, "act": act, "logp": behaviour.clone(), "lidar": torch.zeros(10, 0)}
    recentre(net, policy, batch, pooled=True, chunk=4)  # chunks: 4, 4, 2
    assert torch.allclose(batch["logp"], current, atol=1e-6)
    assert torch.allclose(batch["weight"], (current - behaviour).exp().clamp(max=BEHAVIOUR_WEIGHT_CAP), atol=1e-6)
    assert batch["weight"].max() <= BEHAVIOUR_WEIGHT_CAP and batch["weight"].min() < 1.0


def _update_once(precision: str) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """One `ppo_update` of a fresh seeded net on a fixed synthetic batch: (stats, the parameters' change,
    the parameters' dtypes as one tensor of itemsizes)."""
    from multirace.environment.actions import load_action_space
    from multirace.train.ppo import ppo_update

    torch.manual_seed(2)
    space = load_action_space(None)
    policy, net = Policy(space), build_net(TINY, (120, 160, 1), None, value_head=True)
    before = torch.cat([p.detach().flatten().clone() for p in net.parameters()])
    generator = torch.Generator().manual_seed(5)
    obs = torch.randint(0, 4081, (256, 30, 40), dtype=torch.int16, generator=generator)
    act = torch.randint(0, 10, (256,), generator=generator)
    with torch.no_grad():
        logp = policy.log_prob(policy.dist(net.forward_all(obs, pooled=True)[0]), act)
    batch = {"obs": obs, "act": act, "logp": logp, "adv": torch.randn(256, generator=generator),
             "val": torch.zeros(256), "ret": torch.rand(256, generator=generator) * 5}
    config = make_config("fast", minibatch_size=128, epochs=2, update_precision=precision)
    stats = ppo_update(net, policy, torch.optim.Adam(net.parameters(), lr=1e-3), batch, config, space,
                       value_only=False, pooled=True, generator=torch.Generator().manual_seed(7))
    after = torch.cat([p.detach().flatten() for p in net.parameters()])
    return stats, after - before, torch.tensor([p.dtype.itemsize for p in net.parameters()])


def test_a_bfloat16_update_moves_the_weights_as_the_float32_one_and_keeps_them_float32():
    stats16, step16, sizes16 = _update_once("bfloat16")
    stats32, step32, _ = _update_once("float32")
    assert all(math.isfinite(v) for v in stats16.values())
    assert (sizes16 == 4).all()  # mixed precision: the weights (and the agent file) stay float32
    assert not torch.equal(step16, step32)  # the setting took effect
    cosine = torch.nn.functional.cosine_similarity(step16, step32, dim=0)
    assert cosine > 0.9, f"bfloat16 update direction differs from float32's: cosine {cosine:.3f}"
    assert abs(stats16["value_loss"] - stats32["value_loss"]) < 0.05 * stats32["value_loss"]


def test_update_precision_auto_follows_the_cpu_and_a_bad_value_is_refused():
    from multirace.train.threads import update_in_bfloat16

    assert update_in_bfloat16("auto") == bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    assert update_in_bfloat16("bfloat16") and not update_in_bfloat16("float32")
    with pytest.raises(ValueError, match="update_precision.*float16"):
        make_config("fast", update_precision="float16")


def test_the_throughput_preset_keeps_fasts_batch_and_overlaps_the_update():
    fast, throughput = make_config("fast"), make_config("throughput")
    assert throughput.overlap_update and not fast.overlap_update
    assert (throughput.cars_per_env, throughput.rollout_steps) == (8, 128)
    assert throughput.batch_size == fast.batch_size == 2048
    assert input_pooling(throughput) == input_pooling(fast) == 4
