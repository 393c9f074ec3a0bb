"""Several race envs stepped in worker processes, as stacked numpy arrays.

Each worker process owns one `RaceEnv` (built there from a picklable factory)
and resets it automatically when its episode ends. Everything per step that
has a fixed shape lives in shared memory, one block per kind with a slot per
worker: the actions the learner writes, and the camera images (and the vector
sensors' values: LIDAR ranges, SPEED; or the state vectors of state envs),
rewards and done flags the workers write. Cars driven by commands rather
than actions (self-play's pool opponents) get them in a block of their own,
(steering degrees, speed m/s) per car, NaN for the cars that take actions;
their env takes each as a `drivers.Command`, whatever its action space. A
step is then one command byte down each pipe and one byte back (or, when info
keys were asked for, a small pickled list of those infos): the pipe round
trip is the largest cost of a worker step after the env itself. The
full DeepRacer params (waypoint lists) are costly to send and stay behind.

After each reply a worker polls for its next command for `spin_wait` seconds
(half a millisecond), yielding its core on every poll, before it sleeps. A
sleeping worker's core goes idle, and waking an idle core (of a virtual
machine above all) costs more than the pipe itself: with two workers in
lock-step, the one that finished first would otherwise idle its core at
every step. Polling is cheap to the learner, which gets the core at the
next yield.
"""
from __future__ import annotations

import math
import multiprocessing as mp
import os
import select
import sys
import time
from multiprocessing import shared_memory
from typing import Callable, Sequence

import numpy as np

from .actions import Command
from .rewards import RewardFunctionError

DEFAULT_INFO_KEYS = ("progress", "laps_completed", "lap_times", "resets", "status", "collisions")
RESET, ACTIONS, COMMANDS, STEP, CLOSE, DONE = b"r", b"a", b"m", b"s", b"c", b"d"  # one-byte commands, the bare reply
ACTOR, ACT = b"t", b"x"  # attach an actor (a picklable factory), run it once (a picklable payload)
FAILED = b"f"  # the reply of a worker whose env's reward function failed; its message follows
SPIN_WAIT = 0.0005  # seconds a worker polls for its next command before it sleeps in a blocking read
VECTOR_PREFIX = "vector:"  # shared-array names of the vector sensors (LIDAR, SPEED, ...): "vector:lidar"


class SharedArray:
    """A numpy array in a named shared-memory block; `attach` maps the same block in another process."""

    def __init__(self, shape, dtype, name: str | None = None):
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        size = max(1, int(np.prod(self.shape)) * self.dtype.itemsize)
        self.memory = shared_memory.SharedMemory(name=name, create=name is None, size=size if name is None else 0)
        self.array = np.ndarray(self.shape, self.dtype, buffer=self.memory.buf)

    @property
    def spec(self) -> tuple:
        return self.memory.name, self.shape, self.dtype.str

    @classmethod
    def attach(cls, spec: tuple) -> "SharedArray":
        name, shape, dtype = spec
        return cls(shape, dtype, name=name)

    def close(self, unlink: bool = False) -> None:
        self.array = None
        self.memory.close()
        if unlink:
            self.memory.unlink()


def _worker(remote, make_env, info_keys, spin_wait: float) -> None:
    """A worker process: builds its env and serves the learner's commands until told to close."""
    import cv2

    cv2.setNumThreads(1)  # one core per worker; OpenCV's own threads only contend
    # and torch's (an expert's net in a training env): its second thread spins beside the env, on the core the
    # other worker needs (it took more CPU than the env itself)
    os.environ["OMP_NUM_THREADS"] = "1"  # read where torch is imported later
    torch = sys.modules.get("torch")  # imported already (spawn imports the main script again here)
    if torch is not None:
        torch.set_num_threads(1)
    _Worker(remote, make_env(), info_keys, spin_wait).serve()


