"""Several race envs stepped in worker processes, as stacked numpy arrays.

Each worker process owns one `RaceEnv` (built there from a picklable factory)
and resets it automatically when its episode ends. Observations come back as
one array (envs, cars, H, W, C); only the info keys asked for cross the pipe,
since the full DeepRacer params (waypoint lists) are costly to send.
"""
from __future__ import annotations

import multiprocessing as mp
from typing import Callable, Sequence

import numpy as np

DEFAULT_INFO_KEYS = ("progress", "laps_completed", "lap_times", "resets", "status", "collisions")


def _worker(remote, make_env, info_keys) -> None:
    import cv2

    cv2.setNumThreads(1)  # one core per worker; OpenCV's own threads only contend
    env = make_env()
    episode_seed = None

    def pack(obs, infos):
        stacked = np.stack([obs[a] for a in env.possible_agents])
        small = [{k: infos[a][k] for k in info_keys if k in infos[a]} for a in env.possible_agents]
        return stacked, small

    try:
        while True:
            command, payload = remote.recv()
            if command == "reset":
                episode_seed = payload
                obs, infos = env.reset(seed=payload)
                remote.send(pack(obs, infos))
            elif command == "step":
                actions = {a: payload[k] for k, a in enumerate(env.possible_agents)}
                obs, rewards, terms, truncs, infos = env.step(actions)
                reward = np.array([rewards[a] for a in env.possible_agents], np.float32)
                done = all(terms.values()) or all(truncs.values())
                truncated = all(truncs.values())
                final_obs, final_infos = pack(obs, infos)
                if done:
                    episode_seed = None if episode_seed is None else episode_seed + 1000
                    obs, infos = env.reset(seed=episode_seed)
                    obs, _ = pack(obs, infos)
                else:
                    obs = final_obs
                remote.send((obs, reward, done, truncated, final_infos))
            elif command == "close":
                break
    finally:
        env.close()
        remote.close()


class SubprocVectorEnv:
    """`len(make_envs)` race envs in worker processes, stepped in lock-step."""

    def __init__(self, make_envs: Sequence[Callable], info_keys: Sequence[str] = DEFAULT_INFO_KEYS):
        context = mp.get_context("spawn")  # PyBullet clients must not be forked
        self.remotes, self.processes = [], []
        for make_env in make_envs:
            parent, child = context.Pipe()
            process = context.Process(target=_worker, args=(child, make_env, tuple(info_keys)), daemon=True)
            process.start()
            child.close()
            self.remotes.append(parent)
            self.processes.append(process)
        self.num_envs = len(make_envs)

    def reset(self, seeds: Sequence[int | None] | None = None):
        """Reset every env; returns observations (E, A, H, W, C) and per-env lists of small infos."""
        seeds = list(seeds) if seeds is not None else [None] * self.num_envs
        for remote, seed in zip(self.remotes, seeds):
            remote.send(("reset", seed))
        results = [remote.recv() for remote in self.remotes]
        return np.stack([r[0] for r in results]), [r[1] for r in results]

    def step(self, actions):
        """Step every env with `actions[e][car]`.

        Returns observations (after auto-reset), rewards (E, A), dones (E,), truncated (E,), and the
        small infos of the step that was taken (before any reset).
        """
        for remote, action in zip(self.remotes, actions):
            remote.send(("step", action))
        results = [remote.recv() for remote in self.remotes]
        obs = np.stack([r[0] for r in results])
        rewards = np.stack([r[1] for r in results])
        dones = np.array([r[2] for r in results])
        truncated = np.array([r[3] for r in results])
        return obs, rewards, dones, truncated, [r[4] for r in results]

    def close(self) -> None:
        for remote in self.remotes:
            try:
                remote.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for process in self.processes:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
