"""`multirace agent export FILE.pt --out model.tar.gz`: an agent as the archive a DeepRacer car loads.

The archive holds exactly one frozen TensorFlow graph, `agent/model.pb`, and
`model_metadata.json` at its root (the car's loader walks the tree for the one
`.pb` and reads the metadata from the root). The graph is the agent's policy
network with the car's node names:

- inputs ``main_level/agent/main/online/network_0/{SENSOR}/{SENSOR}``, float32,
  raw 0-255 grey pixels ``[1, 120, 160, 1]`` for ``FRONT_FACING_CAMERA``
  (``[1, 120, 160, 2]`` for ``STEREO_CAMERAS``) and the ranges ``[1, N]`` for ``LIDAR``;
- the image normalisation (``/255``, ``-0``) inside the graph, as DeepRacer's
  embedder does (the car feeds raw pixels);
- the only output (the graph's only sink) ``main_level/agent/main/online/network_1/ppo_head_0/policy``:
  a softmax over the metadata's action list (discrete), or the two means in
  ``[-1, 1]`` that the car maps linearly onto the metadata's ``low..high`` (continuous).

Layers are named as DeepRacer's networks name them (``Conv2d_0``,
``BatchnormActivationDropout_1_activation``, ``Flatten/flatten/Reshape``,
``middleware_fc_embedder/Dense_0``, ``ppo_head_0/policy_fc``), convolutions are
VALID NHWC with HWIO kernels, and the flatten is NHWC's, so the graph computes
exactly what the torch policy computes. An imported DeepRacer network that
multirace runs as a `graphnet.GraphNet` (5-layer, deep, SAC, stereo) exports from
its layers the same way (`graph_net_graph`). An agent that reads a multirace
sensor DeepRacer's cars lack (``SPEED``, `Sensor.on_deepracer`) is refused.
"""
from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path

import numpy as np
import torch

from ..atomic import AtomicOutput
from ..racing.agentfile import load_agent, net_sensors
from ..racing.graphnet import GRAPH_FIELD, GraphNet
from ..racing.nets import AveragePool, CameraNet
from ..resources import resolve_agent_path
from ..sensors.suite import SensorSuite
from .tfgraph import DT_FLOAT, DT_INT32, GraphBuilder

CAMERA_SIZE = (120, 160)  # (height, width) the car's inference feeds
ROOT = "main_level/agent/main/online"
OUTPUT = f"{ROOT}/network_1/ppo_head_0/policy"
CAR_ALGORITHM = "clipped_ppo"  # the car's output name for PPO; every multirace policy head exports as one


class ExportError(ValueError):
    """An agent that a DeepRacer car cannot run as it is; the message names the file and the reason."""


def input_name(sensor: str) -> str:
    """The car's placeholder name for one sensor."""
    return f"{ROOT}/network_0/{sensor}/{sensor}"


def _dense(g: GraphBuilder, scope: str, x: str, weight: torch.Tensor, bias: torch.Tensor) -> str:
    kernel = g.const(f"{scope}/kernel", weight.detach().numpy().T)
    b = g.const(f"{scope}/bias", bias.detach().numpy())
    y = g.op(f"{scope}/MatMul", "MatMul", [x, kernel], transpose_a=False, transpose_b=False)
    return g.op(f"{scope}/BiasAdd", "BiasAdd", [y, b], data_format="NHWC")


