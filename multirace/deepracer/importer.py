"""`multirace agent import PATH --out FILE.pt`: a DeepRacer model as a multirace agent file.

PATH is a car archive (`.tar.gz` with one `.pb` and `model_metadata.json`), a
folder holding them, a frozen `.pb` with `model_metadata.json` beside it, or a
training checkpoint folder (DeepRacer's `model/`: the graph from the `.meta`, the
weights from the `.ckpt.index` + `.data`, see `checkpoint`).

The weights are found by walking the graph back from its output (the
``.../ppo_head_0/policy`` or ``.../sac_policy_head_0/policy`` node, else the
graph's only sink), not by names, which changed across DeepRacer versions:
``Const`` (through ``Identity``) into ``Conv2D`` / ``MatMul``, then
``BiasAdd`` (or ``Add``) with a constant, ``Relu``, the NHWC ``Reshape``
(flatten), ``ConcatV2`` of several sensors' embedders, the input scaling
(``RealDiv``/``Sub``/``Mul`` by constants) and the graph-only gradient
rescaler between middleware and head (``(1-r)*stop_gradient(x) + r*x``, which
is ``x``), which is skipped. The walk gives `GraphSpec`: per-sensor layer
lists, the layers after them, and the output op.

A graph whose layers are one of multirace's networks (`nets.NETWORKS`: DeepRacer's
shallow network, multirace's small and tiny CNNs; camera, or camera plus a
64-64 LIDAR branch) with a PPO head becomes a `CameraNet` agent file that every
multirace command loads. Other DeepRacer networks (5-layer, deep, SAC heads,
stereo cameras, DeepRacer's 256-256 LIDAR embedder) become a
`racing.graphnet.GraphNet` agent file (its layers in the metadata field
``deepracer_graph``, `drnet`), which races, leagues, `multirace.load_agent`
and export load like any other; only training cannot start from one.
"""
from __future__ import annotations

import json
import tarfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..environment.actions import ActionSpace, ActionSpaceError
from ..racing.agentfile import MAX_PARAMETERS, AgentFileError, make_metadata, net_sensors, save_agent
from ..racing.graphnet import GraphNet, plan
from ..racing.nets import NETWORKS, AveragePool, CameraNet, num_outputs_for, parameter_count
from ..sensors.registry import BY_KIND, BY_NAME, CAMERA_KEY
from .drnet import save_graph_agent, spec_from_graph
from .tfgraph import GraphError, Tensor, parse_graph

MAX_ARCHIVE_BYTES = 512 * 2**20  # unpacked members of a car archive read at most
MAX_ARCHIVE_MEMBERS = 10_000  # members of a car archive
ARCHIVE_SECONDS = 60.0  # reading a car archive may take this long
PASS_THROUGH = ("Identity", "StopGradient", "Snapshot")
WEIGHTED_OPS = {"Conv2D": 4, "MatMul": 2, "BiasAdd": 1}  # ops that take a constant: its number of dimensions
RESCALER_OPS = ("StridedSlice", "Sub", "VariableV2", "VarHandleOp", "ReadVariableOp")  # the factors r and 1-r
MAX_GRAPH_VALUES = MAX_PARAMETERS + 2**20  # constant values a walk may decode: the weights, and small constants
CONTINUOUS_LOG_STD = -1.0  # imported continuous policies: the log-std outputs (the .pb has no log-std)


class ModelImportError(ValueError):
    """A DeepRacer model that cannot be imported; the message names the file, node or field."""


class NotCameraNet(ModelImportError):
    """The graph is a valid DeepRacer network but not one of multirace's `CameraNet`s."""


@dataclass
class Chain:
    """Layers from the inputs to one node: a sensor's placeholder or the concatenated chains, then `layers`."""

    sensor: str | None = None
    shape: list | None = None
    branches: list = field(default_factory=list)
    layers: list = field(default_factory=list)  # (kind, params) tuples


