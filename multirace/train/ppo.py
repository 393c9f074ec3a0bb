"""PPO with shared parameters from the camera (CleanRL style: reads top to bottom).

Every learning car in every env is driven by the same policy and all their
samples train it (parameter sharing / self-play). Envs run in worker processes
(`vector.SubprocVectorEnv`, one per core) and pool their camera images as the
net's first layer pools them (`pool_inputs`: the same outputs, a sixteenth of
the pixels for the tiny net). Each worker drives its own cars with a copy of
the policy for a whole rollout (`actors`, `train/actors.py`); where the
opponent pool or expert labels need it, the learner instead runs inference
on the whole batch of cars at each step on one torch thread. The learner
does the PPO updates on `update_threads` (the workers wait meanwhile, so
their cores are free), in
bfloat16 where the CPU computes it natively (`update_precision`); or,
with `overlap_update`, the update of a rollout runs on a thread while the
workers sample the next one (`Updater`; decoupled PPO corrects for the
one-iteration-old policy that sampled it).

    multirace train --track reinvent_base --minutes 10 --out agent.pt

writes `agent.pt` (an agent file `multirace race` and the league accept),
`agent.png` (learning curve), `agent.train.json` (history, evaluations),
`agent.ckpt/` (a resumable checkpoint and periodic agent snapshots) and `agent.deepracer/` (a
DeepRacer-for-Cloud training folder: sim-traces, model metadata, hyperparameters, training metrics).
"""
from __future__ import annotations

import copy
import functools
import threading
import time

import numpy as np
import torch
from torch import nn

from ..environment.actions import load_action_space
from ..environment.rewards import NAMED_REWARDS
from ..racing.nets import build_net, input_pool
from ..sensors.camera import image_shape_of
from .actors import Actors
from .config import TrainConfig
from .envs import INFO_KEYS, TrainEnv, env_settings
from .policy import Policy, forward
from .robust import RobustKnobs
from .rollout import Rollout, batch_input, expert_actions, finished_episodes, vector_sizes
from .run import TrainingRun
from .threads import update_in_bfloat16, update_threads
from .warmstart import init_lineage, init_settings, load_init_agent


def init_continuous_head(net, space) -> None:
    """Start a continuous policy in the middle of the action box with a quarter-range spread."""
    low, high = np.array(space.low), np.array(space.high)
    with torch.no_grad():
        net.head.weight.mul_(0.01)
        net.head.bias.copy_(torch.tensor([*((low + high) / 2), *np.log(np.maximum((high - low) / 4, 1e-3))],
                                         dtype=torch.float32))


class RewardScale:
    """Divides rewards by a running standard deviation of the discounted return (as gym's NormalizeReward).

    Keeps value targets near 1 instead of the hundreds a 2 m/s progress reward adds up to, so the value
    loss does not swamp the policy's gradient in the trunk the two heads share.
    """

    def __init__(self, n: int, gamma: float):
        self.gamma, self.returns = gamma, np.zeros(n)
        self.count, self.mean, self.var = 1e-4, 0.0, 1.0

    def __call__(self, rewards: np.ndarray, dones: np.ndarray) -> np.ndarray:
        self.returns = self.returns * self.gamma + rewards
        batch_mean, batch_var, k = self.returns.mean(), self.returns.var(), len(self.returns)
        total = self.count + k
        delta = batch_mean - self.mean
        self.var = (self.var * self.count + batch_var * k + delta ** 2 * self.count * k / total) / total
        self.mean, self.count = self.mean + delta * k / total, total
        self.returns[dones] = 0.0
        return rewards / np.sqrt(self.var + 1e-8)

    def state(self) -> dict:
        return {"count": self.count, "mean": self.mean, "var": self.var}

    def load(self, state: dict) -> None:
        self.count, self.mean, self.var = state["count"], state["mean"], state["var"]


# ------------------------------------------------------------------- runs
def training_runs(config: TrainConfig) -> list:
    """(track, reverse) pairs to train on: named tracks x directions, plus generated tracks."""
    runs = [(t, r) for t in config.tracks for r in config.directions()]
    if config.procedural_tracks:
        from ..sim.trackgen import generate_track

        for k in range(int(config.procedural_tracks)):
            rows = generate_track(seed=10_000 + config.seed * 1000 + k).rows
            runs += [(rows, r) for r in config.directions()]
    if not runs:
        raise ValueError("tracks: need at least one track")
    return runs