def _camera_embedder(g: GraphBuilder, net: CameraNet, sensor: str, scope: str) -> tuple[str, tuple]:
    """Normalisation, the conv trunk and the NHWC flatten; returns (node, (H, W, C) of the last conv)."""
    height, width, channels = net.image_shape
    x = g.op(f"{scope}/truediv", "RealDiv", [input_name(sensor), g.const(f"{scope}/truediv/y", np.float32(255.0))])
    x = g.op(f"{scope}/sub", "Sub", [x, g.const(f"{scope}/sub/y", np.float32(0.0))])
    index = 0
    for layer in net.conv:
        if isinstance(layer, AveragePool):
            k = int(layer.kernel_size)
            x = g.op(f"{scope}/AvgPool", "AvgPool", [x], ksize=("ints", [1, k, k, 1]),
                     strides=("ints", [1, k, k, 1]), padding="VALID", data_format="NHWC")
        elif isinstance(layer, torch.nn.Conv2d):
            s = layer.stride[0]
            kernel = g.const(f"{scope}/Conv2d_{index}/kernel", layer.weight.detach().permute(2, 3, 1, 0).numpy())
            bias = g.const(f"{scope}/Conv2d_{index}/bias", layer.bias.detach().numpy())
            x = g.op(f"{scope}/Conv2d_{index}/Conv2D", "Conv2D", [x, kernel], strides=("ints", [1, s, s, 1]),
                     padding="VALID", data_format="NHWC", dilations=("ints", [1, 1, 1, 1]))
            x = g.op(f"{scope}/Conv2d_{index}/BiasAdd", "BiasAdd", [x, bias], data_format="NHWC")
        elif isinstance(layer, torch.nn.ReLU):
            x = g.op(f"{scope}/BatchnormActivationDropout_{index + 1}_activation", "Relu", [x])
            index += 2
    with torch.no_grad():
        out = net.conv[:-1](torch.zeros(1, channels, height, width))  # everything but the Flatten
    shape = (out.shape[2], out.shape[3], out.shape[1])
    flat = g.const(f"{scope}/Flatten/flatten/Reshape/shape", np.array([-1, int(np.prod(shape))], np.int32))
    x = g.node(f"{scope}/Flatten/flatten/Reshape", "Reshape", [x, flat], T=("type", DT_FLOAT),
               Tshape=("type", DT_INT32))
    return x, shape


def policy_graph(net: CameraNet, space, sensors: SensorSuite | None = None) -> bytes:
    """The frozen GraphDef bytes of `net`'s policy with the car's node names (see the module docstring);
    `sensors` (default: what the net reads, `net_sensors`) name its inputs: the camera, then each vector
    sensor (``LIDAR`` or ``SECTOR_LIDAR``) in the schema's order."""
    sensors = sensors if sensors is not None else net_sensors(net)
    height, width, channels = net.image_shape
    g = GraphBuilder()
    sensor = sensors.names[0]
    g.node(input_name(sensor), "Placeholder", dtype=("type", DT_FLOAT), shape=("shape", [-1, height, width, channels]))
    for vector in sensors.vectors:
        g.node(input_name(vector.name), "Placeholder", dtype=("type", DT_FLOAT), shape=("shape", [-1, vector.inputs]))
    net1 = f"{ROOT}/network_1"
    x, (h, w, c) = _camera_embedder(g, net, sensor, f"{net1}/{sensor}")
    fc = net.fc[0]
    weight = fc.weight.detach()
    conv_flat = h * w * c
    # torch flattens (C, H, W); the graph flattens NHWC (H, W, C): reorder the first dense layer's columns
    camera_cols = weight[:, :conv_flat].reshape(-1, c, h, w).permute(0, 2, 3, 1).reshape(-1, conv_flat)
    weight = torch.cat([camera_cols, weight[:, conv_flat:]], dim=1)
    embeddings = [x]
    for vector in sensors.vectors:
        scope = f"{net1}/{vector.name}"
        y = g.op(f"{scope}/sub", "Sub", [input_name(vector.name), g.const(f"{scope}/sub/y", np.float32(0.0))])
        branch = net.get_submodule(vector.key)
        for k in (0, 2):
            y = _dense(g, f"{scope}/Dense_{k}", y, branch[k].weight, branch[k].bias)
            y = g.op(f"{scope}/BatchnormActivationDropout_{k + 1}_activation", "Relu", [y])
        embeddings.append(y)
    if len(embeddings) > 1:
        axis = g.const(f"{net1}/concat/axis", np.int32(1))
        x = g.node(f"{net1}/concat", "ConcatV2", [*embeddings, axis], N=len(embeddings), T=("type", DT_FLOAT),
                   Tidx=("type", DT_INT32))
    x = _dense(g, f"{net1}/middleware_fc_embedder/Dense_0", x, weight, fc.bias)
    x = g.op(f"{net1}/middleware_fc_embedder/BatchnormActivationDropout_1_activation", "Relu", [x])
    head_w, head_b = net.head.weight.detach(), net.head.bias.detach()
    if space.discrete:
        logits = _dense(g, f"{net1}/ppo_head_0/policy_fc", x, head_w, head_b)
        g.op(OUTPUT, "Softmax", [logits])
    else:
        # the car maps v in [-1, 1] linearly onto low..high: fold mean -> v into the head's means
        low, high = np.array(space.low, np.float64), np.array(space.high, np.float64)
        half = np.where(high > low, (high - low) / 2, np.inf)
        scale = torch.tensor(1.0 / half, dtype=torch.float32)[:, None]
        mean_w = head_w[:2] * scale
        mean_b = (head_b[:2] - torch.tensor((low + high) / 2, dtype=torch.float32)) * scale[:, 0]
        mean = _dense(g, f"{net1}/ppo_head_0/policy_mean", x, mean_w, mean_b)
        g.op(OUTPUT, "Identity", [mean])
    return g.to_bytes()


