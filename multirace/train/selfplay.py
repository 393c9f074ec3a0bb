"""Opponent pool with prioritised fictitious self-play (PFSP, as in AlphaStar).

In every env, the first cars are the learner (shared parameters) and the last
``round(pool_fraction * cars)`` cars are driven by one opponent from the pool
for the whole PPO iteration; their samples do not train the learner. The pool
holds past snapshots of the learner (added every `snapshot_every` seconds,
the oldest dropped beyond `max_snapshots`) and the shipped agents in
``agents/*.pt`` whose camera matches. Opponents are drawn with PFSP weights
``(1 - p_win) ** power + eps``, where ``p_win`` is the learner's smoothed win
rate against that opponent (a win: the learner cars gained more reward per
car than the opponent cars over the iteration), so opponents the learner
loses to are met more often.

An opponent is a `Driver`: `drive` gives one car's command from its
observation (in any race), `drive_batch` many cars' commands in one net pass
(training: one pass per env), both through the opponent's own action space.
In training its cars' commands reach the env as commands
(`SubprocVectorEnv.step`'s `commands`), whatever the learner's action space.
"""
from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import torch

from ..environment.drivers import Driver
from .config import SHIPPED_AGENTS as SHIPPED_DIR


class Opponent(Driver):
    """A pool member: a policy net and its action space (`kind`: "snapshot" or "shipped"), and its record
    against the learner."""

    def __init__(self, name, net, space, kind):
        self.name, self.net, self.space, self.kind = name, net, space, kind
        self.wins, self.games = 1.0, 2.0  # prior: p_win 0.5

    def drive(self, state, car, observation=None) -> tuple[float, float]:
        """The opponent's greedy command for its car's observation: an image, or {"camera": image, key: values}
        with the sensors beside the camera its net reads."""
        if isinstance(observation, dict):
            batch = {key: np.asarray(value)[None] for key, value in observation.items()}
        else:
            batch = np.asarray(observation)[None]
        steer, speed = self.drive_batch(batch)[0]
        return float(steer), float(speed)

    def drive_batch(self, observations) -> np.ndarray:
        """Commands (N, 2) (steering degrees, speed m/s) for N cars' observations in one net pass: images
        (N, ...), or {"camera": images, key: values (N, n), ...}; each the greedy action of the opponent's space."""
        images = observations["camera"] if isinstance(observations, dict) else observations
        x = torch.from_numpy(np.ascontiguousarray(images))
        if self.net.vector_inputs:
            x = {"camera": x, **{key: torch.from_numpy(np.ascontiguousarray(observations[key]))
                                 for key in self.net.vector_inputs}}
        with torch.no_grad():
            out = self.net(x).numpy()
        return np.array([self.space.command(self.space.greedy(row)) for row in out], np.float64).reshape(-1, 2)

    @property
    def p_win(self) -> float:
        return self.wins / self.games


class OpponentPool:
    """See the module docstring."""

    def __init__(self, config, space, image_shape, rng, max_snapshots: int = 8, power: float = 2.0,
                 shipped_dir=SHIPPED_DIR, vector_inputs: dict | None = None):
        self.config, self.space, self.image_shape, self.rng = config, space, tuple(image_shape), rng
        self.vector_inputs = dict(vector_inputs or {})  # the envs' sensors beside the camera, {key: size}
        self.max_snapshots, self.power = int(max_snapshots), float(power)
        self.members: list[Opponent] = []
        self.last_snapshot = time.perf_counter()
        self.assigned: list[Opponent | None] = []
        self.scores = None
        self._load_shipped(shipped_dir)

    def _load_shipped(self, folder) -> None:
        from ..racing.agentfile import AgentFileError, load_agent

        for path in sorted(Path(folder).glob("*.pt")) if folder and Path(folder).is_dir() else []:
            try:
                agent = load_agent(path, step_budget=None)
            except (AgentFileError, OSError, ValueError):
                continue
            reads = agent.sensors.vector_inputs  # each one the envs give, at the size they give it
            if tuple(agent.image_shape) == self.image_shape and all(
                    self.vector_inputs.get(key) == size for key, size in reads.items()):
                self.members.append(Opponent(agent.name, agent.net, agent.action_space, "shipped"))

    # ------------------------------------------------------------ members
    def due(self, elapsed: float | None = None) -> bool:
        return time.perf_counter() - self.last_snapshot >= self.config.snapshot_every

    def add_snapshot(self, net, name: str) -> None:
        clone = copy.deepcopy(net).eval()
        self.members.append(Opponent(name, clone, self.space, "snapshot"))
        snapshots = [m for m in self.members if m.kind == "snapshot"]
        if len(snapshots) > self.max_snapshots:
            self.members.remove(snapshots[0])
        self.last_snapshot = time.perf_counter()

    def weights(self) -> np.ndarray:
        w = np.array([(1.0 - m.p_win) ** self.power + 0.02 for m in self.members])
        return w / w.sum()

    # ------------------------------------------------------ per iteration
    def opponent_cars(self, cars: int) -> int:
        return min(cars - 1, max(1, int(round(self.config.pool_fraction * cars)))) if cars > 1 else 0

    def assign(self, envs: int, cars: int) -> np.ndarray:
        """Score the last iteration, draw this iteration's opponent per env; the learner mask (E, A)."""
        self._score()
        mask = np.ones((envs, cars), bool)
        k = self.opponent_cars(cars)
        self.assigned = [None] * envs
        if self.members and k:
            p = self.weights()
            for e in range(envs):
                self.assigned[e] = self.members[int(self.rng.choice(len(self.members), p=p))]
                mask[e, cars - k:] = False
        self.mask = mask
        self.scores = np.zeros((envs, cars))
        return mask

    def commands(self, obs, mask: np.ndarray) -> np.ndarray | None:
        """The opponent cars' commands (E, A, 2), (steering degrees, speed m/s), NaN for the learner's cars;
        one `Opponent.drive_batch` per env with an opponent (None if no env has one).

        `obs`: images (E, A, H, W, C), or {"camera": images, key: values (E, A, n), ...}.
        """
        if all(opponent is None for opponent in self.assigned):
            return None
        commands = np.full(mask.shape + (2,), np.nan)
        for e, opponent in enumerate(self.assigned):
            if opponent is not None:
                cars = np.nonzero(~mask[e])[0]
                batch = {key: value[e, cars] for key, value in obs.items()} if isinstance(obs, dict) else obs[e, cars]
                commands[e, cars] = opponent.drive_batch(batch)
        return commands

    def observe(self, e: int, a: int, info: dict, reward: float = 0.0) -> None:
        if self.scores is not None:
            self.scores[e, a] += reward

    def episode_end(self, env_done) -> None:
        pass

    def _score(self) -> None:
        if self.scores is None:
            return
        for e, opponent in enumerate(self.assigned):
            if opponent is None:
                continue
            mine, theirs = self.scores[e][self.mask[e]], self.scores[e][~self.mask[e]]
            result = 1.0 if mine.mean() > theirs.mean() else 0.0
            opponent.wins = 0.95 * opponent.wins + result
            opponent.games = 0.95 * opponent.games + 1.0

    def summary(self) -> dict:
        if not self.members:
            return {"size": 0}
        p = self.weights()
        k = int(np.argmax(p))
        return {"size": len(self.members), "hardest": self.members[k].name,
                "p_win_vs_hardest": round(self.members[k].p_win, 2)}
