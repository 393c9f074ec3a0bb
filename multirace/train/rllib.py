"""`multirace train --engine rllib`: the training env under Ray RLlib (PPO, one shared policy).

The same `TrainEnv` as the local engine (tracks, directions, cars, bots,
reward, action space, camera, domain randomisation, all from `TrainConfig`)
is exposed as a PettingZoo ParallelEnv, wrapped in RLlib's
``ParallelPettingZooEnv`` and trained by RLlib's PPO (new API stack) with
``num_env_runners`` sampling actors. Every car maps to one shared RLModule
(parameter sharing, as the local engine). The RLModule *is* multirace's
`nets.CameraNet` (policy head plus value head on one trunk), so at the end its
weights are written as an ordinary agent file that `multirace race` accepts,
next to the RLlib checkpoint:

    multirace train --engine rllib --minutes 10 --out agent.pt            # local Ray, cores-1 env runners
    multirace train --engine rllib --address auto --envs 16 --out a.pt    # on a running Ray cluster

Outputs: ``FILE.pt`` (agent file, the final weights), ``FILE.rllib/`` (RLlib
checkpoint: ``Algorithm.from_checkpoint`` resumes or serves it),
``FILE.train.json`` (config, per-iteration history) and ``FILE.snapshots/``
(an agent file every ``eval_every`` seconds, to race or evaluate afterwards).

Per-car training episodes as the local engine: an off-track ends the car's
RLlib agent (terminated, value target 0) and the car drives on under a fresh
agent id (``car_2.1``, ``car_2.2``, ...), all mapped to the shared policy.

Differences from the local engine (this is RLlib's PPO, not ours): the
learning rate is constant (no wall-clock annealing); minibatches are capped at
the env-step batch (RLlib's check), so with one env runner they are smaller;
no periodic time-trial evaluations or best-policy selection (the agent file
holds the final weights); no opponent pool, nature adversary or curriculum
(the env-level options ``randomize`` and procedural tracks are kept). Needs
``pip install -e ".[rllib]"``.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ..atomic import write_text

MODULE_ID = "shared"  # the one policy every car maps to
ENV_NAME = "multirace_train"
INSTALL_HINT = 'pip install -e ".[rllib]"'


def require_rllib():
    """Import Ray RLlib or stop with the install command."""
    try:
        import ray  # noqa: F401
        from ray.rllib.algorithms.ppo import PPOConfig  # noqa: F401
        from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv  # noqa: F401
    except ImportError as exc:
        raise ValueError(f"--engine rllib needs Ray RLlib, which is not installed here ({exc}); install it with "
                         f"`{INSTALL_HINT}` (or pip install 'ray[rllib]'), or use --engine local "
                         "(the default)") from None


# ------------------------------------------------------------------ the env
def _parallel_env_class():
    from pettingzoo import ParallelEnv

    class RaceTrainParallelEnv(ParallelEnv):
        """`TrainEnv` (training rewards, several tracks) as a PettingZoo ParallelEnv for RLlib.

        Per-car training episodes, as the local engine: when a car's training episode
        ends (an off-track with ``terminate_off_track``), that agent id is *terminated*
        (value target 0) and the car - which the race rules have put back on the centre
        line - goes on under a fresh id, ``car_2`` -> ``car_2.1`` -> ``car_2.2`` ...,
        because an RLlib multi-agent episode cannot bring a terminated agent back. Every
        id maps to the one shared policy. At ``episode_steps`` every car is truncated.
        """

        metadata = {"name": "multirace_train_v0", "render_modes": []}

        def __init__(self, train_env):
            self.train_env = train_env
            self.cars = list(train_env.possible_agents)
            self.possible_agents = list(self.cars)
            self._lives = [0] * len(self.cars)
            self.agents = list(self.possible_agents)
            probe = train_env.env_for(0)
            self._obs_space = probe.observation_space(self.cars[0])
            self._act_space = probe.action_space(self.cars[0])

        def observation_space(self, agent):
            return self._obs_space

        def action_space(self, agent):
            return self._act_space

        def _id(self, i: int) -> str:
            return self.cars[i] if self._lives[i] == 0 else f"{self.cars[i]}.{self._lives[i]}"

        def reset(self, seed=None, options=None):
            obs, infos = self.train_env.reset(seed=seed, options=options)
            self._lives = [0] * len(self.cars)
            self.agents = list(self.cars)
            return obs, infos

        def step(self, actions):
            by_car = {self.cars[i]: actions[self._id(i)] for i in range(len(self.cars)) if self._id(i) in actions}
            if self._act_space.__class__.__name__ == "Box":  # RLlib's Gaussian is unbounded; keep to the box
                by_car = {c: np.clip(np.asarray(v, np.float32), self._act_space.low, self._act_space.high)
                          for c, v in by_car.items()}
            obs, rewards, _, _, infos = self.train_env.step(by_car)
            over = not self.train_env.agents  # the env episode is over (episode_steps): every car truncated
            o, r, te, tr, inf = {}, {}, {}, {}, {}
            for i, car in enumerate(self.cars):
                aid = self._id(i)
                o[aid], r[aid], inf[aid] = obs[car], float(rewards[car]), infos[car]
                te[aid], tr[aid] = (False, True) if over else (bool(infos[car].get("train_done")), False)
                if te[aid]:  # the car drives on (back on the centre line) as a new agent
                    self._lives[i] += 1
                    o[self._id(i)], inf[self._id(i)] = obs[car], infos[car]
                    te[self._id(i)], tr[self._id(i)] = False, False
            self.agents = [] if over else [self._id(i) for i in range(len(self.cars))]
            return o, r, te, tr, inf

        def close(self):
            self.train_env.close()

    return RaceTrainParallelEnv


def make_rllib_env(env_config: dict):
    """RLlib env creator: `TrainEnv` -> ParallelEnv -> `ParallelPettingZooEnv`. Plain-data config."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from .envs import TrainEnv

    config = dict(env_config)
    worker = int(getattr(env_config, "worker_index", 0)) * 1000 + int(getattr(env_config, "vector_index", 0))
    train_env = TrainEnv(worker=worker, **config)
    return ParallelPettingZooEnv(_parallel_env_class()(train_env))


