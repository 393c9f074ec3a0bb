"""Actors (`TrainConfig.actors`): each env worker drives its own cars with a copy of the policy for a whole
rollout, so the learner does no per-step round trip and only updates.

The learner owns the shared blocks: the behaviour policy's weights (a flat float32 vector, written before
each rollout) and the rollout's (T, E, A, ...) arrays that every worker fills in its own slot: the net's
inputs, actions, log-probs, values (a row T+1 for the bootstrap value of the last observations), rewards and
the env-done flags. The per-step small infos (dones, episode figures, sim-trace rows) come back once per
rollout, in step order. Each worker samples its actions from its own torch generator, seeded from the run's
seed and the worker's index, so a seed still gives the same run.
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from ..environment.vector import SharedArray
from ..sensors.registry import CAMERA_KEY
from .policy import Policy, forward


def flat_weights(net) -> torch.Tensor:
    """Every tensor of the net's state, flattened into one float32 vector (the order of `state_dict`)."""
    return torch.cat([value.detach().reshape(-1).float() for value in net.state_dict().values()])


def load_flat_weights(net, flat) -> None:
    """Load a `flat_weights` vector into a net of the same architecture."""
    state, start = net.state_dict(), 0
    for key, value in state.items():
        size = value.numel()
        state[key] = torch.as_tensor(flat[start:start + size]).reshape(value.shape).to(value.dtype)
        start += size
    net.load_state_dict(state)


class RolloutActor:
    """One worker's cars, driven for `steps` steps by its copy of the policy (built in the worker process).

    `spec`: the `net` (a copy of the learner's: its architecture; its weights come with each rollout), the
    action `space`, `pooled` (the workers send pooled images), `seed`, and the shared blocks' specs (`weights`,
    `buffers`)."""

    def __init__(self, worker, spec: dict):
        self.worker = worker
        self.net = spec["net"].eval()
        self.policy, self.pooled, self.vectors = Policy(spec["space"]), spec["pooled"], tuple(self.net.vector_inputs)
        self.generator = torch.Generator().manual_seed(int(spec["seed"]))
        self.weights = SharedArray.attach(spec["weights"])
        self.blocks = {name: SharedArray.attach(block) for name, block in spec["buffers"].items()}  # kept: mapped
        self.buffers = {name: block.array for name, block in self.blocks.items()}
        self.version = None

    def net_input(self, obs):
        """The worker's observations (per agent) as the net's input for its cars."""
        agents = self.worker.agents
        if not self.vectors:
            return torch.from_numpy(np.stack([obs[a] for a in agents]))
        return {CAMERA_KEY: torch.from_numpy(np.stack([obs[a][CAMERA_KEY] for a in agents])),
                **{key: torch.from_numpy(np.stack([obs[a][key] for a in agents]).astype(np.float32))
                   for key in self.vectors}}

    def __call__(self, payload: tuple) -> list:
        """Run `steps` steps with the weights of `version` (loaded if new); the small infos of each step."""
        steps, version = payload
        if version != self.version:
            load_flat_weights(self.net, self.weights.array)
            self.version = version
        worker, b, slot = self.worker, self.buffers, self.worker.slot
        step_infos = []
        for t in range(steps):
            x = self.net_input(worker.obs)
            with torch.inference_mode():
                out, value = forward(self.net, x, self.pooled)
                action, logp = self.policy.sample(out, self.generator)
            b["logp"][t, slot] = logp.numpy()
            b["obs"][t, slot] = (x[CAMERA_KEY] if self.vectors else x).numpy()
            for key in self.vectors:
                b["vector:" + key][t, slot] = x[key].numpy()
            b["act"][t, slot] = action.numpy().reshape(b["act"].shape[2:])
            b["val"][t, slot] = value.reshape(-1).numpy()
            rewards, done, _, infos = worker.advance(action.tolist())
            b["rew"][t, slot] = rewards
            b["env_done"][t, slot] = done
            step_infos.append(infos)
        with torch.inference_mode():
            b["val"][steps, slot] = forward(self.net, self.net_input(worker.obs), self.pooled)[1].reshape(-1).numpy()
        return step_infos


class Actors:
    """The learner's side: the shared weights and rollout blocks, and the actors attached to `vec`'s workers."""

    def __init__(self, vec, net, space, rollout, pooled: bool, seed: int):
        E, T = vec.num_envs, rollout.steps
        A = rollout.cars // E
        self.vec, self.steps, self.version = vec, T, 0
        self.weights = vec.shared_array("actor:weights", flat_weights(net).shape, np.float32)
        act_dtype = np.int64 if space.discrete else np.float32
        blocks = {"obs": ((T, E, A, *rollout.obs_shape), rollout.obs.dtype),
                  "act": ((T, E, A, *rollout.act_shape), act_dtype),
                  "logp": ((T, E, A), np.float32), "val": ((T + 1, E, A), np.float32),
                  "rew": ((T, E, A), np.float32), "env_done": ((T, E), bool),
                  **{"vector:" + key: ((T, E, A, size), np.float32) for key, size in rollout.vector_inputs.items()}}
        self.buffers = {name: vec.shared_array("actor:" + name, shape, dtype)
                        for name, (shape, dtype) in blocks.items()}
        spec = {"net": net,  # pickled to each worker: a copy
                "space": space, "pooled": pooled,
                "weights": self.weights.spec, "buffers": {name: block.spec for name, block in self.buffers.items()}}
        vec.attach_actors([functools.partial(RolloutActor, spec={**spec, "seed": seed * 1000 + 17 * e + 1})
                           for e in range(E)])

    def run(self, net) -> tuple[dict, list]:
        """A rollout by every worker with `net`'s weights: ({block name: (T, E, A, ...) array}, the small infos
        of each step as [t][env][car])."""
        self.weights.array[:] = flat_weights(net).numpy()
        self.version += 1
        per_worker = self.vec.act([(self.steps, self.version)] * self.vec.num_envs)
        infos = [[per_worker[e][t] for e in range(len(per_worker))] for t in range(self.steps)]
        return {name: block.array for name, block in self.buffers.items()}, infos
