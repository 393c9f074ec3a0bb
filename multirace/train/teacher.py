"""Learning by cheating, stage 1: a state policy (the teacher) learns to race by PPO from the reward.

The teacher reads each car's privileged state (`environment.state.car_features`: its motion, where it
sits on the road, the centre line ahead in its own frame, the nearest cars) instead of a camera, so the
envs render nothing and the net is a small MLP: PPO gets many more samples per second and learns from
far fewer. It learns from the same reward as a camera run (the built-in progress reward or a
DeepRacer reward file) and is evaluated like one: a greedy 3-lap time trial under the race rules. Stage
2 (`distill.py`) teaches a camera policy to drive as it does by DAgger; no scripted driver is involved.

The teacher's network, its file and the teacher as a driver are in `racing/teacher_net.py`.
"""
from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np
import torch

from ..environment.actions import load_action_space
from .actors import Actors
from .config import TrainConfig
from .envs import INFO_KEYS, TrainEnv, env_settings
from .ppo import Policy, RewardScale, anneal_learning_rate, check_reward_file, collect_actor_rollout, \
    collect_rollout, ppo_update, training_runs
from .rivals import race_opponents
from .robust import RobustKnobs
from .rollout import Rollout, expert_actions
from ..racing.teacher_net import StatePolicyNet, TeacherController, TeacherDriver, load_teacher, save_teacher


def evaluate_teacher(net: StatePolicyNet, track: str, laps: int = 3, seed: int = 0, reverse: bool = False,
                     bots=(), randomize=None) -> dict:
    """A greedy race of the teacher under the race rules (`multirace race`'s, with DeepRacer's action noise):
    a time trial, or with `bots` a head-to-head race against them in which each collision it caused counts like
    an off-track (as `run.evaluate_time_trial` does for a camera agent), in the world `randomize` perturbs; its
    result row (laps, resets, total_time, best_lap, status, ...)."""
    from ..racing.runner import RaceConfig, run_race

    controller = TeacherController(TeacherDriver(net, "teacher"))
    result = run_race([controller], RaceConfig(track=track, reverse=reverse, laps=laps, seed=seed,
                                               bots=race_opponents(bots),
                                               race="head_to_head" if bots else "time_trial",
                                               randomize=randomize))
    car = next(c for c in result["cars"] if c["car"] == "car_0")
    return {**car, "resets": car["resets"] + car["collisions_caused"]} if bots else car