def env_config_for(config, runs) -> dict:
    """The env_config of every env runner's `TrainEnv`: the training runs and the config's env settings."""
    from .envs import env_settings

    return {"runs": runs, **env_settings(config), "deepracer_log": False}  # this engine writes no DeepRacer folder


# --------------------------------------------------------------- the module
def _module_class():
    """The RLModule class, built once per process (Ray is imported only when the rllib engine runs)."""
    if "CameraRLModule" in globals():
        return globals()["CameraRLModule"]
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.apis import ValueFunctionAPI
    from ray.rllib.core.rl_module.torch import TorchRLModule

    class CameraRLModule(TorchRLModule, ValueFunctionAPI):
        """multirace's `CameraNet` (with value head) as an RLlib RLModule: weights map 1:1 onto an agent file.

        Discrete actions: the net's logits feed RLlib's Categorical. Continuous: its
        [mean steer, mean speed, log-std steer, log-std speed] feed RLlib's DiagGaussian,
        which takes exactly that layout.
        """

        def setup(self):
            import gymnasium as gym
            import torch

            from ..racing.nets import CONTINUOUS_OUTPUTS, TINY, CameraNet
            from ..sensors.camera import image_shape_of

            network = (self.model_config or {}).get("network", TINY)
            discrete = isinstance(self.action_space, gym.spaces.Discrete)
            outputs = int(self.action_space.n) if discrete else CONTINUOUS_OUTPUTS
            self.net = CameraNet(network, image_shape_of(self.observation_space.shape), outputs, value_head=True)
            if not discrete:  # start in the middle of the action box with a quarter-range spread (as ppo.py)
                low = np.asarray(self.action_space.low, np.float64)
                high = np.asarray(self.action_space.high, np.float64)
                with torch.no_grad():
                    self.net.head.weight.mul_(0.01)
                    self.net.head.bias.copy_(torch.tensor(
                        [*((low + high) / 2), *np.log(np.maximum((high - low) / 4, 1e-3))], dtype=torch.float32))

        def _forward(self, batch, **kwargs):
            return {Columns.ACTION_DIST_INPUTS: self.net(batch[Columns.OBS])}

        def _forward_train(self, batch, **kwargs):
            features = self.net.features(batch[Columns.OBS])
            return {Columns.ACTION_DIST_INPUTS: self.net.head(features), Columns.EMBEDDINGS: features}

        def compute_values(self, batch, embeddings=None):
            if embeddings is None:
                embeddings = self.net.features(batch[Columns.OBS])
            return self.net.value_head(embeddings).squeeze(-1)

    CameraRLModule.__module__ = __name__
    CameraRLModule.__qualname__ = "CameraRLModule"
    globals()["CameraRLModule"] = CameraRLModule  # so pickle finds it by name in every process
    return CameraRLModule


