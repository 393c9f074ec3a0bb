"""An RL teacher (learning by cheating, `train.teacher`): its network, its file, and the teacher as a driver.

The net is a Gaussian policy MLP over a car's privileged state (`environment.state.car_features`).
A teacher file is a torch weights-only archive: {"weights", "features", "hidden", "action_space",
"view", "training"} (``view``: the traffic its state lists, `state.STATE_VIEWS`; "all" where absent);
loading it runs no code. `TeacherDriver` drives a car from that state: DAgger's expert
(``teacher:PATH`` as an expert spec); `TeacherController` races one (the entrant ``teacher:PATH``).
"""
from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..environment.actions import load_action_space
from ..environment.drivers import Driver
from ..environment.state import CAR_FEATURES, STATE_VIEWS, car_features
from .entrant import TEACHER_PREFIX, Controller, file_sha256, teacher_spec


class StatePolicyNet(nn.Module):
    """Gaussian policy and value MLPs over the privileged state; outputs are commands in degrees and m/s.

    The mean is the action box's centre plus its half-range times a linear output, and the log-std a
    learned vector, so the net learns in units of the box whatever the space's range.
    """

    vector_inputs: dict = {}  # it reads the state vector alone, no sensors beside a camera (`rollout.batch_input`)

    def __init__(self, space, features: int = CAR_FEATURES, hidden: int = 128, view: str = "all"):
        super().__init__()
        if view not in STATE_VIEWS:
            raise ValueError(f"teacher view: expected one of {', '.join(STATE_VIEWS)}, got {view!r}")
        self.view = view  # the traffic its state lists (`state.car_features`)
        if space.discrete:
            raise ValueError("the privileged teacher drives a continuous action space (steering and speed "
                             "ranges); give --action-space a continuous model_metadata.json")
        self.features, self.hidden, self.space = int(features), int(hidden), space
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
                "action_space": space.to_metadata(), "view": net.view, "training": training}, tmp)
    tmp.replace(path)
    return path


def load_teacher(path) -> StatePolicyNet:
    """A teacher file's net, ready to drive (weights-only load: no code runs)."""
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        space = load_action_space(saved["action_space"])
        net = StatePolicyNet(space, int(saved["features"]), int(saved["hidden"]), str(saved.get("view", "all")))
        net.load_state_dict(saved["weights"])
        net.training_notes = dict(saved.get("training") or {})
    except (OSError, KeyError, RuntimeError, ValueError, TypeError, pickle.UnpicklingError, EOFError) as exc:
        raise ValueError(f"teacher file {path}: not a readable teacher ({type(exc).__name__}: {exc})") from None
    if net.features != CAR_FEATURES:
        raise ValueError(f"teacher file {path}: reads {net.features} state values, this version gives {CAR_FEATURES}")
    return net.eval()


class TeacherDriver(Driver):
    """A teacher's state policy driving from its car's privileged state vector (the observation it reads), its
    commands within its action space's box; `speed_scale` < 1 asks for that share of the teacher's speed (a
    margin for a student that sees less)."""

    def __init__(self, net: StatePolicyNet, name: str, speed_scale: float = 1.0):
        if not 0.0 < speed_scale <= 1.0:
            raise ValueError(f"{name}: the speed scale must be in (0, 1], not {speed_scale:g}")
        self.net = net.eval()
        self.speed_scale = float(speed_scale)
        self.low, self.high = np.asarray(net.space.low, float), np.asarray(net.space.high, float)
        self.name = name + (f"@{speed_scale:g}" if speed_scale != 1.0 else "")

    @classmethod
    def load(cls, path, speed_scale: float = 1.0) -> "TeacherDriver":
        """The driver of a teacher file."""
        return cls(load_teacher(path), f"{TEACHER_PREFIX}{Path(path).name}", speed_scale)

    @property
    def view(self) -> str:
        """The traffic the state vectors it reads list (`state.STATE_VIEWS`)."""
        return self.net.view

    def drive(self, state, car, observation=None) -> tuple[float, float]:
        """The teacher's command from `observation`, its car's privileged state vector (of its `view`)."""
        return self.drive_many(observation[None])[0]

    def drive_many(self, observations: np.ndarray) -> list[tuple[float, float]]:
        """The teacher's commands for several cars' state vectors (N, features), in one pass of its net."""
        commands = self.net.command(observations).astype(float) * (1.0, self.speed_scale)
        return [tuple(command) for command in np.clip(commands, self.low, self.high).tolist()]


class TeacherController(Controller):
    """A teacher as a race entrant (``teacher:PATH``), driving from its car's privileged state: a research
    entrant (the DeepRacer car has none of its inputs), to race a student's teacher in heats or time trials."""

    def __init__(self, driver: TeacherDriver, sha256: str | None = None):
        self.driver, self.name, self.file_sha256 = driver, driver.name, sha256

    @classmethod
    def load(cls, spec: str) -> "TeacherController":
        """The entrant of ``teacher:PATH`` (``teacher:PATH@SCALE``: at that share of its speed)."""
        path, scale = teacher_spec(spec)
        return cls(TeacherDriver.load(path, scale), file_sha256(Path(path)))

    def act(self, observation, info) -> tuple[float, float]:
        return self.driver.drive(None, self.car, car_features(self.env, self.car, self.driver.view))