def train_teacher(config: TrainConfig, out, seconds: float, log=print) -> dict:
    """PPO of a `StatePolicyNet` for `seconds` of wall time (or `max_iterations`); writes the best-evaluated
    teacher to `out` and returns its summary (evaluations, agent-steps, the sampling and update split)."""
    started = time.perf_counter()
    torch.manual_seed(config.seed)
    space = load_action_space(config.action_space)
    policy = Policy(space)
    runs = training_runs(config)
    check_reward_file(config, runs)
    # (a discrete space is refused here, before any env starts)
    net = StatePolicyNet(space, hidden=config.teacher_hidden, view=config.teacher_view)
    if config.teacher_init:
        _start_from(net, config.teacher_init)
    settings = {**env_settings(config), "observation": "state", "state_view": config.teacher_view,
                "expert_labels": False, "deepracer_log": False}
    from ..environment.vector import SubprocVectorEnv

    vec = SubprocVectorEnv([functools.partial(TrainEnv, runs, worker=w, **settings) for w in range(config.num_envs)],
                           info_keys=INFO_KEYS)
    E, A, T = config.num_envs, config.cars_per_env, config.rollout_steps
    N = E * A
    optimiser = torch.optim.Adam(net.parameters(), lr=config.teacher_lr, eps=1e-5)
    reward_scale = RewardScale(N, config.gamma) if config.teacher_norm_reward else None
    teacher_config = dataclasses.replace(config, lr=config.teacher_lr, epochs=config.teacher_epochs,
                                         minibatch_size=config.teacher_minibatch, ent_coef=config.teacher_ent_coef, expert_coef=0.0,
                                         update_precision="float32")  # state inputs: no convolutions to speed up
    robust = RobustKnobs(TrainConfig(), seed=config.seed)  # no pool or nature: every car is the learner
    learner_mask = np.ones((E, A), bool)
    summary = {"agent_steps": 0, "iterations": 0, "sample_seconds": 0.0, "update_seconds": 0.0, "evals": []}
    best = None
    last_eval = time.perf_counter()
    try:
        obs, _ = vec.reset(seeds=[config.seed * 100_000 + e for e in range(E)])
        rollout = Rollout(T, N, obs.shape[2:], {}, space, obs_dtype=np.float32)
        rollout.start(obs, expert_actions([[{}] * A] * E, discrete=False))  # no expert labels: NaN
        torch.set_num_threads(1)
        actors = Actors(vec, net, space, rollout, pooled=False, seed=config.seed) if config.actors else None
        while time.perf_counter() - started < seconds and not (
                config.max_iterations and summary["iterations"] >= config.max_iterations):
            fraction = (time.perf_counter() - started) / seconds
            t0 = time.perf_counter()
            if actors is not None:  # the workers drive their cars with the teacher's copy
                next_value, _, _ = collect_actor_rollout(actors, net, rollout, robust, learner_mask, reward_scale,
                                                         teacher_config)
            else:
                next_value, _, _ = collect_rollout(vec, net, policy, rollout, robust, learner_mask, reward_scale,
                                                   teacher_config)
            t1 = time.perf_counter()
            advantages, returns = rollout.advantages(next_value, config.gamma, config.gae_lambda)
            anneal_learning_rate(optimiser, teacher_config, fraction)
            ppo_update(net, policy, optimiser, rollout.learner_batch(advantages, returns), teacher_config, space,
                       value_only=False)
            summary["sample_seconds"] += t1 - t0
            summary["update_seconds"] += time.perf_counter() - t1
            summary["agent_steps"] += T * N
            summary["iterations"] += 1
            if time.perf_counter() - last_eval >= config.eval_every:
                best = _evaluate_and_keep(net, config, started, summary, best, log)
                last_eval = time.perf_counter()
    finally:
        vec.close()
    best = _evaluate_and_keep(net, config, started, summary, best, log)
    net.load_state_dict(best[1])
    summary.update(wall_seconds=round(time.perf_counter() - started, 1), selected=best[2])
    notes = {k: v for k, v in summary.items() if k != "evals"}
    save_teacher(out, net, space, {**notes, "tracks": [str(t) for t in config.tracks], "reverse": config.reverse,
                                   "bots": list(config.bots), "teacher_init": config.teacher_init or None})
    return summary


def _start_from(net: StatePolicyNet, path) -> None:
    """Load a teacher file's weights into `net` (`teacher_init`); its action space and sizes must be the run's
    (its view need not: a teacher of every car near it may learn to race from the camera's view)."""
    start = load_teacher(path)
    if (start.hidden, list(start.space.low), list(start.space.high)) != (
            net.hidden, list(net.space.low), list(net.space.high)):
        raise ValueError(f"teacher_init {path}: its action space ({list(start.space.low)}..{list(start.space.high)}) "
                         f"or width ({start.hidden}) is not the run's ({list(net.space.low)}..{list(net.space.high)}, "
                         f"{net.hidden})")
    net.load_state_dict(start.state_dict())


def _evaluate_and_keep(net, config: TrainConfig, started: float, summary: dict, best, log):
    """Evaluate the teacher now, record it, and return the best (score, weights, evaluation) so far."""
    from .run import combined_evaluation, eval_score, evaluation_runs

    row = combined_evaluation([evaluate_teacher(net, track, config.eval_laps, reverse=reverse, bots=config.eval_bots,
                                                randomize=config.eval_randomize)
                               for track, reverse in evaluation_runs(config)], config.eval_laps)
    row.update(elapsed=round(time.perf_counter() - started, 1), agent_steps=summary["agent_steps"])
    summary["evals"].append(row)
    if log:
        lap = f"{row['best_lap']:.2f} s" if row["best_lap"] else "-"
        log(f"teacher {row['elapsed']:6.0f} s {row['agent_steps']:9d} steps: {row['laps']}/{row['target']} laps, "
            f"{row['resets']} resets, best lap {lap}")
    score = eval_score(row)
    if best is None or score > best[0]:
        best = (score, {k: v.detach().clone() for k, v in net.state_dict().items()}, row)
    return best