@dataclass
class GraphSpec:
    """The walked graph: `inputs` {sensor: (shape, layers)}, then `layers` after their merge, then `output`."""

    inputs: dict
    layers: list
    output: str  # "softmax", "identity" or "tanh"
    output_node: str


class _Walker:
    def __init__(self, nodes, source, variables=None):
        self.nodes, self.source, self.variables = nodes, source, variables
        self._values: dict = {}  # Const node name -> its decoded array (each decoded once)
        self._decoded = 0  # values decoded so far, within MAX_GRAPH_VALUES

    def _follow(self, name, through, packs=False):
        """The node `name` reaches through the pass-through ops `through` (and packs of one tensor, with
        `packs`); None if it reaches nothing; a cycle is a ModelImportError naming the node."""
        node = self.nodes.get(name)
        for _ in range(len(self.nodes) + 1):
            if node is None or not (node.op in through or packs and self._is_pack_of_one(node)):
                return node
            node = self.nodes.get(node.inputs[0]) if node.inputs else None
        raise ModelImportError(f"{self.source}: node {name!r}: its {'/'.join(through)} inputs form a cycle")

    def value(self, name):
        """The constant a node evaluates to (Const, or a checkpoint's variable, through Identity), else None.
        A constant is decoded when first used, sized first against what is left of `MAX_GRAPH_VALUES`."""
        node = self._follow(name, PASS_THROUGH + ("ReadVariableOp",))
        if node is not None and node.op in ("VariableV2", "VarHandleOp") and self.variables is not None:
            return self.variables[node.name] if node.name in self.variables else None
        if node is None or node.op != "Const" or not isinstance(node.attrs.get("value"), Tensor):
            return None
        if node.name not in self._values:
            tensor = node.attrs["value"]
            self._decoded += tensor.size()
            if self._decoded > MAX_GRAPH_VALUES:
                raise ModelImportError(f"{self.source}: node {node.name!r}: the graph's constants hold over "
                                       f"{MAX_GRAPH_VALUES:,} values (the parameter limit of an agent file)")
            self._values[node.name] = tensor.decode()
        return self._values[node.name]

    def _strip(self, name):
        node = self._follow(name, PASS_THROUGH, packs=True)
        if node is None:
            raise ModelImportError(f"{self.source}: node {name!r} is referenced but not in the graph (or reads "
                                   "one that is not)")
        return node.name

    @staticmethod
    def _is_pack_of_one(node) -> bool:
        return node.op == "Pack" and len(node.inputs) == 1

    def _is_unpack(self, node) -> bool:
        """`x[0]` of a tensor packed into a new first axis (the head's StridedSlice after the rescaler)."""
        if node.op != "StridedSlice" or node.attrs.get("shrink_axis_mask") != 1 or len(node.inputs) < 2:
            return False
        begin = self.value(node.inputs[1])
        return begin is not None and np.asarray(begin).ravel().tolist() == [0]

    def _variable_input(self, node):
        inputs = [i for i in node.inputs if self.value(i) is None]
        constants = [self.value(i) for i in node.inputs if self.value(i) is not None]
        return inputs, constants

    def _rescaler_source(self, node):
        """The x of `(1-r)*stop_gradient(x) + r*x` (an Add of two Muls reaching the same node), else None."""
        sources = set()
        for name in node.inputs:
            mul = self.nodes.get(self._strip(name))
            if mul is None or mul.op != "Mul":
                return None
            for i in mul.inputs:
                if self.value(i) is None and self.nodes[self._strip(i)].op not in RESCALER_OPS:
                    sources.add(self._strip(i))
        return sources.pop() if len(sources) == 1 else None

    def walk(self, name, depth=0) -> Chain:
        if depth > 200:
            raise ModelImportError(f"{self.source}: the graph is deeper than 200 layers at node {name!r}")
        node = self.nodes.get(name)
        if node is None:
            raise ModelImportError(f"{self.source}: node {name!r} is referenced but not in the graph")
        op, where = node.op, f"{self.source}: node {name!r} ({node.op})"
        if op == "Placeholder":
            sensor = name.rstrip("/").split("/")[-1]
            return Chain(sensor=sensor, shape=node.attrs.get("shape"))
        if op in PASS_THROUGH or self._is_pack_of_one(node) or self._is_unpack(node):
            return self.walk(node.inputs[0], depth + 1)
        if op in ("ConcatV2", "Concat"):
            inputs, _ = self._variable_input(node)
            return Chain(branches=[self.walk(i, depth + 1) for i in inputs])
        if op in ("Add", "AddV2") and all(self.value(i) is None for i in node.inputs):
            source = self._rescaler_source(node)
            if source is None:
                raise ModelImportError(f"{where}: an addition of two computed tensors is not a layer DeepRacer's "
                                   "networks have")
            return self.walk(source, depth + 1)
        if op in ("Reshape", "Flatten"):
            chain = self.walk(node.inputs[0], depth + 1)
            chain.layers.append(("flatten", {}))
            return chain
        inputs, constants = self._variable_input(node)
        if len(inputs) != 1:
            raise ModelImportError(f"{where}: expected one computed input, found {len(inputs)}")
        if op in ("Add", "AddV2") and not constants:
            raise ModelImportError(f"{where}: an addition with one input")
        if op in WEIGHTED_OPS and (len(constants) != 1 or np.ndim(constants[0]) != WEIGHTED_OPS[op]):
            raise ModelImportError(f"{where}: expected one constant of {WEIGHTED_OPS[op]} dimension(s), found "
                                   f"{[np.shape(c) for c in constants]}")
        chain = self.walk(inputs[0], depth + 1)
        layers = chain.layers
        if op in ("BiasAdd", "Add", "AddV2"):
            if not layers or layers[-1][0] not in ("conv", "dense") or "bias" in layers[-1][1]:
                if not layers or layers[-1][0] != "scale":
                    raise ModelImportError(f"{where}: a bias without a convolution or dense layer before it")
                layers[-1][1]["shift"] = layers[-1][1].get("shift", 0.0) + float(np.asarray(constants[0]).ravel()[0])
            else:
                layers[-1][1]["bias"] = np.asarray(constants[0], np.float32).reshape(-1)
        elif op == "Conv2D":
            if node.attrs.get("padding") != "VALID" or node.attrs.get("data_format", "NHWC") != "NHWC":
                raise ModelImportError(f"{where}: only VALID NHWC convolutions are supported")
            strides = _four(node.attrs.get("strides") or [1, 1, 1, 1], "strides", where)
            if strides[1] != strides[2]:
                raise ModelImportError(f"{where}: unequal strides {strides}")
            layers.append(("conv", {"kernel": np.asarray(constants[0], np.float32), "stride": int(strides[1])}))
        elif op == "MatMul":
            kernel = np.asarray(constants[0], np.float32)
            if node.attrs.get("transpose_b"):
                kernel = kernel.T
            layers.append(("dense", {"kernel": kernel}))
        elif op == "AvgPool":
            k, s = _four(node.attrs.get("ksize"), "ksize", where), _four(node.attrs.get("strides"), "strides", where)
            if k != s or k[1] != k[2] or node.attrs.get("padding") != "VALID":
                raise ModelImportError(f"{where}: only VALID pooling with stride equal to the window is supported")
            layers.append(("pool", {"k": int(k[1])}))
        elif op in ("Relu", "Tanh", "Softmax"):
            layers.append((op.lower(), {}))
        elif op in ("RealDiv", "Mul", "Sub") and len(constants) == 1 and np.asarray(constants[0]).size == 1:
            c = float(np.asarray(constants[0]).ravel()[0])
            if op == "RealDiv" and c == 0:
                raise ModelImportError(f"{where}: division by zero")
            scale = 1.0 / c if op == "RealDiv" else c if op == "Mul" else 1.0
            shift = -c if op == "Sub" else 0.0
            if layers and layers[-1][0] == "scale":
                prev = layers[-1][1]
                prev["scale"], prev["shift"] = prev["scale"] * scale, prev["shift"] * scale + shift
            else:
                layers.append(("scale", {"scale": scale, "shift": shift}))
        else:
            raise ModelImportError(f"{where}: op {op} is not one of DeepRacer's network layers")
        return chain