def check_reward_file(config: TrainConfig, runs) -> None:
    """Load and call a reward .py file once here, so a bad file fails with its message, not a dead worker."""
    if config.reward is None or config.reward in NAMED_REWARDS:
        return
    from ..environment.rewards import RewardFunctionError

    probe = TrainEnv(runs[:1], num_cars=1, action_space=config.action_space, reward=config.reward,
                     camera=config.camera, episode_steps=3)
    try:
        probe.reset(seed=0)
        while probe.env.agents:  # the whole (3-step) episode: every step calls the reward function
            probe.step({"car_0": probe.env.actions.space.sample()})
    except RewardFunctionError as exc:
        raise ValueError(f"--reward: {exc}") from None
    finally:
        probe.close()


def make_vector_env(config: TrainConfig, shared=None, cars=None, bots=None, pool: int = 1):
    """The training envs in worker processes (`pool` > 1: they send camera images pooled, `TrainEnv`)."""
    from ..environment.vector import SPIN_WAIT, SubprocVectorEnv

    runs = training_runs(config)
    check_reward_file(config, runs)
    settings = env_settings(config)
    settings.update(num_cars=cars or config.cars_per_env, bots=tuple(config.bots if bots is None else bots),
                    pool=pool)
    factories = [functools.partial(TrainEnv, runs, shared=shared, worker=w, **settings) for w in range(config.num_envs)]
    spin = config.worker_spin_wait
    if spin is None:
        spin = 0.0 if config.overlap_update else SPIN_WAIT
    return SubprocVectorEnv(factories, info_keys=INFO_KEYS, spin_wait=spin)


def observation_shapes(obs, pool: int) -> tuple:
    """(one car's observation shape as sent, the camera's (H, W, C) as the net records it, {key: values per
    car} of the sensors beside the camera) of the vector env's first observations, their images pooled by
    `pool`."""
    obs_shape = (obs["camera"] if isinstance(obs, dict) else obs).shape[2:]
    height, width, channels = image_shape_of(obs_shape)
    return obs_shape, (height * pool, width * pool, channels), vector_sizes(obs)


def input_pooling(config: TrainConfig) -> int:
    """How far the workers may pool camera images for the net (`nets.input_pool`; 1: not at all)."""
    k = input_pool(config.network)
    height, width = config.camera
    if not config.pool_inputs or config.opponent_pool or height % k or width % k:
        return 1
    return k


def cpu_seconds(vec) -> float | None:
    """CPU seconds the learner (every thread) and the env workers have used so far (None: not known here)."""
    workers = vec.worker_cpu_seconds()
    return None if workers is None else round(time.process_time() + workers, 3)


# ------------------------------------------------------------------ the rollout
def collect_rollout(vec, net, policy: Policy, rollout: Rollout, robust: RobustKnobs, learner_mask,
                    reward_scale, config: TrainConfig, deepracer=None, pooled: bool = False):
    """T steps of every env into `rollout`, inference batched over all cars (the pool's opponents drive
    theirs), each learning car's steps logged to the `deepracer` folder if given. Returns the value of the
    last observations, the env's own reward summed over the rollout (`rollout.rew` may be scaled and
    bootstrapped) and the training episodes that ended. `pooled`: the workers pool the images."""
    E, A = config.num_envs, config.cars_per_env
    N = E * A
    net.eval()
    env_reward, episodes = 0.0, []
    for t in range(rollout.steps):
        x = rollout.net_input(rollout.next_obs)
        rollout.store_input(t, x)
        rollout.done[t] = rollout.next_done
        with torch.no_grad():
            out, value = forward(net, x, pooled)
            dist = policy.dist(out)
            action = dist.sample()
            rollout.logp[t] = policy.log_prob(dist, action)
        rollout.act[t], rollout.val[t], rollout.expert[t] = action, value, rollout.next_expert
        actions = action.numpy().reshape(E, A, *rollout.act_shape)
        commands = robust.opponent_commands(rollout.next_obs, learner_mask)  # the pool's cars: their own commands
        rollout.learn[t] = learner_mask.reshape(N)
        rollout.next_obs, reward, env_done, _, infos = vec.step(actions, commands)
        if config.expert_coef:
            rollout.next_expert = expert_actions(infos, policy.discrete)
        env_reward += record_step(rollout, t, infos, reward, env_done, value, learner_mask, reward_scale, robust,
                                  config.gamma, deepracer, episodes)
    with torch.no_grad():
        next_value = forward(net, rollout.net_input(rollout.next_obs), pooled)[1]
    return next_value, env_reward, episodes