class _Worker:
    """One worker's env and the shared arrays it reads actions from and writes observations and rewards to."""

    def __init__(self, remote, env, info_keys, spin_wait: float):
        self.remote, self.env, self.info_keys, self.spin_wait = remote, env, info_keys, spin_wait
        self.agents = env.possible_agents
        self.fd = remote.fileno()
        self.shared: dict = {}  # name -> SharedArray, once the learner has sent them
        self.slot = 0
        self.integer_actions = True
        self.episode_seed = None
        self.obs = None  # the env's latest observations (per agent)
        self.actor = None  # with `attach_actor`: runs this worker's cars itself (`SubprocVectorEnv.act`)

    def serve(self) -> None:
        """Answer the learner's commands (step, reset, new action arrays, actors) until it closes or goes away."""
        handlers = {STEP: self.step, RESET: self.reset, ACTIONS: self.attach_actions, COMMANDS: self.attach_commands,
                    ACTOR: self.attach_actor, ACT: self.act}
        try:
            while True:
                command = self.next_command()
                if command in (CLOSE, b""):  # b"": the learner is gone
                    break
                if command in handlers:
                    handlers[command]()
        except RewardFunctionError as failure:
            self.report(failure)
        finally:
            for array in self.shared.values():
                array.close()
            self.env.close()
            self.remote.close()

    def next_command(self) -> bytes:
        """The learner's next command byte; polled for `spin_wait` seconds (yielding the core) before sleeping."""
        deadline = time.perf_counter() + self.spin_wait
        while time.perf_counter() < deadline:
            if select.select([self.fd], [], [], 0)[0]:
                break
            os.sched_yield()
        return os.read(self.fd, 1)

    def advance(self, actions: list) -> tuple:
        """Step the env with one action per car (a new episode when it ends): (rewards per car, done, truncated,
        the small infos of the step taken, read before any reset, or None without `info_keys`); the observations
        after it (the new episode's first) are in `self.obs`."""
        agents = self.agents
        obs, rewards, terms, truncs, infos = self.env.step(dict(zip(agents, actions)))
        truncated = all(truncs.values())
        done = all(terms.values()) or truncated
        infos = self.small_infos(infos) if self.info_keys else None  # read before the reset below
        if done:
            self.episode_seed = None if self.episode_seed is None else self.episode_seed + 1000
            obs, _ = self.env.reset(seed=self.episode_seed)
        self.obs = obs
        return [rewards[a] for a in agents], done, truncated, infos

    def step(self) -> None:
        """Step the env with the actions in this worker's row and publish the result."""
        rewards, done, truncated, infos = self.advance(self.actions())
        self.shared["rewards"].array[self.slot] = rewards
        self.shared["flags"].array[self.slot] = (done, truncated)
        self.publish_images(self.obs)
        if infos is not None:
            self.remote.send(infos)
        else:
            os.write(self.fd, DONE)

    def attach_actor(self) -> None:
        """Build the actor from the factory the learner sends (called with this worker)."""
        self.actor = self.remote.recv()(self)

    def act(self) -> None:
        """Run the actor on the payload the learner sends; its result goes back."""
        self.remote.send(self.actor(self.remote.recv()))

    def actions(self) -> list:
        """Each car's action from this worker's row: the learner's action, or a `Command` where the car is driven
        by commands (its row of the commands block is not NaN)."""
        row = self.shared["actions"].array[self.slot]
        actions = row[:, 0].astype(int).tolist() if self.integer_actions else row.tolist()
        if "commands" in self.shared:
            for k, (steer, speed) in enumerate(self.shared["commands"].array[self.slot].tolist()):
                if not math.isnan(steer):
                    actions[k] = Command((steer, speed))
        return actions

    def reset(self) -> None:
        """Start an episode with the seed the learner sends; publish its first observations."""
        self.episode_seed = self.remote.recv()
        self.obs, infos = self.env.reset(seed=self.episode_seed)
        self.publish_images(self.obs)
        self.remote.send(self.small_infos(infos))

    def attach_actions(self) -> None:
        """Attach the action array the learner sends (and whether its actions are integers)."""
        spec, self.integer_actions = self.remote.recv()
        if "actions" in self.shared:
            self.shared["actions"].close()
        self.shared["actions"] = SharedArray.attach(spec)

    def attach_commands(self) -> None:
        """Attach the commands block the learner sends."""
        self.shared["commands"] = SharedArray.attach(self.remote.recv())

    def small_infos(self, infos) -> list[dict]:
        return [{key: infos[a][key] for key in self.info_keys if key in infos[a]} for a in self.agents]

    def publish_images(self, obs) -> None:
        """Write the observations to this worker's slot of the shared arrays (sized by the learner on first use)."""
        agents, shared = self.agents, self.shared
        first = obs[agents[0]]
        vectors = [key for key in first if key != "camera"] if isinstance(first, dict) else []  # LIDAR, SPEED, ...
        if "images" not in shared:  # first images: the learner sizes the shared blocks from them
            image = first["camera"] if isinstance(first, dict) else first
            self.remote.send(((len(agents),) + image.shape, tuple((key, first[key].shape) for key in vectors),
                              image.dtype.str))
            self.slot, specs = self.remote.recv()
            shared.update({name: SharedArray.attach(spec) for name, spec in specs.items()})
        images = shared["images"].array[self.slot]
        for k, agent in enumerate(agents):
            images[k] = obs[agent]["camera"] if vectors else obs[agent]
        for key in vectors:
            values = shared[VECTOR_PREFIX + key].array[self.slot]
            for k, agent in enumerate(agents):
                values[k] = obs[agent][key]

    def report(self, failure: RewardFunctionError) -> None:
        """Tell the learner why this worker stops (it raises it, once), instead of a traceback per worker."""
        if not self.info_keys:
            os.write(self.fd, FAILED)
        self.remote.send(str(failure))