def _four(values, attribute: str, where: str) -> list:
    """A Conv2D or pooling attribute of four positive integers (NHWC), else a ModelImportError naming it."""
    if not isinstance(values, list) or len(values) != 4 or not all(isinstance(v, int) and 0 < v <= 4096
                                                                     for v in values):
        raise ModelImportError(f"{where}: attribute {attribute} is {str(values)[:80]}; expected 4 positive integers")
    return values


def output_node(nodes, source: str) -> str:
    """The policy output: DeepRacer's PPO or SAC `policy` node (the online network's in a training graph),
    else the graph's only sink."""
    policies = sorted((name for name in nodes if name.endswith(("ppo_head_0/policy", "sac_policy_head_0/policy"))),
                      key=lambda name: "/online/" not in name)
    if policies:
        return policies[0]
    consumed = {i for n in nodes.values() for i in n.inputs}
    sinks = [n for n in nodes if n not in consumed and nodes[n].op not in ("Const", "NoOp", "Placeholder")]
    if len(sinks) != 1:
        raise ModelImportError(f"{source}: no ppo_head_0/policy or sac_policy_head_0/policy node, and the graph has "
                           f"{len(sinks)} outputs ({', '.join(sinks[:4])})")
    return sinks[0]


def graph_spec(data: bytes, source: str, variables=None) -> GraphSpec:
    """Walk a frozen graph's bytes from the policy output (see the module docstring); with `variables` (a
    `checkpoint.Checkpoint`), the bytes are a training checkpoint's `.meta` and its weights come from there."""
    try:
        nodes = parse_graph(data, source, meta=variables is not None)
        out = output_node(nodes, source)
        top = _Walker(nodes, source, variables).walk(out)
    except GraphError as exc:
        raise ModelImportError(str(exc)) from None
    final = "identity"
    if top.layers and top.layers[-1][0] in ("softmax", "tanh"):
        final = top.layers.pop()[0]
    chains = top.branches if top.branches else []
    if not chains:  # one sensor: split its chain after the flatten (or keep all for a vector input)
        cut = next((k + 1 for k, (kind, _) in enumerate(top.layers) if kind == "flatten"), 0)
        chains = [Chain(sensor=top.sensor, shape=top.shape, layers=top.layers[:cut])]
        top = Chain(layers=top.layers[cut:])
    inputs = {}
    for chain in chains:
        if chain.sensor is None:
            raise ModelImportError(f"{source}: nested concatenations are not one of DeepRacer's networks")
        inputs[chain.sensor] = (chain.shape, chain.layers)
    return GraphSpec(inputs=dict(sorted(inputs.items())), layers=top.layers, output=final, output_node=out)