def record_step(rollout: Rollout, t: int, infos, reward, env_done, value, learner_mask, reward_scale, robust,
                gamma: float, deepracer, episodes: list) -> float:
    """What step t of every car returned, into `rollout`: its rewards (scaled, and bootstrapped with `value`
    where the step limit cut an episode), the dones entering step t+1, the training episodes that ended (added
    to `episodes`), the sim-trace rows. Returns the env's own reward summed over the cars."""
    N = rollout.cars
    if deepracer is not None:
        deepracer.write_step(infos, reward, learner_mask)
    done = np.array([info["train_done"] for env_infos in infos for info in env_infos]).reshape(N)
    step_reward = reward.reshape(N).astype(np.float64)
    total = float(step_reward.sum())
    if reward_scale is not None:
        step_reward = reward_scale(step_reward, done)
    rollout.rew[t] = torch.from_numpy(step_reward.astype(np.float32))
    # an episode cut by the step limit (not by an off-track or a crash) would have gone on:
    # bootstrap it, with this state's value standing in for the unseen next state's
    cut = np.array([info["time_limit"] for env_infos in infos for info in env_infos]).reshape(N)
    rollout.rew[t] += gamma * value * torch.from_numpy(cut.astype(np.float32))
    rollout.next_done = torch.from_numpy(done.astype(np.float32))
    episodes += finished_episodes(infos, learner_mask)
    robust.after_step(infos, reward, env_done)
    return total


def collect_actor_rollout(actors, net, rollout: Rollout, robust: RobustKnobs, learner_mask, reward_scale,
                          config: TrainConfig, deepracer=None):
    """`collect_rollout` with the workers' actors driving their cars (`TrainConfig.actors`): the same returns."""
    T, N = rollout.steps, rollout.cars
    blocks, infos = actors.run(net)
    rollout.obs[:] = blocks["obs"].reshape(rollout.obs.shape)
    for key, values in rollout.vectors.items():
        values[:] = blocks["vector:" + key].reshape(values.shape)
    rollout.act[:] = torch.from_numpy(blocks["act"].reshape(rollout.act.shape))
    rollout.logp[:] = torch.from_numpy(blocks["logp"].reshape(T, N))
    values = torch.from_numpy(blocks["val"].reshape(T + 1, N).copy())
    rollout.val[:] = values[:T]
    rollout.learn[:] = learner_mask.reshape(N)
    env_reward, episodes = 0.0, []
    for t in range(T):
        rollout.done[t] = rollout.next_done
        env_reward += record_step(rollout, t, infos[t], blocks["rew"][t], blocks["env_done"][t], values[t],
                                  learner_mask, reward_scale, robust, config.gamma, deepracer, episodes)
    return values[T], env_reward, episodes


def decayed(rate: float, fraction: float) -> float:
    """`rate` decayed linearly over a budget of which `fraction` is spent, to a floor of 10 %."""
    return rate * max(0.1, 1.0 - fraction)


def anneal_learning_rate(optimiser, config: TrainConfig, fraction: float) -> None:
    """Linear decay of the learning rate over the time budget, to a floor of 10 %."""
    if config.anneal_lr:
        for group in optimiser.param_groups:
            group["lr"] = decayed(config.lr, fraction)


# ------------------------------------------------------------------ the PPO update
def beyond_box(out: torch.Tensor, space) -> torch.Tensor:
    """How far a continuous policy's means (`out[:, :2]`) lie beyond its action box: the mean over the batch of
    the squared distance past the box's edges, in half-ranges of the box (0 for means inside it)."""
    low = torch.as_tensor(space.low, dtype=out.dtype)
    high = torch.as_tensor(space.high, dtype=out.dtype)
    half_range = ((high - low) / 2).clamp(min=1e-3)
    excess = torch.relu((out[:, :2] - (low + high) / 2).abs() / half_range - 1.0)
    return excess.square().sum(-1).mean()