def graph_net_graph(net) -> bytes:
    """The frozen GraphDef bytes of an imported DeepRacer network (`graphnet.GraphNet`), under PPO's names.

    A SAC policy's mean goes through ``tanh`` inside the graph, so that its output is a PPO head's
    ``[-1, 1]`` (what DeepRacer's simulator drove it with), which every car maps the same way.
    """
    g = GraphBuilder()
    state = {k: v.detach() for k, v in net.state_dict().items()}
    net1 = f"{ROOT}/network_1"
    embeddings = []

    def layers(spec, x, scope, prefix, feature):
        dense_index = 0
        for i, layer in enumerate(spec):
            kind, name = layer["type"], f"{scope}/layer_{i}"
            if kind == "scale":
                if abs(layer["scale"] * 255.0 - 1.0) < 1e-9:
                    x = g.op(f"{scope}/truediv", "RealDiv", [x, g.const(f"{scope}/truediv/y", np.float32(255.0))])
                else:
                    x = g.op(f"{scope}/mul", "Mul", [x, g.const(f"{scope}/mul/y", np.float32(layer["scale"]))])
                x = g.op(f"{scope}/sub", "Sub", [x, g.const(f"{scope}/sub/y", np.float32(-layer["shift"]))])
            elif kind == "conv":
                w, b = state[f"{prefix}.{i}.weight"], state[f"{prefix}.{i}.bias"]
                s = layer["stride"]
                x = g.op(f"{name}/Conv2D", "Conv2D", [x, g.const(f"{name}/kernel", w.permute(2, 3, 1, 0).numpy())],
                         strides=("ints", [1, s, s, 1]), padding="VALID", data_format="NHWC",
                         dilations=("ints", [1, 1, 1, 1]))
                x = g.op(f"{name}/BiasAdd", "BiasAdd", [x, g.const(f"{name}/bias", b.numpy())], data_format="NHWC")
            elif kind == "pool":
                k = layer["k"]
                x = g.op(f"{name}/AvgPool", "AvgPool", [x], ksize=("ints", [1, k, k, 1]),
                         strides=("ints", [1, k, k, 1]), padding="VALID", data_format="NHWC")
            elif kind == "relu":
                x = g.op(f"{name}/Relu", "Relu", [x])
            elif kind == "flatten":
                shape = g.const(f"{name}/Reshape/shape", np.array([-1, feature(i)], np.int32))
                x = g.node(f"{name}/Reshape", "Reshape", [x, shape], T=("type", DT_FLOAT), Tshape=("type", DT_INT32))
            elif kind == "dense":
                x = _dense(g, f"{scope}/Dense_{dense_index}", x, state[f"{prefix}.{i}.weight"],
                           state[f"{prefix}.{i}.bias"])
                dense_index += 1
        return x

    for sensor in net.sensors:
        spec = net.spec["inputs"][sensor]
        g.node(input_name(sensor), "Placeholder", dtype=("type", DT_FLOAT), shape=("shape", [-1, *spec["shape"]]))
        embedder = net.embedders[sensor]

        def feature(i, embedder=embedder, shape=spec["shape"]):
            with torch.no_grad():
                return int(embedder[:i + 1](torch.zeros(1, shape[2], shape[0], shape[1])).shape[1])

        embeddings.append(layers(spec["layers"], input_name(sensor), f"{net1}/{sensor}", f"embedders.{sensor}",
                                 feature))
    x = embeddings[0]
    if len(embeddings) > 1:
        axis = g.const(f"{net1}/concat/axis", np.int32(1))
        x = g.node(f"{net1}/concat", "ConcatV2", [*embeddings, axis], N=len(embeddings), T=("type", DT_FLOAT),
                   Tidx=("type", DT_INT32))
    x = layers(net.spec["layers"], x, f"{net1}/middleware_and_head", "post", None)
    if net.output == "softmax":
        g.op(OUTPUT, "Softmax", [x])
    else:
        g.op(OUTPUT, "Identity", [g.op(f"{net1}/ppo_head_0/tanh", "Tanh", [x]) if net.output == "sac" else x])
    return g.to_bytes()


