"""Several race envs stepped in worker processes, as stacked numpy arrays.

Each worker process owns one `RaceEnv` (built there from a picklable factory)
and resets it automatically when its episode ends. Camera images travel
through shared memory (each worker writes its cars' images into its own slot),
so the pipe carries only rewards, flags and the info keys asked for; the full
DeepRacer params (waypoint lists) are costly to send and stay behind.
"""
from __future__ import annotations

import multiprocessing as mp
from multiprocessing import shared_memory
from typing import Callable, Sequence

import numpy as np

DEFAULT_INFO_KEYS = ("progress", "laps_completed", "lap_times", "resets", "status", "collisions")


def _worker(remote, make_env, info_keys) -> None:
    import cv2

    cv2.setNumThreads(1)  # one core per worker; OpenCV's own threads only contend
    env = make_env()
    agents = env.possible_agents
    memory, images = None, None
    episode_seed = None

    def publish(obs, infos=None):
        nonlocal memory, images
        if images is None:  # first images: ask for a shared buffer of their size
            remote.send(("shape", (len(agents),) + obs[agents[0]].shape))
            memory = shared_memory.SharedMemory(name=remote.recv())
            images = np.ndarray((len(agents),) + obs[agents[0]].shape, np.uint8, buffer=memory.buf)
        for k, agent in enumerate(agents):
            images[k] = obs[agent]
        if infos is not None:
            return [{key: infos[a][key] for key in info_keys if key in infos[a]} for a in agents]

    try:
        while True:
            command, payload = remote.recv()
            if command == "reset":
                episode_seed = payload
                obs, infos = env.reset(seed=payload)
                small = publish(obs, infos)
                remote.send(("infos", small))
            elif command == "step":
                obs, rewards, terms, truncs, infos = env.step({a: payload[k] for k, a in enumerate(agents)})
                reward = [float(rewards[a]) for a in agents]  # plain lists pickle faster than small arrays
                truncated = all(truncs.values())
                done = all(terms.values()) or truncated
                small = [{key: infos[a][key] for key in info_keys if key in infos[a]} for a in agents]
                if done:
                    episode_seed = None if episode_seed is None else episode_seed + 1000
                    obs, _ = env.reset(seed=episode_seed)
                publish(obs)
                remote.send(("step", (reward, done, truncated, small)))
            elif command == "close":
                break
    finally:
        images = None
        if memory is not None:
            memory.close()
        env.close()
        remote.close()


class SubprocVectorEnv:
    """`len(make_envs)` race envs in worker processes, stepped in lock-step."""

    def __init__(self, make_envs: Sequence[Callable], info_keys: Sequence[str] = DEFAULT_INFO_KEYS):
        context = mp.get_context("spawn")  # PyBullet clients must not be forked
        self.remotes, self.processes, self.memories = [], [], []
        for make_env in make_envs:
            parent, child = context.Pipe()
            process = context.Process(target=_worker, args=(child, make_env, tuple(info_keys)), daemon=True)
            process.start()
            child.close()
            self.remotes.append(parent)
            self.processes.append(process)
        self.num_envs = len(make_envs)
        self.images = [None] * self.num_envs

    def _receive(self, k: int):
        """The next reply of worker k, first serving its request for a shared image buffer."""
        kind, payload = self.remotes[k].recv()
        if kind == "shape":  # one buffer per worker, sized by its first images
            memory = shared_memory.SharedMemory(create=True, size=int(np.prod(payload)))
            self.memories.append(memory)
            self.images[k] = np.ndarray(payload, np.uint8, buffer=memory.buf)
            self.remotes[k].send(memory.name)
            kind, payload = self.remotes[k].recv()
        return payload

    def _observations(self) -> np.ndarray:
        return np.stack(self.images)  # a copy: the workers overwrite their buffers next step

    def reset(self, seeds: Sequence[int | None] | None = None):
        """Reset every env; returns observations (E, A, H, W, C) and per-env lists of small infos."""
        seeds = list(seeds) if seeds is not None else [None] * self.num_envs
        for remote, seed in zip(self.remotes, seeds):
            remote.send(("reset", seed))
        infos = [self._receive(k) for k in range(self.num_envs)]
        return self._observations(), infos

    def step(self, actions):
        """Step every env with `actions[e][car]`.

        Returns observations (after auto-reset), rewards (E, A), dones (E,), truncated (E,), and the
        small infos of the step that was taken (before any reset).
        """
        for remote, action in zip(self.remotes, actions):
            remote.send(("step", np.asarray(action).tolist()))
        results = [self._receive(k) for k in range(self.num_envs)]
        rewards = np.array([r[0] for r in results], np.float32)
        dones = np.array([r[1] for r in results])
        truncated = np.array([r[2] for r in results])
        return self._observations(), rewards, dones, truncated, [r[3] for r in results]

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
        self.images = []
        for memory in self.memories:
            memory.close()
            memory.unlink()
        self.memories = []