def _trunk_signature(net: CameraNet) -> list:
    sig = []
    for layer in net.conv:
        if isinstance(layer, AveragePool):
            sig.append(("pool", int(layer.kernel_size)))
        elif isinstance(layer, torch.nn.Conv2d):
            sig.append(("conv", tuple(layer.weight.shape), layer.stride[0]))
    return sig


def _graph_signature(layers) -> list:
    sig = []
    for kind, p in layers:
        if kind == "pool":
            sig.append(("pool", p["k"]))
        elif kind == "conv":
            sig.append(("conv", tuple(np.transpose(p["kernel"], (3, 2, 0, 1)).shape), p["stride"]))
    return sig


def _dense_stack(layers, source, what):
    """[(kernel, bias, relu)] of a list of dense and relu layers."""
    stack = []
    for kind, p in layers:
        if kind == "dense":
            stack.append([p["kernel"], p.get("bias", np.zeros(p["kernel"].shape[1], np.float32)), False])
        elif kind == "relu" and stack:
            stack[-1][2] = True
        else:
            raise NotCameraNet(f"{source}: {what}: a {kind} layer where only dense layers were expected")
    return stack


def to_camera_net(spec: GraphSpec, space: ActionSpace, source: str) -> CameraNet:
    """The `CameraNet` computing what the graph computes (multirace's output conventions)."""
    lidars = [s for s in spec.inputs if s in BY_NAME and BY_NAME[s].key != CAMERA_KEY]  # the registry's names
    cameras = [s for s in spec.inputs if s not in lidars]
    if len(cameras) != 1 or len(lidars) > 1:
        raise NotCameraNet(f"{source}: inputs {list(spec.inputs)}: multirace agents read one camera (and a LIDAR)")
    shape, cam_layers = spec.inputs[cameras[0]]
    height, width, channels = [int(v) for v in (shape or [-1, 120, 160, 1])[1:]]
    if channels not in (1, 3):
        raise NotCameraNet(f"{source}: {cameras[0]} has {channels} channels; multirace's networks read 1 or 3")
    scale = next((p for kind, p in cam_layers if kind == "scale"), {"scale": 1.0, "shift": 0.0})
    if abs(scale["scale"] * 255.0 - 1.0) > 1e-6 or abs(scale["shift"]) > 1e-9:
        raise NotCameraNet(f"{source}: the camera input is scaled by {scale['scale']} and shifted by "
                           f"{scale['shift']}; DeepRacer's networks (and multirace's) read pixels/255")
    flat_at = next((k for k, (kind, _) in enumerate(cam_layers) if kind == "flatten"), None)
    if flat_at is None or flat_at != len(cam_layers) - 1:
        raise NotCameraNet(f"{source}: the camera embedder has dense layers after its flatten "
                           "(DeepRacer's 5-layer or deep network), which no multirace network has")
    lidar_stack = []
    if lidars:
        lidar_shape, lidar_layers = spec.inputs[lidars[0]]
        lidar_stack = _dense_stack([layer for layer in lidar_layers if layer[0] != "scale"], source, "LIDAR embedder")
    post = _dense_stack(spec.layers, source, "middleware and head")
    if len(post) != 2 or not post[0][2] or post[1][2]:
        raise NotCameraNet(f"{source}: {len(post)} dense layers after the embedders (a SAC head or a deep "
                           "middleware); multirace networks have one hidden layer and the output layer")
    if spec.output == "tanh" or "sac_policy_head" in spec.output_node:
        raise NotCameraNet(f"{source}: a SAC policy (tanh-squashed mean) is not one of multirace's networks")
    outputs = num_outputs_for(space)
    lidar_samples = int(lidar_stack[0][0].shape[0]) if lidar_stack else 0
    if lidars and (BY_NAME[lidars[0]].kind != "lidar" or lidar_samples != BY_KIND["lidar"].inputs):
        raise NotCameraNet(f"{source}: {lidars[0]} with {lidar_samples} inputs; multirace's networks read the "
                           f"{BY_KIND['lidar'].inputs}-beam LIDAR")
    for network in NETWORKS:
        try:
            with torch.device("meta"):  # sized and matched before anything is allocated
                net = CameraNet(network, (height, width, channels), outputs, lidar_samples=lidar_samples)
        except ValueError:
            continue
        if _trunk_signature(net) != _graph_signature(cam_layers):
            continue
        if lidar_stack and [tuple(k.shape) for k, _, _ in lidar_stack] != [
                tuple(net.lidar[0].weight.T.shape), tuple(net.lidar[2].weight.T.shape)]:
            continue
        if post[0][0].shape != tuple(net.fc[0].weight.T.shape):
            continue
        if parameter_count(net) > MAX_PARAMETERS:
            raise ModelImportError(f"{source}: the {network} network on {height}x{width}x{channels} images has "
                                   f"{parameter_count(net):,} parameters, over the limit of {MAX_PARAMETERS:,}")
        net = CameraNet(network, (height, width, channels), outputs, lidar_samples=lidar_samples)
        _fill(net, cam_layers, lidar_stack, post, space, source)
        return net.eval()
    raise NotCameraNet(f"{source}: the camera layers {_graph_signature(cam_layers)} are not one of multirace's "
                       f"networks ({', '.join(NETWORKS)})")