def ppo_update(net, policy: Policy, optimiser, batch: dict, config: TrainConfig, space,
               value_only: bool, pooled: bool = False, generator=None) -> dict:
    """Clipped PPO epochs over minibatches of the learner's samples (plus the expert loss and the loss on means
    beyond the action box (`bound_coef`) where asked);
    `value_only` fits the value head alone (a fresh head under an --init policy); `pooled`: the images
    are pooled (`nets.pool_image`); `generator`: the minibatches' random source (torch's own if None).
    Returns the statistics."""
    net.train()
    size = len(batch["obs"])
    mb = min(config.minibatch_size, size)
    bfloat16 = update_in_bfloat16(config.update_precision)
    clip_fracs, approx_kl, pg_loss, v_loss, entropy, expert_loss = [], 0.0, 0.0, 0.0, 0.0, 0.0
    for epoch in range(config.epochs):
        order = torch.randperm(size, generator=generator)
        for start in range(0, size - mb + 1, mb):
            idx = order[start:start + mb]
            out, value = forward(net, batch_input(net, batch, idx), pooled, bfloat16)
            dist = policy.dist(out)
            logp = policy.log_prob(dist, batch["act"][idx])
            log_ratio = logp - batch["logp"][idx]
            ratio = log_ratio.exp()
            with torch.no_grad():
                approx_kl = ((ratio - 1) - log_ratio).mean().item()
                clip_fracs.append(((ratio - 1.0).abs() > config.clip).float().mean().item())
            adv = batch["adv"][idx]
            if config.norm_adv:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg = torch.max(-adv * ratio, -adv * torch.clamp(ratio, 1 - config.clip, 1 + config.clip))
            pg = (pg * batch["weight"][idx]).mean() if "weight" in batch else pg.mean()
            old_value, ret = batch["val"][idx], batch["ret"][idx]
            if config.clip_value:
                v_clipped = old_value + torch.clamp(value - old_value, -config.clip, config.clip)
                vl = 0.5 * torch.max((value - ret) ** 2, (v_clipped - ret) ** 2).mean()
            else:
                vl = 0.5 * ((value - ret) ** 2).mean()
            ent = policy.entropy(dist).mean()
            loss = pg - config.ent_coef * ent + config.vf_coef * vl
            if config.bound_coef and not space.discrete:  # pull means past the box's edge back to it
                loss = loss + config.bound_coef * beyond_box(out, space)
            if config.expert_coef:  # imitation of the expert where it labelled the image
                labels = batch["expert"][idx]
                known = labels >= 0 if space.discrete else ~torch.isnan(labels).any(-1)
                safe = labels.clamp(min=0) if space.discrete else torch.nan_to_num(labels)
                nll = -(policy.log_prob(dist, safe) * known).sum() / known.sum().clamp(min=1)
                loss = loss + config.expert_coef * nll
                expert_loss = nll.item()
            optimiser.zero_grad()
            if value_only:
                loss = config.vf_coef * vl
            loss.backward()
            if value_only:
                for name, param in net.named_parameters():
                    if not name.startswith("value_head."):
                        param.grad = None
            nn.utils.clip_grad_norm_(net.parameters(), config.max_grad_norm)
            optimiser.step()
            pg_loss, v_loss, entropy = pg.item(), vl.item(), ent.item()
        if config.target_kl is not None and approx_kl > config.target_kl:
            break
    return {"policy_loss": round(pg_loss, 4), "value_loss": round(v_loss, 4), "entropy": round(entropy, 4),
            "expert_loss": round(expert_loss, 4), "approx_kl": round(approx_kl, 5),
            "clip_frac": round(float(np.mean(clip_fracs)) if clip_fracs else 0.0, 4)}


# ------------------------------------------------------------------ the update, now or beside sampling
BEHAVIOUR_WEIGHT_CAP = 1.0  # truncation of the current / behaviour probability ratio (IMPALA's rho-bar)


def recentre(net, policy: Policy, batch: dict, pooled: bool, chunk: int) -> None:
    """Decoupled PPO (Hilton et al., 2022) for a batch an older policy sampled: the clip is centred on the
    current policy (`batch["logp"]` becomes its log-probabilities) and each sample's policy loss is weighted
    by the current / behaviour probability ratio, truncated at `BEHAVIOUR_WEIGHT_CAP` (`batch["weight"]`)."""
    parts = []
    with torch.no_grad():
        for start in range(0, len(batch["obs"]), chunk):
            x = batch_input(net, batch, slice(start, start + chunk))
            parts.append(policy.log_prob(policy.dist(forward(net, x, pooled)[0]), batch["act"][start:start + chunk]))
    logp = torch.cat(parts) if parts else batch["logp"]
    batch["weight"] = (logp - batch["logp"]).exp().clamp(max=BEHAVIOUR_WEIGHT_CAP)
    batch["logp"] = logp