def __getattr__(name):  # `multirace.train.rllib.CameraRLModule` without importing Ray at module import
    if name == "CameraRLModule":
        return _module_class()
    raise AttributeError(name)


def net_state_from_module(module_state: dict) -> dict:
    """A `CameraNet` state dict from an RLModule state dict (keys ``net.*``; numpy or torch values)."""
    import torch

    state = {k[len("net."):]: torch.as_tensor(np.asarray(v)) for k, v in module_state.items() if k.startswith("net.")}
    if not state:
        raise ValueError(f"RLlib module state has no 'net.*' weights (keys: {sorted(module_state)[:5]})")
    return state


# -------------------------------------------------------------- algorithm
def build_ppo_config(config, runs, num_env_runners: int):
    """The RLlib `PPOConfig` of a `TrainConfig` (same env, same PPO knobs where RLlib has them)."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    # counted in env steps (RLlib's default; its agent-step counting breaks on agents that come and go):
    # rollout_steps per env runner, i.e. rollout_steps x cars agent-steps each, as TrainConfig.batch_size.
    # RLlib's minibatches are in agent-steps but must not exceed the env-step batch (its config check).
    train_batch = max(1, num_env_runners) * config.rollout_steps
    cfg = (
        PPOConfig()
        .environment(ENV_NAME, env_config=env_config_for(config, runs), normalize_actions=False,
                     clip_actions=False, disable_env_checking=True)
        .framework("torch")
        .env_runners(num_env_runners=num_env_runners, num_envs_per_env_runner=1, num_cpus_per_env_runner=1,
                     rollout_fragment_length="auto", sample_timeout_s=600.0)
        .learners(num_learners=0)
        .multi_agent(policies={MODULE_ID}, policy_mapping_fn=_map_to_shared, policies_to_train=[MODULE_ID])
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={MODULE_ID: RLModuleSpec(
            module_class=_module_class(), model_config={"network": config.network})}))
        .training(train_batch_size_per_learner=train_batch,
                  minibatch_size=min(int(config.minibatch_size), train_batch),
                  num_epochs=int(config.epochs), lr=float(config.lr), gamma=float(config.gamma),
                  lambda_=float(config.gae_lambda), clip_param=float(config.clip),
                  entropy_coeff=float(config.ent_coef), vf_loss_coeff=float(config.vf_coef),
                  grad_clip=float(config.max_grad_norm), grad_clip_by="global_norm", use_kl_loss=False,
                  vf_clip_param=float(config.clip) if config.clip_value else 1e9)
        .debugging(seed=int(config.seed), log_level="ERROR")
    )
    return cfg


def _map_to_shared(agent_id, *args, **kwargs):
    return MODULE_ID


def _metric(result: dict, *keys, default=None):
    node = result
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            return default
        node = node[key]
    return node


def _total(value) -> float:
    """A step counter of a result: a number, or a {agent or module id: number} dict summed."""
    if isinstance(value, dict):
        return float(sum(_total(v) for v in value.values()))
    try:
        value = float(value or 0.0)
    except (TypeError, ValueError):
        return 0.0
    return value if np.isfinite(value) else 0.0


def _finite_mean(values):
    values = [float(v) for v in values if v is not None and np.isfinite(float(v))]
    return float(np.mean(values)) if values else None


def iteration_stats(result: dict, cars: int) -> dict:
    """The figures of one `algo.train()` result we log (RLlib new-API-stack result keys).

    ``car_return_mean``: the mean return of one car over an env episode (episode_steps
    steps, all its training episodes together): RLlib's ``episode_return_mean`` (the
    sum over every agent id of the env episode) / cars; None until an env episode ends.
    """
    runners = result.get("env_runners", {})
    total = _finite_mean([runners.get("episode_return_mean")])
    per_car = None if total is None else total / max(1, cars)
    return {
        "iteration": int(result.get("training_iteration", 0)),
        "env_steps": int(_total(runners.get("num_env_steps_sampled_lifetime"))),
        "agent_steps": int(_total(runners.get("num_agent_steps_sampled_lifetime"))),
        "episodes": int(_total(runners.get("num_episodes_lifetime"))),
        "car_return_mean": None if per_car is None else round(per_car, 3),
        "agent_ids": len(runners.get("agent_episode_returns_mean") or {}),  # car_N.LIFE ids RLlib tracks
        "policy_loss": _metric(result, "learners", MODULE_ID, "policy_loss"),
        "vf_loss": _metric(result, "learners", MODULE_ID, "vf_loss"),
        "entropy": _metric(result, "learners", MODULE_ID, "entropy"),
    }


def _float(v):
    try:
        return round(float(v), 5)
    except (TypeError, ValueError):
        return None


def default_env_runners(config, explicit_envs) -> int:
    """--envs if given, else the config's num_envs capped at cores - 1 (at least 1)."""
    if explicit_envs is not None:
        return max(0, int(explicit_envs))
    return max(1, min(int(config.num_envs), (os.cpu_count() or 2) - 1))


