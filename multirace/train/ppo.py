"""PPO with shared parameters from the camera (CleanRL style: reads top to bottom).

Every learning car in every env is driven by the same policy and all their
samples train it (parameter sharing / self-play). Envs run in worker processes
(`vector.SubprocVectorEnv`, one per core); the learner runs inference on the
whole batch of cars at once on one torch thread, then does the PPO updates on
`update_threads` (the workers wait meanwhile, so their cores are free).

    multirace train --track reinvent_base --minutes 10 --out agent.pt

writes `agent.pt` (an agent file `multirace race` and the league accept),
`agent.png` (learning curve), `agent.train.json` (history, evaluations) and
`agent.ckpt/` (a resumable checkpoint and periodic agent snapshots).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, Normal

from ..environment.actions import load_action_space
from ..racing.agentfile import lidar_samples, make_metadata, read_payload, parse_metadata, save_agent
from ..racing.nets import CameraNet, add_lidar_inputs, build_net
from .config import TrainConfig
from .envs import INFO_KEYS, TrainEnv, env_settings


# ------------------------------------------------------------------ policy
class Policy:
    """Turns the net's outputs into a distribution over the action space (discrete or Gaussian)."""

    def __init__(self, space):
        self.space = space
        self.discrete = space.discrete

    def dist(self, out: torch.Tensor):
        if self.discrete:
            return Categorical(logits=out)
        return Normal(out[:, :2], torch.exp(torch.clamp(out[:, 2:], -5.0, 2.0)))

    def log_prob(self, dist, actions):
        lp = dist.log_prob(actions)
        return lp if self.discrete else lp.sum(-1)

    def entropy(self, dist):
        ent = dist.entropy()
        return ent if self.discrete else ent.sum(-1)


def init_continuous_head(net, space) -> None:
    """Start a continuous policy in the middle of the action box with a quarter-range spread."""
    low, high = np.array(space.low), np.array(space.high)
    with torch.no_grad():
        net.head.weight.mul_(0.01)
        net.head.bias.copy_(torch.tensor([*((low + high) / 2), *np.log(np.maximum((high - low) / 4, 1e-3))],
                                         dtype=torch.float32))


def load_init_agent(path, net) -> None:
    """Initialise the policy from an agent file (e.g. a DAgger imitation agent); the value head stays new.

    A camera-only agent can start a LIDAR net: its LIDAR inputs start with zero weight (`add_lidar_inputs`).
    """
    payload = read_payload(path)
    state = {k: v for k, v in payload["state_dict"].items() if not k.startswith("value_head.")}
    if net.lidar is not None and not any(k.startswith("lidar.") for k in state):
        camera_only = CameraNet(net.network, net.image_shape, net.num_outputs, value_head=True)
        load_init_agent(path, camera_only)
        net.load_state_dict(add_lidar_inputs(camera_only, net.lidar_samples).state_dict())
        return
    missing, unexpected = net.load_state_dict(state, strict=False)
    if unexpected or any(not k.startswith("value_head.") for k in missing):
        raise ValueError(f"--init {path}: weights do not match the network ({missing or unexpected})")


def init_settings(path) -> dict:
    """The network, image and action space an --init agent file was built with (and the LIDAR, if it reads one)."""
    metadata = parse_metadata(read_payload(path), str(path))
    image = metadata["image"]
    settings = {"network": metadata["neural_network"], "action_space": {k: metadata[k] for k in
                ("action_space", "action_space_type")}, "camera": (image["height"], image["width"])}
    if lidar_samples(metadata):  # a camera-only file leaves lidar as configured (it can start a LIDAR net)
        settings["lidar"] = True
    return settings


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
    if config.reward in ("progress", "centre", None):
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