def car_metadata(metadata: dict, space, sensors: SensorSuite) -> dict:
    """model_metadata.json as the car reads it (sensor, algorithm, action space), plus the agent's notes."""
    out = {k: v for k, v in metadata.items() if k not in ("action_space", "action_space_type")}
    out.update(sensor=sensors.names, training_algorithm=CAR_ALGORITHM, **space.to_metadata())
    out.setdefault("version", "5")
    return out


def export_agent(path, out) -> Path:
    """Write the car archive of the agent file at `path` (or a shipped agent's name) to `out` (a `.tar.gz`)."""
    path, out = resolve_agent_path(str(path)), Path(out)
    if not out.name.endswith(".tar.gz"):
        raise ExportError(f"{out}: the car accepts only archives named *.tar.gz")
    agent = load_agent(path, step_budget=None)
    graph_net = isinstance(agent.net, GraphNet)
    height, width, channels = agent.image_shape
    if (height, width) != CAMERA_SIZE or channels not in (1, 2):
        raise ExportError(f"{path}: the agent reads {height}x{width}x{channels} images; the car feeds "
                          f"{CAMERA_SIZE[0]}x{CAMERA_SIZE[1]} grey images (1 channel, 2 for stereo)")
    if not agent.sensors.on_deepracer:
        theirs = [sensor.name for sensor in agent.sensors.entries if not sensor.on_deepracer]
        raise ExportError(f"{path}: the agent reads {', '.join(theirs)} (metadata field 'sensor'), a multirace "
                          "sensor that DeepRacer's cars do not have")
    if graph_net:
        graph = graph_net_graph(agent.net)
        metadata = {k: v for k, v in agent.metadata.items() if k != GRAPH_FIELD}
        metadata = car_metadata(metadata, agent.action_space, agent.sensors)
        metadata["sensor"] = list(agent.net.sensors)
    else:
        graph = policy_graph(agent.net, agent.action_space, agent.sensors)
        metadata = car_metadata(agent.metadata, agent.action_space, agent.sensors)
    with AtomicOutput(out) as tmp, tarfile.open(tmp, "w:gz", compresslevel=6) as tar:
        for name, data in (("agent/model.pb", graph),
                           ("model_metadata.json", json.dumps(metadata, indent=4).encode())):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mode = 0o644
            tar.addfile(info, io.BytesIO(data))
    return out