def _fill(net: CameraNet, cam_layers, lidar_stack, post, space, source) -> None:
    convs = [p for kind, p in cam_layers if kind == "conv"]
    torch_convs = [m for m in net.conv if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        for module, p in zip(torch_convs, convs):
            module.weight.copy_(torch.from_numpy(np.transpose(p["kernel"], (3, 2, 0, 1))))
            module.bias.copy_(torch.from_numpy(p.get("bias", np.zeros(module.out_channels, np.float32))))
        for module, (kernel, bias, _) in zip((net.lidar[0], net.lidar[2]) if lidar_stack else (), lidar_stack):
            module.weight.copy_(torch.from_numpy(kernel.T))
            module.bias.copy_(torch.from_numpy(bias))
        feature_map = net.conv[:-1](torch.zeros(1, net.image_shape[2], *net.image_shape[:2])).shape[1:]
        c, h, w = feature_map
        kernel, bias, _ = post[0]
        conv_flat = c * h * w
        cam = torch.from_numpy(kernel[:conv_flat]).reshape(h, w, c, -1).permute(2, 0, 1, 3).reshape(conv_flat, -1)
        net.fc[0].weight.copy_(torch.cat([cam, torch.from_numpy(kernel[conv_flat:])], 0).T)
        net.fc[0].bias.copy_(torch.from_numpy(bias))
        kernel, bias, _ = post[1]
        weight, bias = torch.from_numpy(kernel.T), torch.from_numpy(bias)
        if space.discrete:
            if weight.shape[0] != len(space.actions):
                raise ModelImportError(f"{source}: the policy has {weight.shape[0]} outputs but model_metadata.json "
                                   f"lists {len(space.actions)} actions")
            net.head.weight.copy_(weight)
            net.head.bias.copy_(bias)
        else:
            if weight.shape[0] != 2:
                raise ModelImportError(f"{source}: a continuous policy has 2 outputs, this one {weight.shape[0]}")
            low, high = np.array(space.low), np.array(space.high)
            half = torch.tensor((high - low) / 2, dtype=torch.float32)
            centre = torch.tensor((high + low) / 2, dtype=torch.float32)
            net.head.weight.zero_()
            net.head.weight[:2] = weight * half[:, None]
            net.head.bias.copy_(torch.cat([bias * half + centre, torch.full((2,), CONTINUOUS_LOG_STD)]))


def _checkpoint_folder(path: Path) -> Path | None:
    """The folder holding a training checkpoint (`*.ckpt.index`), if `path` is or holds one."""
    for folder in (path, path / "model"):
        if folder.is_dir() and any(folder.glob("*.ckpt.index")) and not any(folder.glob("*.pb")):
            return folder
    return None


def read_model(path) -> tuple[bytes, dict, str]:
    """(graph bytes, model_metadata dict, source name) of a car archive, a folder or a `.pb` file."""
    path = Path(path)
    if path.is_file() and path.name.endswith((".tar.gz", ".tgz", ".tar")):
        graph, metadata_bytes, source = read_archive(path)
    else:
        pb = path
        if path.is_dir():
            found = sorted(path.rglob("*.pb"))
            if len(found) != 1:
                raise ModelImportError(f"{path}: holds {len(found)} .pb files; expected exactly one")
            pb = found[0]
        if not pb.is_file():
            raise ModelImportError(f"{path}: no such file")
        meta_path = next((p / "model_metadata.json" for p in (pb.parent, pb.parent.parent, path)
                          if (p / "model_metadata.json").is_file()), None)
        if meta_path is None:
            raise ModelImportError(f"{pb}: no model_metadata.json beside it")
        if pb.stat().st_size > MAX_ARCHIVE_BYTES or meta_path.stat().st_size > 2**20:
            raise ModelImportError(f"{pb}: larger than {MAX_ARCHIVE_BYTES // 2**20} MB (or its metadata over 1 MB)")
        graph, metadata_bytes, source = pb.read_bytes(), meta_path.read_bytes(), str(pb)
    return graph, _metadata(metadata_bytes, f"{source}: model_metadata.json"), source


def _metadata(data: bytes, where: str) -> dict:
    """A model_metadata.json's object; a one-line ModelImportError naming `where` otherwise."""
    try:
        metadata = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelImportError(f"{where} is not UTF-8 JSON ({exc})") from None
    except RecursionError:
        raise ModelImportError(f"{where} is nested too deeply") from None
    if not isinstance(metadata, dict):
        raise ModelImportError(f"{where} is not a JSON object")
    return metadata


def read_archive(path: Path) -> tuple[bytes, bytes, str]:
    """(graph bytes, model_metadata bytes, source) of a car archive, read member by member: each header's
    declared size is checked before its data is read or skipped (a member of gigabytes of zeros is refused,
    not decompressed), only the .pb and model_metadata.json are read, within `ARCHIVE_SECONDS`."""
    deadline, declared, found = time.monotonic() + ARCHIVE_SECONDS, 0, {}
    try:
        with tarfile.open(path) as tar:
            for count, member in enumerate(tar, 1):
                declared += max(member.size, 0)
                if declared > MAX_ARCHIVE_BYTES or count > MAX_ARCHIVE_MEMBERS:
                    raise ModelImportError(f"{path}: member {member.name!r}: the archive holds over "
                                           f"{MAX_ARCHIVE_BYTES // 2**20} MB or {MAX_ARCHIVE_MEMBERS} members")
                if time.monotonic() > deadline:
                    raise ModelImportError(f"{path}: not read within {ARCHIVE_SECONDS:g} s")
                kind = ".pb" if member.name.endswith(".pb") else "model_meta" if (
                    member.name.lstrip("./") == "model_metadata.json") else None
                if kind is None or not member.isfile():
                    continue
                if kind == "model_meta" and member.size > 2**20:
                    raise ModelImportError(f"{path}: model_metadata.json is larger than 1 MB")
                if kind in found:
                    what = ".pb" if kind == ".pb" else "model_metadata.json"
                    raise ModelImportError(f"{path}: holds at least 2 {what} files; a car archive holds exactly one")
                found[kind] = (member.name, tar.extractfile(member).read())
    except (tarfile.TarError, EOFError, OSError, zlib.error) as exc:
        raise ModelImportError(f"{path}: not a readable .tar.gz archive ({type(exc).__name__}: "
                               f"{str(exc)[:120] or 'truncated'})") from None
    if ".pb" not in found:
        raise ModelImportError(f"{path}: holds no .pb file; a car archive holds exactly one")
    if "model_meta" not in found:
        raise ModelImportError(f"{path}: no model_metadata.json at the archive's root")
    return found[".pb"][1], found["model_meta"][1], f"{path}:{found['.pb'][0]}"


def read_checkpoint(folder: Path):
    """(.meta bytes, model_metadata dict, source, Checkpoint) of a DeepRacer training `model/` folder."""
    from .checkpoint import Checkpoint, checkpoint_prefix

    try:
        prefix = checkpoint_prefix(folder)
        variables = Checkpoint(prefix)
    except GraphError as exc:
        raise ModelImportError(str(exc)) from None
    meta = Path(f"{prefix}.meta")
    metadata_path = next((p for p in (folder / "model_metadata.json", folder.parent / "model_metadata.json")
                          if p.is_file()), None)
    if not meta.is_file() or metadata_path is None:
        raise ModelImportError(f"{prefix}: a checkpoint needs its .meta graph and model_metadata.json beside it")
    if meta.stat().st_size > MAX_ARCHIVE_BYTES:
        raise ModelImportError(f"{meta}: larger than {MAX_ARCHIVE_BYTES // 2**20} MB")
    if metadata_path.stat().st_size > 2**20:
        raise ModelImportError(f"{metadata_path}: larger than 1 MB")
    return meta.read_bytes(), _metadata(metadata_path.read_bytes(), str(metadata_path)), str(prefix), variables


def import_model(path, out, name: str | None = None) -> Path:
    """Import the DeepRacer model at `path` (see the module docstring) as the agent file `out`.

    `path` may also be a training checkpoint folder (DeepRacer's `model/` with `.coach_checkpoint`,
    `NAME.ckpt.index`, `.data-*` and `.meta`, and model_metadata.json there or one folder up).
    """
    folder = _checkpoint_folder(Path(path))
    variables = None
    if folder is not None:
        graph, metadata, source, variables = read_checkpoint(folder)
    else:
        graph, metadata, source = read_model(path)
    try:
        space = ActionSpace(metadata, f"{source}: model_metadata.json")
    except ActionSpaceError as exc:
        raise ModelImportError(str(exc)) from None
    spec = graph_spec(graph, source, variables)
    name = name or Path(out).stem
    notes = {"imported_from": Path(str(path)).name, "training_algorithm": metadata.get("training_algorithm",
                                                                                       "clipped_ppo")}
    try:
        net = to_camera_net(spec, space, source)
    except NotCameraNet as exc:
        return _import_graph_net(spec, space, metadata, source, out, name, notes, reason=str(exc))
    agent_meta = make_metadata(space, net.network, name, net.image_shape,
                               version=str(metadata.get("version", "5")), training_algorithm="deepracer_import",
                               sensor=net_sensors(net).names, training=notes)
    return _saved(lambda: save_agent(out, net, agent_meta, verify=True), source)


def _import_graph_net(spec, space, metadata, source, out, name, notes, reason) -> Path:
    """A DeepRacer network that no multirace network matches, as a `graphnet.GraphNet` agent file."""
    try:
        layers, state = spec_from_graph(spec, source)
        parameters, _ = plan(layers)  # its size from the layers' shapes, before anything is built
        if parameters > MAX_PARAMETERS:
            raise ValueError(f"{parameters:,} parameters, over the limit of {MAX_PARAMETERS:,}")
        net = GraphNet(layers, space)
        net.load_state_dict(state, strict=True)
        net.eval()
        with torch.no_grad():
            blank = torch.zeros(1, *net.image_shape, dtype=torch.uint8)
            out_row = net({"camera": blank, "lidar": torch.zeros(1, net.lidar_samples)} if net.lidar_samples
                          else blank)
    except (ValueError, RuntimeError) as exc:
        raise ModelImportError(f"{source}: not a network multirace can run ({exc}; {reason})") from None
    if out_row.shape != (1, net.num_outputs):
        raise ModelImportError(f"{source}: the policy gives {out_row.shape[1]} outputs; model_metadata.json's "
                               f"{space.kind} action space needs {net.num_outputs}")
    height, width, channels = net.image_shape
    agent_meta = {"name": name, "sensor": sorted(spec.inputs),
                  "image": {"height": height, "width": width, "channels": channels},
                  "neural_network": metadata.get("neural_network", GraphNet.network),
                  "training_algorithm": "deepracer_import", "version": str(metadata.get("version", "5")),
                  "training": {**notes, "network": reason}, **space.to_metadata()}
    return _saved(lambda: save_graph_agent(out, net, agent_meta, verify=True), source)


def _saved(save, source: str) -> Path:
    """`save()`'s path; an agent file that no loader would read (non-finite weights, over the parameter or
    metadata limits...) is refused with the loader's reason before anything is written."""
    try:
        return save()
    except AgentFileError as exc:
        raise ModelImportError(f"{source}: imported, but refused before writing: {exc}") from None