def make_vector_env(config: TrainConfig, shared=None, cars=None, bots=None):
    from ..environment.vector import SubprocVectorEnv

    runs = training_runs(config)
    check_reward_file(config, runs)
    settings = env_settings(config)
    settings.update(num_cars=cars or config.cars_per_env, bots=tuple(config.bots if bots is None else bots))
    factories = [functools.partial(TrainEnv, runs, shared=shared, worker=w, **settings) for w in range(config.num_envs)]
    return SubprocVectorEnv(factories, info_keys=INFO_KEYS)


# ------------------------------------------------------------- evaluation
def evaluate_time_trial(agent_path, track: str, laps: int = 3, seed: int = 0, reverse: bool = False,
                        bots=()) -> dict:
    """Race the agent file alone (as `multirace race FILE --format time_trial`); its result row.

    With `bots`: a head-to-head race against them instead, in which each collision the agent caused
    counts like an off-track reset in the row's "resets" (so the best-policy choice avoids both).
    """
    from ..racing.agentfile import AgentController
    from ..racing.runner import RaceConfig, run_race

    if bots:
        from .evaluate import race_agent

        row = race_agent(agent_path, track, reverse=reverse, laps=laps, seed=seed, bots=tuple(bots),
                         race="head_to_head", step_budget=5.0)
        return {**row, "resets": row["resets"] + row["collisions_caused"]}
    # a generous step budget: the evaluation measures driving, not how busy the machine is
    result = run_race([AgentController(agent_path, step_budget=5.0)], RaceConfig(track=track, reverse=reverse, race="time_trial",
                                                               laps=laps, seed=seed))
    return result["cars"][0]


def save_agent_file(path, net, space, config: TrainConfig, obs_shape, training: dict) -> Path:
    name = Path(path).stem
    metadata = make_metadata(space, net.network, name, obs_shape, training_algorithm="clipped_ppo",
                             lidar=net.lidar is not None, training=training)
    return save_agent(path, net, metadata)