class Updater:
    """Runs `ppo_update` on the learner's batches: at once, or with `overlap_update` on a thread while the
    next rollout is sampled. `behaviour` is the net rollouts are sampled with: `net` itself, or under
    overlap a copy that takes the new weights when an update finishes (so a rollout is sampled with the
    policy from before the previous rollout's update: one iteration stale, which `recentre` corrects
    for). The overlapped update runs on one torch thread and draws its minibatches from its own
    generator, so a seed still gives the same run."""

    def __init__(self, net, policy: Policy, optimiser, config: TrainConfig, space, pooled: bool):
        self.net, self.policy, self.optimiser, self.config, self.space = net, policy, optimiser, config, space
        self.pooled = pooled
        self.overlap = bool(config.overlap_update)
        self.behaviour = copy.deepcopy(net) if self.overlap else net
        self.generator = torch.Generator().manual_seed(config.seed + 1) if self.overlap else None
        self.thread, self.stats, self.error, self.seconds = None, {}, None, 0.0
        self.pending = None  # with overlap: the last batch submitted, trained on while the next rollout is sampled

    def _run(self, batch: dict, fraction: float, value_only: bool) -> None:
        t = time.perf_counter()
        try:
            anneal_learning_rate(self.optimiser, self.config, fraction)
            if self.overlap:  # sampled by the policy from before the last update
                recentre(self.net, self.policy, batch, self.pooled, self.config.minibatch_size)
            self.stats = ppo_update(self.net, self.policy, self.optimiser, batch, self.config, self.space,
                                    value_only=value_only, pooled=self.pooled,
                                    generator=self.generator)
        except BaseException as exc:  # raised again in the main thread by `finish`
            self.error = exc
        self.seconds = time.perf_counter() - t

    def start(self, batch: dict, fraction: float, value_only: bool, background: bool | None = None) -> None:
        """Train on `batch` (the learning rate annealed to `fraction` of the budget), on the thread if overlapping."""
        self.stats, self.seconds = {}, 0.0
        if self.overlap if background is None else background:
            self.thread = threading.Thread(target=self._run, args=(batch, fraction, value_only), daemon=True)
            self.thread.start()
            return
        if not self.overlap:
            torch.set_num_threads(update_threads(self.config.update_threads))  # one thread on a busy machine
        self._run(batch, fraction, value_only)
        torch.set_num_threads(int(self.config.threads))

    def finish(self) -> dict:
        """Wait for the running update; the new weights go to `behaviour`; its statistics ({} if none ran)."""
        if self.thread is not None:
            self.thread.join()
            self.thread = None
        if self.error is not None:
            error, self.error = self.error, None
            raise error
        if self.overlap and self.stats:
            self.behaviour.load_state_dict(self.net.state_dict())
        stats, self.stats = self.stats, {}
        return stats

    def begin(self) -> None:
        """With overlap: start the update of the last rollout submitted, on the thread."""
        if self.pending is not None:
            self.start(*self.pending)
            self.pending = None

    def submit(self, batch: dict, fraction: float, value_only: bool) -> dict:
        """A rollout's batch: trained on now, or with overlap kept for `begin`, once the running update is
        done. Returns the statistics of the update that ran ({} in an overlapped first iteration)."""
        if self.overlap:
            self.pending = (batch, fraction, value_only)
        else:
            self.start(batch, fraction, value_only)
        return self.finish()

    def train_now(self) -> float:
        """Run the pending update (if any) here and wait for it; its seconds."""
        if self.pending is None:
            return 0.0
        self.start(*self.pending, background=False)
        self.pending = None
        self.finish()
        return self.seconds

    def stop(self) -> None:
        """Wait for a running update and drop it (the run is ending on an error)."""
        if self.thread is not None:
            self.thread.join()
            self.thread = None