def _check_config(config, space, log) -> None:
    """Refuse what the RLlib engine cannot train (with the option named), and note what it ignores."""
    from ..racing.nets import CameraNet, num_outputs_for
    from ..sensors.suite import SensorSuite

    if config.sensors() != SensorSuite():
        what = "lidar=true" if config.lidar else f"sensor={config.sensors().names}"
        raise ValueError(f"--engine rllib: {what} is a local-engine option for now: the RLlib module reads the "
                         "single camera (and with camera + LIDAR dict observations RLlib's PettingZoo wrapper "
                         "loses the per-car episode ids' observations: car_0.1, ...; seen with ray 2.60)")
    if config.opponent_pool or config.nature or config.curriculum:
        log("note: --engine rllib ignores the opponent pool, nature adversary and curriculum "
            "(env randomisation and procedural tracks are kept)")
    try:  # a network / camera mismatch fails here with our message, not deep inside a Ray actor
        CameraNet(config.network, (*config.camera, 1), num_outputs_for(space), value_head=True)
    except ValueError as exc:
        raise ValueError(f"--set camera / --network: {exc}") from None


def _start_ray(address, num_env_runners: int) -> bool:
    """Join the Ray cluster at `address` or start a local Ray; True when this call started it."""
    import ray

    if ray.is_initialized():
        return False
    if address:
        try:
            ray.init(address=address, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise ValueError(f"--address {address}: could not connect to a Ray cluster there ({exc}); "
                             "start one with `ray start --head` or leave --address out for a local Ray") from None
    else:
        ray.init(num_cpus=max(os.cpu_count() or 1, num_env_runners + 1), include_dashboard=False,
                 log_to_driver=False, configure_logging=True, logging_level="ERROR")
    return True


def _train_iterations(algo, config, write_snapshot, log) -> list[dict]:
    """`algo.train()` until the budget is spent (the minutes, or `max_iterations` iterations if that comes
    first), a snapshot agent file every `eval_every` seconds; returns the per-iteration stats."""
    budget = 60.0 * float(config.minutes)
    train_start = last_snapshot = time.perf_counter()
    history = []
    while True:
        result = algo.train()
        stats = iteration_stats(result, config.cars_per_env)
        stats["elapsed"] = round(time.perf_counter() - train_start, 2)
        stats["agent_steps_per_s"] = round(stats["agent_steps"] / max(stats["elapsed"], 1e-9), 1)
        for key in ("policy_loss", "vf_loss", "entropy"):
            stats[key] = _float(stats[key])
        history.append(stats)
        if config.progress:
            ret = stats["car_return_mean"]
            log(f"rllib iter {stats['iteration']:4d} {stats['elapsed']:7.1f}/{budget:.0f} s  "
                f"return/car {'-' if ret is None else f'{ret:8.2f}'}  agent-steps {stats['agent_steps']:8d}  "
                f"{stats['agent_steps_per_s']:7.1f} agent-steps/s  episodes {stats['episodes']}")
        if stats["elapsed"] >= budget or 0 < config.max_iterations <= len(history):
            return history
        if config.eval_every and time.perf_counter() - last_snapshot >= config.eval_every:
            # an agent-file snapshot to race or `multirace evaluate` later (no in-loop evaluation here)
            last_snapshot = time.perf_counter()
            write_snapshot(stats)


def train_rllib(config, out, envs=None, address=None, log=print) -> int:
    """`multirace train --engine rllib` with `config` (a TrainConfig), writing the agent file `out`.

    `envs` is the number of env runners asked for (None: the config's, capped by the cores);
    `address` a Ray cluster to join (None: a local Ray instance). See the module docstring.
    """
    require_rllib()
    import ray
    import torch
    from ray.tune.registry import register_env

    from ..environment.actions import load_action_space
    from ..racing.agentfile import make_metadata, save_agent
    from ..racing.nets import CameraNet, num_outputs_for
    from ..sensors.camera import image_shape_of
    from .ppo import check_reward_file, training_runs

    space = load_action_space(config.action_space)
    _check_config(config, space, log)
    num_env_runners = default_env_runners(config, envs)
    out = Path(out)
    ckpt_dir = out.with_name(out.stem + ".rllib").resolve()
    runs = training_runs(config)
    check_reward_file(config, runs)

    started = time.perf_counter()
    own_ray = _start_ray(address, num_env_runners)
    register_env(ENV_NAME, make_rllib_env)
    import logging

    logging.getLogger("ray.rllib").setLevel(logging.ERROR)  # e.g. "You are running PPO on the new API stack!"
    torch.set_num_threads(int(config.threads))
    ppo_config = build_ppo_config(config, runs, num_env_runners)
    algo = ppo_config.build_algo() if hasattr(ppo_config, "build_algo") else ppo_config.build()
    setup_seconds = time.perf_counter() - started
    log(f"rllib: Ray {ray.__version__} at {address or 'local'}, {num_env_runners} env runner(s) x "
        f"{config.cars_per_env} cars, shared policy '{MODULE_ID}' ({config.network}), set-up {setup_seconds:.1f} s")

    image_shape = image_shape_of(algo.get_module(MODULE_ID).observation_space.shape)

    def write_agent(path, training: dict) -> Path:
        """The learner's current shared-module weights as an agent file."""
        weights = algo.learner_group.get_weights(module_ids=[MODULE_ID])[MODULE_ID]
        net = CameraNet(config.network, image_shape, num_outputs_for(space), value_head=True)
        net.load_state_dict(net_state_from_module(weights), strict=True)
        metadata = make_metadata(space, net.network, Path(path).stem, image_shape, training_algorithm="clipped_ppo",
                                 training={"engine": "rllib", "ray": ray.__version__, **training})
        return save_agent(path, net, metadata)

    def write_snapshot(stats: dict) -> Path:
        return write_agent(out.with_name(out.stem + ".snapshots") / f"{int(stats['elapsed']):05d}s.pt",
                           {"iterations": stats["iteration"], "agent_steps": stats["agent_steps"],
                            "wall_seconds": stats["elapsed"]})

    train_start = time.perf_counter()
    try:
        history = _train_iterations(algo, config, write_snapshot, log)
        wall = time.perf_counter() - train_start
        checkpoint = algo.save_to_path(str(ckpt_dir))
        last = history[-1]
        returns = [h["car_return_mean"] for h in history if h["car_return_mean"] is not None]
        training = {"iterations": last["iteration"], "agent_steps": last["agent_steps"], "wall_seconds": round(wall, 1),
                    "env_runners": num_env_runners, "rllib_checkpoint": str(checkpoint),
                    "car_return_first": returns[0] if returns else None,
                    "car_return_last": returns[-1] if returns else None}
        write_agent(out, training)
    finally:
        algo.stop()
        if own_ray:
            ray.shutdown()
    summary = {"engine": "rllib", "ray": ray.__version__, "out": str(out), **training,
               "steps_per_s": round(last["agent_steps"] / max(wall, 1e-9), 1), "setup_seconds": round(setup_seconds, 1),
               "config": config.to_dict(), "history": history}
    summary["config"]["runs"] = None
    write_text(out.with_suffix(".train.json"), json.dumps(summary, indent=1, default=str))
    log(f"wrote {out} (agent file) and {checkpoint} (RLlib checkpoint): {last['iteration']} iterations, "
        f"{last['agent_steps']} agent-steps in {wall:.0f} s ({summary['steps_per_s']} agent-steps/s), "
        f"return/car per env episode {training['car_return_first']} (first) -> {training['car_return_last']} (last)")
    return 0