def plot_history(history: list, evals: list, path) -> None:
    """Learning curve: episode return and laps per episode against agent-steps, evaluations marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    steps = [h["agent_steps"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    axes[0].plot(steps, [h["return"] for h in history], color="tab:blue")
    axes[0].set_ylabel("mean episode return")
    axes[1].plot(steps, [h["laps_per_episode"] for h in history], color="tab:green", label="laps per episode")
    for e in evals:  # evaluations: green = every lap with no off-track, orange = every lap, grey = not
        finished = e["laps"] >= e["target"]
        colour = ("tab:green" if not e["resets"] else "tab:orange") if finished else "0.75"
        axes[1].axvline(e["agent_steps"], color=colour, lw=1.0)
    axes[1].set_ylabel("laps per training episode")
    axes[1].set_title("evaluations: green clean 3/3, orange 3/3 with off-tracks, grey not", fontsize=8)
    for ax in axes:
        ax.set_xlabel("agent-steps")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def eval_score(e: dict) -> tuple:
    """Order of evaluations: more laps, then fewer off-tracks, then faster."""
    return (e["laps"], -e["resets"], -(e["total_time"] or 1e9))


# ------------------------------------------------------------------ train
def train(config: TrainConfig, out, init=None, resume=None, command=None, log=print) -> dict:
    """Train with PPO until the time budget is spent; write the agent file `out`; return a summary."""
    started = time.perf_counter()
    out = Path(out)
    ckpt_dir = out.with_name(out.stem + ".ckpt")
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    budget = 60.0 * float(config.minutes)

    # --- 1. seeding, threads, resumed state
    torch.set_num_threads(int(config.threads))
    checkpoint = None
    if resume:
        checkpoint = torch.load(resume, map_location="cpu", weights_only=True)
        saved = json.loads(checkpoint["config"])
        for key in ("network", "action_space", "camera", "lidar"):
            value = saved.get(key, getattr(config, key))  # checkpoints from before the LIDAR lack "lidar"
            setattr(config, key, tuple(value) if key == "camera" else value)
    if init:
        for key, value in init_settings(init).items():
            setattr(config, key, value)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    space = load_action_space(config.action_space)
    policy = Policy(space)

    # --- 2. robust options: curriculum scale, nature's weights, opponent pool (all optional)
    from .selfplay import OpponentPool
    from .nature import Nature, curriculum_scale

    shared = None
    nature = Nature(temperature=config.nature_temperature, seed=config.seed) if config.nature else None
    if config.curriculum or nature is not None:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        shared = {"scale": ctx.Value("d", 0.0 if config.curriculum else 1.0)}
        if nature is not None:
            shared["nature"] = ctx.Array("d", nature.weights().tolist())

    # --- 3. envs in worker processes
    vec = make_vector_env(config, shared)
    E, A = config.num_envs, config.cars_per_env
    obs, reset_infos = vec.reset(seeds=[config.seed * 100_000 + e for e in range(E)])
    obs_shape = (obs["camera"] if config.lidar else obs).shape[2:]
    R = obs["lidar"].shape[-1] if config.lidar else 0  # LIDAR ranges per car
    N = E * A

    def batch(obs):
        """(E, A, ...) observations as the net's input for N cars: images, or images and LIDAR ranges."""
        if not R:
            return torch.from_numpy(obs.reshape(N, *obs_shape))
        return {"camera": torch.from_numpy(obs["camera"].reshape(N, *obs_shape)),
                "lidar": torch.from_numpy(obs["lidar"].reshape(N, R))}

    # --- 4. the net (policy + value head), optimiser
    net = build_net(config.network, obs_shape, space, value_head=True, lidar_samples=R)
    if not space.discrete:
        init_continuous_head(net, space)
    if init:
        load_init_agent(init, net)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr, eps=1e-5)
    agent_steps, iteration, history, evals, spent = 0, 0, [], [], 0.0
    if checkpoint is not None:
        net.load_state_dict(checkpoint["net"])
        optimiser.load_state_dict(checkpoint["optimiser"])
        agent_steps, iteration = int(checkpoint["agent_steps"]), int(checkpoint["iteration"])
        history, evals = json.loads(checkpoint["history"]), json.loads(checkpoint["evals"])
        spent = float(checkpoint["elapsed"])
    reward_scale = RewardScale(E * A, config.gamma) if config.norm_reward else None
    saved_scale = json.loads(checkpoint.get("reward_scale", "null")) if checkpoint is not None else None
    if reward_scale is not None and saved_scale:
        reward_scale.load(saved_scale)
    pool = OpponentPool(config, space, obs_shape, rng, lidar_samples=R) if config.opponent_pool else None
    learner_mask = np.ones((E, A), bool)  # which cars' samples train the learner (pool opponents: False)

    # --- 5. rollout storage (T, N): uint8 images, LIDAR ranges, actions, log-probs, rewards, dones, values
    T = config.rollout_steps
    buf_obs = np.zeros((T, N, *obs_shape), np.uint8)
    buf_lidar = np.zeros((T, N, R), np.float32)
    act_shape = () if space.discrete else (2,)
    buf_act = torch.zeros((T, N, *act_shape), dtype=torch.long if space.discrete else torch.float32)
    buf_logp = torch.zeros((T, N))
    buf_rew = torch.zeros((T, N))
    buf_done = torch.zeros((T, N))
    buf_val = torch.zeros((T, N))
    buf_expert = torch.zeros((T, N, *act_shape), dtype=buf_act.dtype)  # expert_coef: the pass driver's actions

    def expert_actions(infos) -> torch.Tensor:
        """The scripted pass driver's action for every car's next observation (-1 / NaN: none)."""
        rows = [info.get("expert_action", -1 if space.discrete else [math.nan, math.nan])
                for env_infos in infos for info in env_infos]
        return torch.tensor(rows, dtype=buf_act.dtype)

    expert_now = expert_actions(reset_infos)
    buf_learn = np.zeros((T, N), bool)
    next_done = torch.zeros(N)

    episodes: list = []  # finished per-car training episodes of this iteration
    first_success = first_clean = None  # first evaluation finishing every lap (and with no off-track)
    for e in evals:
        if e["laps"] >= e["target"] and first_success is None:
            first_success = e["elapsed"]
        if e["laps"] >= e["target"] and e["resets"] == 0 and first_clean is None:
            first_clean = e["elapsed"]
    last_ckpt = last_eval = time.perf_counter()
    best = None  # (score, weights, evaluation) of the best evaluated policy so far
    sample_time = update_time = 0.0
    progress = None
    if config.progress:
        from tqdm import tqdm

        progress = tqdm(total=int(budget), unit="s", desc="ppo", dynamic_ncols=True,
                        bar_format="{desc} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} s {postfix}")

    def elapsed() -> float:
        return time.perf_counter() - started

    def snapshot_agent(path, note=None):
        training = {"method": "ppo", "agent_steps": agent_steps, "iterations": iteration,
                    "tracks": [str(t) for t in config.tracks], "reverse": config.reverse, "seed": config.seed,
                    "wall_seconds": round(spent + elapsed(), 1), "reward": str(config.reward),
                    "robust": bool(config.robust)}
        if command:
            training["command"] = command
        if note:
            training.update(note)
        net.eval()
        return save_agent_file(path, net, space, config, obs_shape, training)

    def save_checkpoint():
        torch.save({"net": net.state_dict(), "optimiser": optimiser.state_dict(), "agent_steps": agent_steps,
                    "reward_scale": json.dumps(reward_scale.state() if reward_scale is not None else None),
                    "iteration": iteration, "history": json.dumps(history), "evals": json.dumps(evals),
                    "elapsed": spent + elapsed(), "config": json.dumps(config.to_dict())},
                   ckpt_dir / "checkpoint.tmp")
        (ckpt_dir / "checkpoint.tmp").replace(ckpt_dir / "checkpoint.pt")

    try:
        start_iteration = iteration
        while iteration == start_iteration or elapsed() < budget:  # at least one iteration per run
            # --- 6. robust knobs for this iteration
            frac = min(1.0, elapsed() / budget)
            if shared is not None and config.curriculum:
                shared["scale"].value = curriculum_scale(frac)
            if nature is not None:
                shared["nature"][:] = nature.weights().tolist()
            if pool is not None:
                learner_mask = pool.assign(E, A)

            # --- 7. rollout: T steps of every env, batched inference over all cars
            t0 = time.perf_counter()
            net.eval()
            env_reward = 0.0  # the env's own rewards this rollout (buf_rew may be scaled and bootstrapped)
            for t in range(T):
                x = batch(obs)
                buf_obs[t] = x["camera"] if R else x
                if R:
                    buf_lidar[t] = x["lidar"]
                buf_done[t] = next_done
                with torch.no_grad():
                    out_, value = net.forward_all(x)
                    dist = policy.dist(out_)
                    action = dist.sample()
                    buf_logp[t] = policy.log_prob(dist, action)
                buf_act[t], buf_val[t], buf_expert[t] = action, value, expert_now
                actions = action.numpy().reshape(E, A, *act_shape)
                if pool is not None:
                    actions = pool.override(actions, obs, learner_mask)
                buf_learn[t] = learner_mask.reshape(N)
                obs, reward, env_done, _, infos = vec.step(actions)
                if config.expert_coef:
                    expert_now = expert_actions(infos)
                done = np.array([[infos[e][a]["train_done"] for a in range(A)] for e in range(E)]).reshape(N)
                step_reward = reward.reshape(N).astype(np.float64)
                env_reward += float(step_reward.sum())
                if reward_scale is not None:
                    step_reward = reward_scale(step_reward, done)
                buf_rew[t] = torch.from_numpy(step_reward.astype(np.float32))
                # an episode cut by the step limit (not by an off-track or a crash) would have gone on:
                # bootstrap it, with this state's value standing in for the unseen next state's
                cut = np.array([[infos[e][a]["time_limit"] for a in range(A)] for e in range(E)]).reshape(N)
                buf_rew[t] += config.gamma * value * torch.from_numpy(cut.astype(np.float32))
                next_done = torch.from_numpy(done.astype(np.float32))
                for e in range(E):
                    for a in range(A):
                        info = infos[e][a]
                        if info["train_done"]:
                            episodes.append({"return": info["ep_return"], "laps": info["ep_laps"],
                                             "length": info["ep_length"], "learner": bool(learner_mask[e, a]),
                                             "caused": info.get("ep_caused", 0),
                                             "perturbation": info["perturbation"]})
                        if pool is not None:
                            pool.observe(e, a, info, float(reward[e, a]))
                if env_done.any() and pool is not None:
                    pool.episode_end(env_done)
            agent_steps += int(buf_learn.sum())
            with torch.no_grad():
                next_value = net.forward_all(batch(obs))[1]
            sample_time += time.perf_counter() - t0

            # --- 8. advantages (GAE); a done at step t+1 means the episode ended with step t
            t1 = time.perf_counter()
            advantages = torch.zeros((T, N))
            last = torch.zeros(N)
            for t in reversed(range(T)):
                nonterminal = 1.0 - (next_done if t == T - 1 else buf_done[t + 1])
                value_next = next_value if t == T - 1 else buf_val[t + 1]
                delta = buf_rew[t] + config.gamma * value_next * nonterminal - buf_val[t]
                last = delta + config.gamma * config.gae_lambda * nonterminal * last
                advantages[t] = last
            returns = advantages + buf_val

            # --- 9. PPO update on the learner's samples (the workers are idle: the learner may use their cores)
            torch.set_num_threads(int(config.update_threads))
            keep = torch.from_numpy(buf_learn.reshape(-1))
            b_obs = torch.from_numpy(buf_obs.reshape(T * N, *obs_shape))[keep]
            b_lidar = torch.from_numpy(buf_lidar.reshape(T * N, R))[keep]
            b_act = buf_act.reshape(T * N, *act_shape)[keep]
            b_logp, b_adv = buf_logp.reshape(-1)[keep], advantages.reshape(-1)[keep]
            b_ret, b_val = returns.reshape(-1)[keep], buf_val.reshape(-1)[keep]
            b_expert = buf_expert.reshape(T * N, *act_shape)[keep]
            if config.anneal_lr:
                for group in optimiser.param_groups:
                    group["lr"] = config.lr * max(0.1, 1.0 - frac)
            net.train()
            warmup = bool(init) and iteration - start_iteration < config.value_warmup and checkpoint is None
            size = len(b_obs)
            mb = min(config.minibatch_size, size)
            clip_fracs, approx_kl, pg_loss, v_loss, entropy, expert_loss = [], 0.0, 0.0, 0.0, 0.0, 0.0
            for epoch in range(config.epochs):
                order = torch.randperm(size)
                for start in range(0, size - mb + 1, mb):
                    idx = order[start:start + mb]
                    out_, value = net.forward_all({"camera": b_obs[idx], "lidar": b_lidar[idx]} if R else b_obs[idx])
                    dist = policy.dist(out_)
                    logp = policy.log_prob(dist, b_act[idx])
                    log_ratio = logp - b_logp[idx]
                    ratio = log_ratio.exp()
                    with torch.no_grad():
                        approx_kl = ((ratio - 1) - log_ratio).mean().item()
                        clip_fracs.append(((ratio - 1.0).abs() > config.clip).float().mean().item())
                    adv = b_adv[idx]
                    if config.norm_adv:
                        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                    pg = torch.max(-adv * ratio, -adv * torch.clamp(ratio, 1 - config.clip, 1 + config.clip)).mean()
                    if config.clip_value:
                        v_clipped = b_val[idx] + torch.clamp(value - b_val[idx], -config.clip, config.clip)
                        vl = 0.5 * torch.max((value - b_ret[idx]) ** 2, (v_clipped - b_ret[idx]) ** 2).mean()
                    else:
                        vl = 0.5 * ((value - b_ret[idx]) ** 2).mean()
                    ent = policy.entropy(dist).mean()
                    loss = pg - config.ent_coef * ent + config.vf_coef * vl
                    if config.expert_coef:  # imitation of the pass driver where it labelled the image
                        labels = b_expert[idx]
                        known = labels >= 0 if space.discrete else ~torch.isnan(labels).any(-1)
                        safe = labels.clamp(min=0) if space.discrete else torch.nan_to_num(labels)
                        nll = -(policy.log_prob(dist, safe) * known).sum() / known.sum().clamp(min=1)
                        loss = loss + config.expert_coef * nll
                        expert_loss = nll.item()
                    optimiser.zero_grad()
                    if warmup:  # a fresh value head under an --init policy: fit values first, policy frozen
                        loss = config.vf_coef * vl
                    loss.backward()
                    if warmup:
                        for name, param in net.named_parameters():
                            if not name.startswith("value_head."):
                                param.grad = None
                    nn.utils.clip_grad_norm_(net.parameters(), config.max_grad_norm)
                    optimiser.step()
                    pg_loss, v_loss, entropy = pg.item(), vl.item(), ent.item()
                if config.target_kl is not None and approx_kl > config.target_kl:
                    break
            torch.set_num_threads(int(config.threads))
            update_time += time.perf_counter() - t1
            iteration += 1

            # --- 10. log
            mine = [ep for ep in episodes if ep["learner"]]
            if nature is not None:
                for ep in mine:
                    if ep["perturbation"] >= 0:
                        nature.update(ep["perturbation"], ep["laps"])
            row = {"iteration": iteration, "agent_steps": agent_steps, "elapsed": round(spent + elapsed(), 1),
                   "episodes": len(mine),
                   "return": float(np.mean([ep["return"] for ep in mine])) if mine else
                   (history[-1]["return"] if history else 0.0),
                   "laps_per_episode": float(np.mean([ep["laps"] for ep in mine])) if mine else
                   (history[-1]["laps_per_episode"] if history else 0.0),
                   "lap_completion": float(np.mean([ep["laps"] >= 1.0 for ep in mine])) if mine else 0.0,
                   "caused_per_lap": (float(sum(ep["caused"] for ep in mine) / max(sum(ep["laps"] for ep in mine),
                                                                                    0.25)) if mine else 0.0),
                   "mean_reward": env_reward / (T * N), "policy_loss": round(pg_loss, 4),
                   "value_loss": round(v_loss, 4), "entropy": round(entropy, 4),
                   "expert_loss": round(expert_loss, 4), "approx_kl": round(approx_kl, 5),
                   "clip_frac": round(float(np.mean(clip_fracs)) if clip_fracs else 0.0, 4),
                   "steps_per_s": round(agent_steps / max(spent + elapsed(), 1e-9), 1) if not spent else
                   round(int(buf_learn.sum()) / max(time.perf_counter() - t0, 1e-9), 1)}
            if pool is not None:
                row["pool"] = pool.summary()
            if nature is not None:
                row["nature"] = nature.summary()
            history.append(row)
            episodes = []
            if progress is not None:
                progress.n = min(int(elapsed()), progress.total)
                progress.set_postfix_str(f"it {iteration} ret {row['return']:.1f} laps/ep "
                                         f"{row['laps_per_episode']:.2f} lap% {100 * row['lap_completion']:.0f} "
                                         f"{row['steps_per_s']:.0f} steps/s"
                                         + (f" eval {evals[-1]['laps']}/{evals[-1]['target']}" if evals else ""))
                progress.refresh()

            # --- 11. snapshots, checkpoints, evaluations
            if pool is not None and pool.due(elapsed()):
                pool.add_snapshot(net, f"snapshot_{iteration}")
            if time.perf_counter() - last_ckpt >= config.checkpoint_every:
                save_checkpoint()
                last_ckpt = time.perf_counter()
            if config.eval_every and time.perf_counter() - last_eval >= config.eval_every:
                latest = snapshot_agent(ckpt_dir / "latest.pt")
                car = evaluate_time_trial(latest, config.eval_track or str(config.tracks[0]), config.eval_laps,
                                          bots=config.eval_bots)
                evals.append({"iteration": iteration, "agent_steps": agent_steps,
                              "elapsed": round(spent + elapsed(), 1), "laps": car["laps"],
                              "target": config.eval_laps, "resets": car["resets"], "total_time": car["total_time"],
                              "best_lap": car["best_lap"], "status": car["status"], "reason": car["reason"]})
                score = eval_score(evals[-1])
                if best is None or score > best[0]:
                    best = (score, {k: v.detach().clone() for k, v in net.state_dict().items()}, evals[-1])
                if car["laps"] >= config.eval_laps and first_success is None:
                    first_success = evals[-1]["elapsed"]
                    snapshot_agent(ckpt_dir / "first_success.pt")
                if car["laps"] >= config.eval_laps and car["resets"] == 0 and first_clean is None:
                    first_clean = evals[-1]["elapsed"]
                    snapshot_agent(ckpt_dir / "first_clean.pt")
                if log and not progress:
                    log(f"eval: {car['laps']}/{config.eval_laps} laps, {car['resets']} resets")
                last_eval = time.perf_counter()
                if config.stop_on_success and first_clean is not None:
                    break
    except (EOFError, ConnectionError) as exc:
        raise ValueError(f"an env worker process stopped ({type(exc).__name__}); its error is printed above "
                         "(for example a reward function that raised or returned a bad value)") from None
    finally:
        if progress is not None:
            progress.close()
        vec.close()

    # --- 12. outputs: agent file, checkpoint, curve, history
    wall = spent + elapsed()
    summary = {"out": str(out), "iterations": iteration, "agent_steps": agent_steps, "wall_seconds": round(wall, 1),
               "steps_per_s": round(agent_steps / max(wall, 1e-9), 1), "sample_seconds": round(sample_time, 1),
               "update_seconds": round(update_time, 1), "first_success_seconds": first_success,
               "first_clean_seconds": first_clean,
               "final_return": history[-1]["return"] if history else None,
               "final_laps_per_episode": history[-1]["laps_per_episode"] if history else None}
    save_checkpoint()
    note = {"first_success_seconds": first_success, "first_clean_seconds": first_clean}
    if best is not None and config.keep_best:
        # the final weights get one last evaluation; the best evaluated policy is what we ship
        final = snapshot_agent(ckpt_dir / "final.pt")
        car = evaluate_time_trial(final, config.eval_track or str(config.tracks[0]), config.eval_laps,
                                  bots=config.eval_bots)
        final_eval = {"laps": car["laps"], "target": config.eval_laps, "resets": car["resets"],
                      "total_time": car["total_time"], "iteration": iteration, "final": True}
        if best[0] > eval_score(final_eval):
            net.load_state_dict(best[1])
            note["selected"] = f"best evaluation (iteration {best[2]['iteration']})"
            summary["selected_eval"] = best[2]
        else:
            note["selected"] = "final weights"
            summary["selected_eval"] = final_eval
    snapshot_agent(out, note)
    plot_history(history, evals, out.with_suffix(".png"))
    out.with_suffix(".train.json").write_text(json.dumps({"summary": summary, "config": config.to_dict(),
                                                          "history": history, "evals": evals}, indent=1))
    summary["evals"] = evals
    summary["history"] = history
    return summary