# ------------------------------------------------------------------ train
def train(config: TrainConfig, out, init=None, resume=None, command=None, log=print) -> dict:
    """Train with PPO until the time budget is spent; write the agent file `out`; return a summary."""
    # --- 1. the run (clock, checkpoints, evaluations, outputs), seeding, the action space
    run = TrainingRun(config, out, command, log)
    checkpoint = run.load_checkpoint(resume)
    if init:
        run.lineage = init_lineage(init)
        for key, value in init_settings(init).items():
            setattr(config, key, value)
    torch.set_num_threads(int(config.threads))
    torch.manual_seed(config.seed)
    space = load_action_space(config.action_space)

    # --- 2. envs in worker processes, with the robust options' knobs
    robust = RobustKnobs(config, seed=config.seed)
    pool = input_pooling(config)
    vec = make_vector_env(config, robust.shared, pool=pool)
    E, A, T, N = config.num_envs, config.cars_per_env, config.rollout_steps, config.num_envs * config.cars_per_env
    obs, reset_infos = vec.reset(seeds=[config.seed * 100_000 + e for e in range(E)])
    obs_shape, image_shape, vectors = observation_shapes(obs, pool)

    # --- 3. the net (policy + value head), optimiser, reward scale, opponent pool, rollout storage
    net = build_net(config.network, image_shape, space, value_head=True, vector_inputs=vectors)
    if not space.discrete:
        init_continuous_head(net, space)
    if init:
        load_init_agent(init, net)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr, eps=1e-5)
    reward_scale = RewardScale(N, config.gamma) if config.norm_reward else None
    run.restore(checkpoint, net, optimiser, reward_scale)
    robust.start_pool(space, image_shape, np.random.default_rng(config.seed), vectors)
    rollout = Rollout(T, N, obs_shape, vectors, space, obs_dtype=np.int16 if pool > 1 else np.uint8)
    rollout.start(obs, expert_actions(reset_infos, space.discrete))
    deepracer = run.deepracer_folder(net, space, image_shape)  # out.deepracer/ (deepracer_log), else None
    updater = Updater(net, Policy(space), optimiser, config, space, pooled=pool > 1)
    # the workers drive their own cars, unless the pool's opponents or the expert's labels need the learner each step
    use_actors = config.actors and not config.opponent_pool and not config.expert_coef
    actors = Actors(vec, net, space, rollout, pool > 1, config.seed) if use_actors else None
    try:
        start_iteration = run.iteration
        while run.keep_going(start_iteration):
            fraction = run.fraction()
            learner_mask = robust.before_iteration(fraction, E, A)
            updater.begin()  # with overlap_update: the last rollout's update, on its thread beside this rollout

            # --- 4. rollout: T steps of every env, batched inference over all cars
            t0 = time.perf_counter()
            if deepracer is not None:
                deepracer.start_iteration(run.iteration)
            if actors is not None:
                next_value, env_reward, episodes = collect_actor_rollout(actors, updater.behaviour, rollout, robust,
                                                                         learner_mask, reward_scale, config, deepracer)
            else:
                next_value, env_reward, episodes = collect_rollout(vec, updater.behaviour, updater.policy, rollout,
                                                                   robust, learner_mask, reward_scale, config,
                                                                   deepracer, pool > 1)
            samples = int(rollout.learn.sum())
            run.agent_steps += samples
            t1 = time.perf_counter()
            run.sample_time += t1 - t0

            # --- 5. advantages (GAE), the PPO update: now (the workers wait), or beside the next rollout
            batch = rollout.learner_batch(*rollout.advantages(next_value, config.gamma, config.gae_lambda))
            run.update_time += time.perf_counter() - t1
            value_only = bool(init) and run.iteration - start_iteration < config.value_warmup and checkpoint is None
            stats = updater.submit(batch, fraction, value_only)
            run.update_time += updater.seconds
            run.iteration += 1

            # --- 6. log, snapshots, checkpoints, evaluations
            extra = {**robust.after_iteration(episodes), "cpu_seconds": cpu_seconds(vec)}
            run.record(episodes, stats, env_reward / (T * N), samples, time.perf_counter() - t0, extra)
            robust.snapshot(net, run.elapsed(), run.iteration)
            if run.checkpoint_and_evaluate(net, optimiser, reward_scale, space, image_shape):
                break
        run.update_time += updater.train_now()  # every rollout is trained on: the last one's update now
    except (EOFError, ConnectionError) as exc:
        raise ValueError(f"an env worker process stopped ({type(exc).__name__}); its error is printed above "
                         "(for example a reward function that raised or returned a bad value)") from None
    finally:
        updater.stop()
        run.stop_progress()
        if deepracer is not None:
            deepracer.close()
        vec.close()

    # --- 7. outputs: agent file (the best evaluated policy), checkpoint, curve, history
    return run.finish(net, optimiser, reward_scale, space, image_shape)
