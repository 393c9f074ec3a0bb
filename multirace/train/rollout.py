"""Rollout storage of the PPO loop: T steps of N cars, their advantages, and the learner's batch."""
from __future__ import annotations

import math

import numpy as np
import torch

from ..sensors.registry import CAMERA_KEY


def vector_sizes(obs) -> dict[str, int]:
    """{key: values per car} of the sensors beside the camera in a vector env's observations (the schema's
    `SensorSuite.vector_inputs`, as the env sends them); {} for bare images."""
    if not isinstance(obs, dict):
        return {}
    return {key: int(value.shape[-1]) for key, value in obs.items() if key != CAMERA_KEY}


def batch_input(net, batch: dict, rows):
    """The net's input for `rows` of a learner batch: its images, with the vectors the net reads beside them."""
    images = batch["obs"][rows]
    if not net.vector_inputs:
        return images
    return {CAMERA_KEY: images, **{key: batch[key][rows] for key in net.vector_inputs}}


class Rollout:
    """(T, N) buffers: uint8 images, the vectors of the sensors beside the camera ({key: size}, e.g. LIDAR
    ranges), actions, log-probs, rewards, dones, values, expert labels, and which cars' samples train the
    learner (opponent-pool cars do not)."""

    def __init__(self, steps: int, cars: int, obs_shape, vector_inputs: dict, space, obs_dtype=np.uint8):
        T, N = steps, cars
        self.steps, self.cars, self.obs_shape, self.vector_inputs = T, N, tuple(obs_shape), dict(vector_inputs)
        self.act_shape = () if space.discrete else (2,)
        act_dtype = torch.long if space.discrete else torch.float32
        self.obs = np.zeros((T, N, *obs_shape), obs_dtype)  # images, or a state policy's float vectors
        self.vectors = {key: np.zeros((T, N, size), np.float32) for key, size in self.vector_inputs.items()}
        self.act = torch.zeros((T, N, *self.act_shape), dtype=act_dtype)
        self.logp = torch.zeros((T, N))
        self.rew = torch.zeros((T, N))
        self.done = torch.zeros((T, N))
        self.val = torch.zeros((T, N))
        self.expert = torch.zeros((T, N, *self.act_shape), dtype=act_dtype)  # the pass driver's actions
        self.learn = np.zeros((T, N), bool)
        self.next_obs = None  # where the next rollout starts: the last observations, dones and expert labels
        self.next_done = torch.zeros(N)
        self.next_expert = None

    def start(self, obs, expert) -> None:
        """The envs' first observations (and the pass driver's labels for them)."""
        self.next_obs, self.next_expert = obs, expert

    def net_input(self, obs):
        """(E, A, ...) observations as the net's input for N cars: images, or images and their vectors."""
        if not self.vector_inputs:
            return torch.from_numpy(obs.reshape(self.cars, *self.obs_shape))
        return {CAMERA_KEY: torch.from_numpy(obs[CAMERA_KEY].reshape(self.cars, *self.obs_shape)),
                **{key: torch.from_numpy(obs[key].reshape(self.cars, size)) for key, size in self.vector_inputs.items()}}

    def store_input(self, t: int, x) -> None:
        """Keep step t's net input."""
        self.obs[t] = x[CAMERA_KEY] if self.vector_inputs else x
        for key, values in self.vectors.items():
            values[t] = x[key]

    def advantages(self, next_value, gamma: float, gae_lambda: float):
        """GAE advantages and returns, bootstrapped with the value of `next_obs`; a done at step t+1 means
        the episode ended with step t."""
        T, next_done = self.steps, self.next_done
        advantages = torch.zeros((T, self.cars))
        last = torch.zeros(self.cars)
        for t in reversed(range(T)):
            nonterminal = 1.0 - (next_done if t == T - 1 else self.done[t + 1])
            value_next = next_value if t == T - 1 else self.val[t + 1]
            delta = self.rew[t] + gamma * value_next * nonterminal - self.val[t]
            last = delta + gamma * gae_lambda * nonterminal * last
            advantages[t] = last
        return advantages, advantages + self.val

    def learner_batch(self, advantages, returns) -> dict:
        """The learner's samples, flattened: obs, each vector by its key (lidar, ...), act, logp, adv, ret, val,
        expert."""
        T, N = self.steps, self.cars
        keep = torch.from_numpy(self.learn.reshape(-1))
        return {"obs": torch.from_numpy(self.obs.reshape(T * N, *self.obs_shape))[keep],
                **{key: torch.from_numpy(values.reshape(T * N, values.shape[-1]))[keep]
                   for key, values in self.vectors.items()},
                "act": self.act.reshape(T * N, *self.act_shape)[keep],
                "logp": self.logp.reshape(-1)[keep], "adv": advantages.reshape(-1)[keep],
                "ret": returns.reshape(-1)[keep], "val": self.val.reshape(-1)[keep],
                "expert": self.expert.reshape(T * N, *self.act_shape)[keep]}


def expert_actions(infos, discrete: bool) -> torch.Tensor:
    """The scripted pass driver's action for every car's next observation (-1 / NaN: none)."""
    rows = [info.get("expert_action", -1 if discrete else [math.nan, math.nan])
            for env_infos in infos for info in env_infos]
    return torch.tensor(rows, dtype=torch.long if discrete else torch.float32)


def finished_episodes(infos, learner_mask) -> list[dict]:
    """The per-car training episodes that ended this step (return, laps, length, collisions caused...)."""
    return [{"return": info["ep_return"], "laps": info["ep_laps"], "length": info["ep_length"],
             "learner": bool(learner_mask[e, a]), "caused": info.get("ep_caused", 0),
             "perturbation": info["perturbation"]}
            for e, env_infos in enumerate(infos) for a, info in enumerate(env_infos) if info["train_done"]]
