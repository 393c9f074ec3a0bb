"""`GraphNet`: any of DeepRacer's policy networks in torch, rebuilt from the layers of its frozen graph.

DeepRacer's 5-layer and deep networks, SAC's policy head and DeepRacer's own
LIDAR embedder have no counterpart among multirace's networks (`nets.NETWORKS`);
an imported model of that kind becomes a `GraphNet`: per-sensor embedders
(input scaling, VALID NHWC convolutions, ReLU, NHWC flatten, dense layers),
concatenated in sorted sensor order, then the dense layers after them and the
policy output. It keeps multirace's conventions (`nets` module docstring):
it takes uint8 images as `nets.channels_first` does (``{"camera", "lidar"}`` dicts with a LIDAR)
and gives action logits (discrete) or ``[mean steer deg, mean speed m/s,
log-std, log-std]`` (continuous; a PPO head's ``[-1, 1]`` output mapped
linearly onto the action space, a SAC head's mean through ``tanh`` first, as
DeepRacer's simulator does).

The architecture is a JSON-able `layers` spec (shapes only) kept in the agent
file's metadata under ``deepracer_graph``; the weights are the state_dict.
`load_graph_agent` reads such a file with the agent-file module's safe
reader. (For the agent-file loader itself to load it, it would build
``GraphNet(metadata["deepracer_graph"], ...)`` when that field is present
instead of a `CameraNet` from ``neural_network``.)
"""
from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..environment.actions import ActionSpace
from ..racing.agentfile import (Agent, AgentFileError, parse_metadata, read_agent_bytes, read_payload,
                                write_agent_file)
from ..racing.nets import CONTINUOUS_OUTPUTS, channels_first
from ..sensors.suite import parse_sensors

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


def save_graph_agent(path, net: GraphNet, metadata: dict) -> Path:
    """Write `net` as an agent file whose metadata carries its spec (field ``deepracer_graph``)."""
    return write_agent_file(path, {**metadata, "deepracer_graph": net.spec}, net)


def load_graph_agent(path) -> Agent:
    """An agent file holding a `GraphNet` (metadata field ``deepracer_graph``) as an agent-file `Agent`."""
    path = Path(path)
    payload = read_payload(path)
    metadata = parse_metadata(payload, str(path))
    spec = metadata.get("deepracer_graph")
    if not isinstance(spec, dict):
        raise AgentFileError(f"{path}: metadata field 'deepracer_graph' is missing (not an imported DeepRacer graph)")
    try:
        net = GraphNet(spec, ActionSpace(metadata, f"{path}: metadata"))
        net.load_state_dict(payload.get("state_dict") or {}, strict=True)
        sensors = parse_sensors(net.sensors, f"{path}: metadata field 'deepracer_graph' inputs")
    except (ValueError, KeyError, TypeError, RuntimeError) as exc:
        raise AgentFileError(f"{path}: metadata field 'deepracer_graph' does not match the weights ({exc})") from None
    net.eval()
    return Agent(path, net, metadata, net.space, hashlib.sha256(read_agent_bytes(path)).hexdigest(), sensors)


def spec_from_graph(graph_spec, source: str) -> tuple[dict, dict]:
    """(`layers` spec, state_dict) of a walked graph (`importer.GraphSpec`)."""
    state = {}

    def convert(layers, prefix):
        out = []
        for kind, p in layers:
            index = len(out)
            if kind == "scale":
                out.append({"type": "scale", "scale": p["scale"], "shift": p["shift"]})
            elif kind == "conv":
                kernel = np.transpose(p["kernel"], (3, 2, 0, 1))
                out.append({"type": "conv", "in": int(kernel.shape[1]), "out": int(kernel.shape[0]),
                            "k": int(kernel.shape[2]), "stride": p["stride"]})
                state[f"{prefix}.{index}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel))
                state[f"{prefix}.{index}.bias"] = torch.from_numpy(p.get("bias", np.zeros(kernel.shape[0], np.float32)))
            elif kind == "dense":
                kernel = p["kernel"]
                out.append({"type": "dense", "in": int(kernel.shape[0]), "out": int(kernel.shape[1])})
                state[f"{prefix}.{index}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.T))
                state[f"{prefix}.{index}.bias"] = torch.from_numpy(p.get("bias", np.zeros(kernel.shape[1], np.float32)))
            elif kind == "pool":
                out.append({"type": "pool", "k": p["k"]})
            elif kind in ("relu", "flatten"):
                out.append({"type": kind})
            else:
                raise ValueError(f"{source}: a {kind} layer inside the network")
        return out

    inputs = {}
    for sensor, (shape, layers) in graph_spec.inputs.items():
        dims = [int(v) for v in (shape or [])[1:]]
        if sensor not in LIDAR_SENSORS and len(dims) != 3:
            dims = [120, 160, 1]
        if any(d <= 0 for d in dims):
            raise ValueError(f"{source}: input {sensor} has an unknown shape {shape}")
        inputs[sensor] = {"shape": dims, "layers": convert(layers, f"embedders.{sensor}")}
    output = "sac" if "sac_policy_head" in graph_spec.output_node or graph_spec.output == "tanh" else (
        "softmax" if graph_spec.output == "softmax" else "ppo")
    spec = {"inputs": inputs, "layers": convert(graph_spec.layers, "post"), "output": output}
    if not math.isfinite(sum(float(v.abs().sum()) for v in state.values())):
        raise ValueError(f"{source}: the graph's weights are not finite")
    return spec, state
