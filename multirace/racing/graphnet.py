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

import math

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


MAX_ACTIVATIONS = 2**26  # values one inference of a GraphNet may compute, all layers together (256 MB)


def _planned_layers(layers: list, shape: tuple, where: str) -> tuple[tuple, int, int]:
    """(output shape, parameters, activation values) of `layers` applied to `shape` ((C, H, W) or (N,)),
    worked out from the spec alone; ValueError naming the layer that does not fit its input."""
    parameters = activations = 0
    for k, layer in enumerate(layers):
        kind, at = layer.get("type"), f"{where} layer {k} ({layer.get('type')})"
        if kind in ("conv", "dense") and not all(isinstance(layer[key], int) and layer[key] > 0
                                                 for key in ("in", "out")):
            raise ValueError(f"{at}: 'in' and 'out' must be positive integers")
        if kind in ("conv", "pool"):
            if len(shape) != 3:
                raise ValueError(f"{at}: needs an image, gets {shape}")
            c, h, w = shape
            size, stride = (layer["k"], layer["stride"]) if kind == "conv" else (layer["k"], layer["k"])
            if kind == "conv" and layer["in"] != c:
                raise ValueError(f"{at}: reads {layer['in']} channels, gets {c}")
            if not (isinstance(size, int) and isinstance(stride, int) and 0 < size <= min(h, w) and stride > 0):
                raise ValueError(f"{at}: a {size}x{size} window (stride {stride}) on a {h}x{w} input")
            shape = (layer["out"] if kind == "conv" else c, (h - size) // stride + 1, (w - size) // stride + 1)
            parameters += layer["out"] * (c * size * size + 1) if kind == "conv" else 0
        elif kind == "flatten":
            shape = (math.prod(shape),)
        elif kind == "dense":
            if shape != (layer["in"],):
                raise ValueError(f"{at}: reads {layer['in']} values, gets {shape}")
            shape = (layer["out"],)
            parameters += layer["out"] * (layer["in"] + 1)
        elif kind not in ("scale", "relu"):
            raise ValueError(f"{at}: unknown layer type")
        activations += math.prod(shape)
    return shape, parameters, activations


def plan(spec: dict) -> tuple[int, int]:
    """(parameters, activation values) of the network a spec describes, from its shapes alone: nothing is
    allocated, so a spec that would need gigabytes is refused by its numbers. ValueError naming the layer
    where the spec does not fit together, or saying that one inference would compute over `MAX_ACTIVATIONS`
    values."""
    try:
        widths, parameters, activations = 0, 0, 0
        for sensor in sorted(spec["inputs"]):
            dims = tuple(int(d) for d in spec["inputs"][sensor]["shape"])
            if any(d <= 0 for d in dims) or len(dims) not in (1, 3):
                raise ValueError(f"input {sensor}: shape {list(dims)}")
            shape = dims if len(dims) == 1 else (dims[2], dims[0], dims[1])
            out, p, a = _planned_layers(spec["inputs"][sensor]["layers"], shape, f"input {sensor}")
            if len(out) != 1:
                raise ValueError(f"input {sensor}: its layers end in {out}, not a vector")
            widths, parameters, activations = widths + out[0], parameters + p, activations + a + math.prod(dims)
        _, p, a = _planned_layers(spec["layers"], (widths,), "the layers after the inputs")
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{type(exc).__name__}: {exc}") from None
    if activations + a > MAX_ACTIVATIONS:
        raise ValueError(f"one inference computes {activations + a:,} values, over the limit of {MAX_ACTIVATIONS:,}")
    return parameters + p, activations + a


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
        self.vector_inputs = {"lidar": self.lidar_samples} if self.lidar_samples else {}  # as `CameraNet` names them
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
