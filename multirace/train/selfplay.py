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
"""
from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import torch

from .config import SHIPPED_AGENTS as SHIPPED_DIR


class Opponent:
    def __init__(self, name, net, space, kind):
        self.name, self.net, self.space, self.kind = name, net, space, kind
        self.wins, self.games = 1.0, 2.0  # prior: p_win 0.5

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

    def override(self, actions: np.ndarray, obs, mask: np.ndarray) -> np.ndarray:
        """Replace the opponent cars' actions by their opponent's greedy actions.

        `obs`: images (E, A, H, W, C), or {"camera": images, key: values (E, A, n), ...}.
        """
        actions = actions.copy()
        images = obs["camera"] if isinstance(obs, dict) else obs
        for e, opponent in enumerate(self.assigned):
            if opponent is None:
                continue
            cars = np.nonzero(~mask[e])[0]
            x = torch.from_numpy(np.ascontiguousarray(images[e, cars]))
            if opponent.net.vector_inputs:
                x = {"camera": x, **{key: torch.from_numpy(np.ascontiguousarray(obs[key][e, cars]))
                                     for key in opponent.net.vector_inputs}}
            with torch.no_grad():
                out = opponent.net(x).numpy()
            for row, a in zip(out, cars):
                if opponent.space.discrete:
                    command = opponent.space.command(int(np.argmax(row)))
                else:
                    command = opponent.space.command(row[:2])
                actions[e, a] = self.space.nearest(*command)
        return actions

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