def _checked(reply):
    """A worker's reply, or the RewardFunctionError it reported (a message: infos are lists)."""
    if isinstance(reply, str):
        raise RewardFunctionError(reply)
    return reply


class SubprocVectorEnv:
    """`len(make_envs)` race envs in worker processes, stepped in lock-step.

    `spin_wait`: seconds each worker polls for its next command before it sleeps (see the module docstring).
    """

    def __init__(self, make_envs: Sequence[Callable], info_keys: Sequence[str] = DEFAULT_INFO_KEYS,
                 spin_wait: float = SPIN_WAIT):
        context = mp.get_context("spawn")  # PyBullet clients must not be forked
        self.info_keys = tuple(info_keys)
        self.remotes, self.processes = [], []
        for make_env in make_envs:
            parent, child = context.Pipe()
            process = context.Process(target=_worker, args=(child, make_env, self.info_keys, spin_wait), daemon=True)
            process.start()
            child.close()
            self.remotes.append(parent)
            self.processes.append(process)
        self.num_envs = len(make_envs)
        # images (E, A, H, W, C), per vector sensor "vector:KEY" (E, A, ...), rewards (E, A), flags (E, 2), actions
        self.shared: dict = {}

    def _share_buffers(self) -> None:
        """Answer every worker's first images with shared blocks sized by them (all envs alike)."""
        shapes = [tuple(remote.recv()) for remote in self.remotes]
        if len(set(shapes)) != 1:
            raise ValueError(f"vector env: the envs' cars, camera images or sensors differ: {shapes}")
        images, vectors, dtype = shapes[0]
        cars = images[0]
        E = self.num_envs
        self.shared = {"images": SharedArray((E,) + images, dtype),
                       "rewards": SharedArray((E, cars), np.float32), "flags": SharedArray((E, 2), bool)}
        for key, shape in vectors:
            self.shared[VECTOR_PREFIX + key] = SharedArray((E, cars) + tuple(shape), np.float32)
        specs = {name: array.spec for name, array in self.shared.items()}
        for k, remote in enumerate(self.remotes):
            remote.send((k, specs))

    def _send_actions(self, actions) -> None:
        actions = np.asarray(actions)
        E, A = self.shared["rewards"].shape
        if actions.shape[:2] != (E, A):
            raise ValueError(f"vector env: actions of shape {actions.shape}, expected ({E}, {A}, ...)")
        integer = np.issubdtype(actions.dtype, np.integer)
        rows = actions.reshape(E, A, -1)
        if "actions" not in self.shared or self.shared["actions"].shape != rows.shape:
            if "actions" in self.shared:
                self.shared["actions"].close(unlink=True)
            self.shared["actions"] = SharedArray(rows.shape, np.float64)
            for remote in self.remotes:
                os.write(remote.fileno(), ACTIONS)
                remote.send((self.shared["actions"].spec, integer))
        self.shared["actions"].array[:] = rows

    def _send_commands(self, commands) -> None:
        """Write the commands block (made and sent to the workers on first use); None: every car takes actions."""
        if commands is None and "commands" not in self.shared:
            return
        if "commands" not in self.shared:
            self.shared["commands"] = SharedArray(self.shared["rewards"].shape + (2,), np.float64)
            for remote in self.remotes:
                os.write(remote.fileno(), COMMANDS)
                remote.send(self.shared["commands"].spec)
        self.shared["commands"].array[:] = np.nan if commands is None else commands

    def reset(self, seeds: Sequence[int | None] | None = None):
        """Reset every env; returns observations (see `_observations`) and per-env lists of small infos."""
        seeds = list(seeds) if seeds is not None else [None] * self.num_envs
        for remote, seed in zip(self.remotes, seeds):
            os.write(remote.fileno(), RESET)
            remote.send(seed)
        if not self.shared:
            self._share_buffers()
        infos = [_checked(remote.recv()) for remote in self.remotes]
        return self._observations(), infos

    def _observations(self):
        """Images (E, A, H, W, C), or with vector sensors {"camera": images, KEY: values (E, A, ...)}
        (KEY: "lidar", "speed", ...)."""
        images = self.shared["images"].array.copy()
        vectors = {name[len(VECTOR_PREFIX):]: array.array.copy() for name, array in self.shared.items()
                   if name.startswith(VECTOR_PREFIX)}
        return {"camera": images, **vectors} if vectors else images

    def step(self, actions, commands=None):
        """Step every env with `actions[e][car]` (integers for discrete actions, (E, A, D) floats otherwise);
        `commands` (E, A, 2), if given: (steering degrees, speed m/s) for the cars driven by commands, NaN for
        the cars that take their action.

        Returns observations (after auto-reset), rewards (E, A), dones (E,), truncated (E,), and the
        small infos of the step that was taken (before any reset).
        """
        self._send_actions(actions)
        self._send_commands(commands)
        for remote in self.remotes:
            os.write(remote.fileno(), STEP)
        if self.info_keys:
            infos = [_checked(remote.recv()) for remote in self.remotes]
        else:
            for k, remote in enumerate(self.remotes):
                reply = os.read(remote.fileno(), 1)
                if reply == FAILED:
                    _checked(remote.recv())
                if reply != DONE:
                    raise RuntimeError(f"vector env: worker {k} ended during a step (see its traceback above)")
            infos = [[{}] * self.shared["rewards"].shape[1]] * self.num_envs
        flags = self.shared["flags"].array
        return (self._observations(), self.shared["rewards"].array.copy(), flags[:, 0].copy(),
                flags[:, 1].copy(), infos)

    def shared_array(self, name: str, shape, dtype) -> SharedArray:
        """A new shared block `name` owned (and unlinked at close) by this vector env, for actors to fill."""
        if name in self.shared:
            self.shared.pop(name).close(unlink=True)
        self.shared[name] = SharedArray(shape, dtype)
        return self.shared[name]

    def attach_actors(self, factories: Sequence[Callable]) -> None:
        """Give each worker an actor: `factories[k](worker)`, built in worker k's process (picklable)."""
        for remote, factory in zip(self.remotes, factories):
            os.write(remote.fileno(), ACTOR)
            remote.send(factory)

    def act(self, payloads: Sequence) -> list:
        """Run every worker's actor on its payload, all at once; their results, in worker order."""
        for remote, payload in zip(self.remotes, payloads):
            os.write(remote.fileno(), ACT)
            remote.send(payload)
        return [_checked(remote.recv()) for remote in self.remotes]

    def worker_cpu_seconds(self) -> float | None:
        """CPU seconds (user + system) the worker processes have used so far; None where /proc is missing."""
        tick, total = os.sysconf("SC_CLK_TCK"), 0.0
        for process in self.processes:
            try:  # fields 14 and 15 of /proc/PID/stat, counted after the ")" that ends the command name
                fields = open(f"/proc/{process.pid}/stat").read().rsplit(")", 1)[1].split()
                total += (int(fields[11]) + int(fields[12])) / tick
            except (OSError, ValueError, IndexError):
                return None
        return total

    def close(self) -> None:
        for remote in self.remotes:
            try:
                os.write(remote.fileno(), CLOSE)
            except OSError:
                pass
        for process in self.processes:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
        for array in self.shared.values():
            array.close(unlink=True)
        self.shared = {}
