"""The teacher's network and its file: a Gaussian policy MLP over the privileged state (`environment.state`).

A teacher file is a torch weights-only archive: {"weights", "features", "hidden", "action_space",
"training"}; loading it runs no code.
"""
from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..environment.actions import load_action_space
from ..environment.state import CAR_FEATURES


class StatePolicyNet(nn.Module):
    """Gaussian policy and value MLPs over the privileged state; outputs are commands in degrees and m/s.

    The mean is the action box's centre plus its half-range times a linear output, and the log-std a
    learned vector, so the net learns in units of the box whatever the space's range.
    """

    vector_inputs: dict = {}  # it reads the state vector alone, no sensors beside a camera (`rollout.batch_input`)

    def __init__(self, space, features: int = CAR_FEATURES, hidden: int = 128):
        super().__init__()
        if space.discrete:
            raise ValueError("the privileged teacher drives a continuous action space (steering and speed "
                             "ranges); give --action-space a continuous model_metadata.json")
        self.features, self.hidden = int(features), int(hidden)
        self.trunk = nn.Sequential(nn.Linear(features, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh())
        self.mean = nn.Linear(hidden, 2)
        self.value_head = nn.Sequential(nn.Linear(features, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                        nn.Linear(hidden, 1))
        low, high = torch.tensor(space.low, dtype=torch.float32), torch.tensor(space.high, dtype=torch.float32)
        self.register_buffer("centre", (low + high) / 2)
        self.register_buffer("half_range", torch.clamp((high - low) / 2, min=1e-3))
        self.log_std = nn.Parameter(torch.full((2,), -math.log(2.0)))  # half a half-range to start
        with torch.no_grad():
            self.mean.weight.mul_(0.01)
            self.mean.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 4): mean steering, mean speed, log-std of each, in the action space's units."""
        mean = self.centre + self.half_range * self.mean(self.trunk(x))
        log_std = (torch.log(self.half_range) + self.log_std).expand_as(mean)
        return torch.cat([mean, log_std], dim=1)

    def forward_all(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.forward(x), self.value_head(x).squeeze(-1)

    def command(self, features: np.ndarray) -> np.ndarray:
        """Greedy (steering degrees, speed m/s) for a batch of state vectors (N, features)."""
        with torch.no_grad():
            return self.forward(torch.as_tensor(features, dtype=torch.float32))[:, :2].numpy()


def save_teacher(path, net: StatePolicyNet, space, training: dict) -> Path:
    """Write a teacher file (weights, sizes, action space and training notes), atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"weights": net.state_dict(), "features": net.features, "hidden": net.hidden,
                "action_space": space.to_metadata(), "training": training}, tmp)
    tmp.replace(path)
    return path


def load_teacher(path) -> StatePolicyNet:
    """A teacher file's net, ready to drive (weights-only load: no code runs)."""
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        space = load_action_space(saved["action_space"])
        net = StatePolicyNet(space, int(saved["features"]), int(saved["hidden"]))
        net.load_state_dict(saved["weights"])
    except (OSError, KeyError, RuntimeError, ValueError, TypeError, pickle.UnpicklingError, EOFError) as exc:
        raise ValueError(f"teacher file {path}: not a readable teacher ({type(exc).__name__}: {exc})") from None
    if net.features != CAR_FEATURES:
        raise ValueError(f"teacher file {path}: reads {net.features} state values, this version gives {CAR_FEATURES}")
    net.space = space
    return net.eval()
