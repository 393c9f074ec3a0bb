"""`GraphNet`: a DeepRacer policy network that none of `nets.NETWORKS` matches, from a layer spec.

DeepRacer's 5-layer and deep networks, SAC's policy head, stereo cameras and
DeepRacer's own LIDAR embedder have no counterpart among multirace's
networks; an imported model of that kind (`deepracer.importer`) runs as a
`GraphNet`: per-sensor embedders (input scaling, VALID NHWC convolutions,
ReLU, NHWC flatten, dense layers), concatenated in sorted sensor order, then
the dense layers after them and the policy output. It keeps multirace's
conventions (`nets` module docstring): it takes uint8 images in any layout
`nets.channels_first` accepts (``{"camera", "lidar"}`` dicts with a LIDAR)
and gives action logits (discrete) or ``[mean steer deg, mean speed m/s,
log-std, log-std]`` (continuous; a PPO head's ``[-1, 1]`` output mapped
linearly onto the action space, a SAC head's mean through ``tanh`` first, as
DeepRacer's simulator does).

The architecture is a JSON-able `layers` spec (shapes only) that an agent file
keeps in its metadata under ``deepracer_graph`` (`GRAPH_FIELD`); the weights
are its state_dict. The agent-file loader builds a `GraphNet` when that field
is present, so such agents race, league and export like any other.
"""
from __future__ import annotations

import torch
from torch import nn

from ..environment.actions import ActionSpace
from .nets import CONTINUOUS_OUTPUTS, channels_first

GRAPH_FIELD = "deepracer_graph"  # the metadata field holding a GraphNet's layer spec
LIDAR_SENSORS = ("LIDAR", "SECTOR_LIDAR")
LOG_STD = -1.0  # the continuous log-std outputs (a frozen policy graph has no log-std)


class _Scale(nn.Module):
    def __init__(self, scale: float, shift: float):
        super().__init__()
        self.scale, self.shift = float(scale), float(shift)

    def forward(self, x):
        return x * self.scale + self.shift


class _FlattenNHWC(nn.Module):
    def forward(self, x):
        return x.permute(0, 2, 3, 1).flatten(1)


def _module(layer: dict) -> nn.Module:
    kind = layer["type"]
    if kind == "scale":
        return _Scale(layer["scale"], layer["shift"])
    if kind == "conv":
        return nn.Conv2d(layer["in"], layer["out"], layer["k"], stride=layer["stride"])
    if kind == "pool":
        return nn.AvgPool2d(layer["k"])
    if kind == "dense":
        return nn.Linear(layer["in"], layer["out"])
    if kind == "relu":
        return nn.ReLU()
    if kind == "flatten":
        return _FlattenNHWC()
    raise ValueError(f"deepracer_graph: unknown layer type {kind!r}")


class GraphNet(nn.Module):
    """A DeepRacer policy network from a `layers` spec (see the module docstring)."""

    network = "DEEPRACER_GRAPH"

    def __init__(self, spec: dict, action_space: ActionSpace):
        super().__init__()
        self.spec, self.space = spec, action_space
        self.sensors = sorted(spec["inputs"])
        self.embedders = nn.ModuleDict({s: nn.Sequential(*map(_module, spec["inputs"][s]["layers"]))
                                        for s in self.sensors})
        self.post = nn.Sequential(*map(_module, spec["layers"]))
        self.output = spec["output"]  # softmax, ppo (linear [-1, 1]) or sac (tanh of the mean)
        cameras = [s for s in self.sensors if s not in LIDAR_SENSORS]
        lidars = [s for s in self.sensors if s in LIDAR_SENSORS]
        if len(cameras) != 1 or len(lidars) > 1:
            raise ValueError(f"deepracer_graph: inputs {self.sensors}: one camera and at most one LIDAR")
        self.camera, self.lidar_sensor = cameras[0], (lidars[0] if lidars else None)
        self.image_shape = tuple(spec["inputs"][self.camera]["shape"])
        self.lidar_samples = spec["inputs"][self.lidar_sensor]["shape"][0] if self.lidar_sensor else 0
        self.num_outputs = len(action_space.actions) if action_space.discrete else CONTINUOUS_OUTPUTS
        self.has_value = False

    def forward(self, obs) -> torch.Tensor:
        """Logits (discrete) or [mean steer, mean speed, log-std, log-std] for uint8 images (or dicts)."""
        ranges = None
        if isinstance(obs, dict):
            obs, ranges = obs["camera"], torch.as_tensor(obs["lidar"], dtype=torch.float32)
        x = channels_first(obs, self.image_shape)
        features = {self.camera: self.embedders[self.camera](x.float())}
        if self.lidar_sensor:
            if ranges is None:
                raise ValueError("this net needs {'camera': images, 'lidar': ranges} observations")
            features[self.lidar_sensor] = self.embedders[self.lidar_sensor](ranges.reshape(x.shape[0], -1))
        out = self.post(torch.cat([features[s] for s in self.sensors], dim=1))
        if self.space.discrete:
            return out
        if self.output == "sac":
            out = torch.tanh(out)
        low, high = (torch.tensor(v, dtype=torch.float32) for v in (self.space.low, self.space.high))
        mean = (low + high) / 2 + out * (high - low) / 2
        return torch.cat([mean, torch.full_like(mean, LOG_STD)], dim=1)
