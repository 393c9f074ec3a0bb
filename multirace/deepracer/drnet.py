"""A walked DeepRacer graph as a `racing.graphnet.GraphNet` agent file: its layer spec and weights.

`spec_from_graph` turns the layers that `importer` found by walking the frozen
graph back from its output into the JSON-able spec a `GraphNet` is built from
(TensorFlow's HWIO kernels and (in, out) dense matrices transposed to torch's);
`save_graph_agent` writes the agent file, the spec in its metadata.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..racing.agentfile import write_agent_file
from ..racing.graphnet import GRAPH_FIELD, LIDAR_SENSORS, GraphNet


def save_graph_agent(path, net: GraphNet, metadata: dict, verify: bool = False) -> Path:
    """Write `net` as an agent file whose metadata carries its spec (field ``deepracer_graph``); `verify`: see
    `agentfile.write_agent_file`."""
    return write_agent_file(path, {**metadata, GRAPH_FIELD: net.spec}, net, verify)


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
