"""Frozen TensorFlow GraphDef files (`model.pb`) written and read with protobuf alone.

The message types are TensorFlow's own (`graph.proto`, `node_def.proto`,
`attr_value.proto`, `tensor.proto`, `tensor_shape.proto`, `versions.proto`),
declared here field for field with the same numbers, so the bytes are the
ones TensorFlow, OpenVINO and the DeepRacer car read. Only the fields a frozen
inference graph uses are declared; unknown fields of other graphs are kept
by protobuf and ignored.

`GraphBuilder` adds nodes (constants, placeholders, ops) and serialises the
graph; `read_graph` parses a `.pb` into `{name: Node}` with attributes, and
constants as `Tensor`s decoded to NumPy arrays only when used
(`parse_graph(..., meta=True)`: the graph of a training checkpoint's `.meta`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

DT_FLOAT, DT_INT32 = 1, 3
_NUMPY = {DT_FLOAT: np.float32, DT_INT32: np.int32}
_DTYPE = {np.dtype(np.float32): DT_FLOAT, np.dtype(np.int32): DT_INT32}
MAX_CONST_ELEMENTS = 2**26  # values in one constant (a 256 MB float32 tensor)
MAX_ATTR_ITEMS = 64  # items of a list or shape attribute decoded (strides, ksize, shapes have 4 or so)
PRODUCER = 27  # a TF1-era GraphDef version (TF 1.13), which every converter accepts


def _messages():
    """The GraphDef message classes, declared with TensorFlow's field numbers (package `tensorflow`)."""
    F = descriptor_pb2.FieldDescriptorProto
    proto = descriptor_pb2.FileDescriptorProto(name="multirace_tf_graph.proto", package="tensorflow",
                                               syntax="proto3")

    OPT, REP = F.LABEL_OPTIONAL, F.LABEL_REPEATED

    def message(name, rows, nested=(), oneof=None):
        m = proto.message_type.add(name=name)
        m.nested_type.extend(nested)
        if oneof:
            m.oneof_decl.add(name=oneof)  # AttrValue's `value`: a False or 0 attribute is still written
        for number, fname, ftype, label, type_name in rows:
            f = m.field.add(name=fname, number=number, type=ftype, label=label)
            if type_name:
                f.type_name = type_name
            if oneof:
                f.oneof_index = 0

    dim = descriptor_pb2.DescriptorProto(name="Dim")
    dim.field.add(name="size", number=1, type=F.TYPE_INT64, label=OPT)
    dim.field.add(name="name", number=2, type=F.TYPE_STRING, label=OPT)
    message("TensorShapeProto", [
        (2, "dim", F.TYPE_MESSAGE, REP, ".tensorflow.TensorShapeProto.Dim"),
        (3, "unknown_rank", F.TYPE_BOOL, OPT, None)], nested=[dim])
    message("TensorProto", [
        (1, "dtype", F.TYPE_INT32, OPT, None),
        (2, "tensor_shape", F.TYPE_MESSAGE, OPT, ".tensorflow.TensorShapeProto"),
        (3, "version_number", F.TYPE_INT32, OPT, None),
        (4, "tensor_content", F.TYPE_BYTES, OPT, None),
        (5, "float_val", F.TYPE_FLOAT, REP, None),
        (7, "int_val", F.TYPE_INT32, REP, None)])
    lst = descriptor_pb2.DescriptorProto(name="ListValue")
    for number, fname, ftype in ((2, "s", F.TYPE_BYTES), (3, "i", F.TYPE_INT64), (4, "f", F.TYPE_FLOAT),
                                 (5, "b", F.TYPE_BOOL), (6, "type", F.TYPE_INT32)):
        lst.field.add(name=fname, number=number, type=ftype, label=REP)
    message("AttrValue", [
        (1, "list", F.TYPE_MESSAGE, OPT, ".tensorflow.AttrValue.ListValue"),
        (2, "s", F.TYPE_BYTES, OPT, None),
        (3, "i", F.TYPE_INT64, OPT, None),
        (4, "f", F.TYPE_FLOAT, OPT, None),
        (5, "b", F.TYPE_BOOL, OPT, None),
        (6, "type", F.TYPE_INT32, OPT, None),
        (7, "shape", F.TYPE_MESSAGE, OPT, ".tensorflow.TensorShapeProto"),
        (8, "tensor", F.TYPE_MESSAGE, OPT, ".tensorflow.TensorProto")], nested=[lst], oneof="value")
    entry = descriptor_pb2.DescriptorProto(name="AttrEntry")
    entry.field.add(name="key", number=1, type=F.TYPE_STRING, label=OPT)
    entry.field.add(name="value", number=2, type=F.TYPE_MESSAGE, label=OPT, type_name=".tensorflow.AttrValue")
    entry.options.map_entry = True
    message("NodeDef", [
        (1, "name", F.TYPE_STRING, OPT, None),
        (2, "op", F.TYPE_STRING, OPT, None),
        (3, "input", F.TYPE_STRING, REP, None),
        (4, "device", F.TYPE_STRING, OPT, None),
        (5, "attr", F.TYPE_MESSAGE, REP, ".tensorflow.NodeDef.AttrEntry")], nested=[entry])
    message("VersionDef", [
        (1, "producer", F.TYPE_INT32, OPT, None),
        (2, "min_consumer", F.TYPE_INT32, OPT, None)])
    message("GraphDef", [
        (1, "node", F.TYPE_MESSAGE, REP, ".tensorflow.NodeDef"),
        (4, "versions", F.TYPE_MESSAGE, OPT, ".tensorflow.VersionDef")])
    message("MetaGraphDef", [(2, "graph_def", F.TYPE_MESSAGE, OPT, ".tensorflow.GraphDef")])  # a checkpoint's .meta
    message("BundleHeaderProto", [(1, "num_shards", F.TYPE_INT32, OPT, None)])  # a checkpoint .index's header
    message("BundleEntryProto", [  # one tensor of a checkpoint's .index
        (1, "dtype", F.TYPE_INT32, OPT, None),
        (2, "shape", F.TYPE_MESSAGE, OPT, ".tensorflow.TensorShapeProto"),
        (3, "shard_id", F.TYPE_INT32, OPT, None),
        (4, "offset", F.TYPE_INT64, OPT, None),
        (5, "size", F.TYPE_INT64, OPT, None)])
    pool = descriptor_pool.DescriptorPool()
    pool.Add(proto)
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"tensorflow.{name}"))
            for name in ("GraphDef", "NodeDef", "AttrValue", "TensorProto", "TensorShapeProto", "MetaGraphDef",
                         "BundleHeaderProto", "BundleEntryProto")}


_M = _messages()
GraphDef, MetaGraphDef = _M["GraphDef"], _M["MetaGraphDef"]
BundleHeaderProto, BundleEntryProto = _M["BundleHeaderProto"], _M["BundleEntryProto"]


class GraphError(ValueError):
    """A .pb is not a frozen GraphDef this reader understands; the message names the file and node."""


def _tensor(array: np.ndarray):
    array = np.asarray(array)
    if array.dtype not in _DTYPE:
        array = array.astype(np.float32 if array.dtype.kind == "f" else np.int32)
    if array.ndim == 0:  # scalars as TensorFlow writes them: in the typed value field
        t = _M["TensorProto"](dtype=_DTYPE[array.dtype])
        (t.float_val if array.dtype == np.float32 else t.int_val).append(array.item())
        return t
    t = _M["TensorProto"](dtype=_DTYPE[array.dtype], tensor_content=np.ascontiguousarray(array).tobytes())
    for size in array.shape:
        t.tensor_shape.dim.add(size=int(size))
    return t


class GraphBuilder:
    """Builds a frozen inference graph node by node; `to_bytes()` is the `.pb` content."""

    def __init__(self):
        self.graph = GraphDef()
        self.graph.versions.producer = PRODUCER

    def node(self, name: str, op: str, inputs=(), **attrs) -> str:
        """Add a node; attrs: int, float, bool, bytes/str, ("type", DT), ("shape", dims), ("ints", [..]), ndarray."""
        n = self.graph.node.add(name=name, op=op)
        n.input.extend(inputs)
        for key, value in attrs.items():
            a = n.attr[key]
            if isinstance(value, np.ndarray):
                a.tensor.CopyFrom(_tensor(value))
            elif isinstance(value, tuple) and value[0] == "type":
                a.type = value[1]
            elif isinstance(value, tuple) and value[0] == "shape":
                for size in value[1]:
                    a.shape.dim.add(size=int(size))
            elif isinstance(value, tuple) and value[0] == "ints":
                a.list.i.extend(int(v) for v in value[1])
            elif isinstance(value, bool):
                a.b = value
            elif isinstance(value, int):
                a.i = value
            elif isinstance(value, float):
                a.f = value
            elif isinstance(value, (str, bytes)):
                a.s = value.encode() if isinstance(value, str) else value
            else:
                raise TypeError(f"node {name}: attribute {key}={value!r} has no GraphDef form")
        return name

    def const(self, name: str, value) -> str:
        """A Const node holding `value` (float32 or int32), read through an Identity like a frozen variable."""
        value = np.asarray(value)
        dtype = DT_FLOAT if value.dtype.kind == "f" else DT_INT32
        self.node(name, "Const", value=value.astype(_NUMPY[dtype]), dtype=("type", dtype))
        return self.node(f"{name}/read", "Identity", [name], T=("type", dtype))

    def op(self, name: str, op: str, inputs, **attrs) -> str:
        """A float32 op node."""
        return self.node(name, op, inputs, T=("type", DT_FLOAT), **attrs)

    def to_bytes(self) -> bytes:
        return self.graph.SerializeToString()


@dataclass
class Node:
    """One node of a parsed graph: its op, input node names (without ports) and decoded attributes."""

    name: str
    op: str
    inputs: list[str]
    attrs: dict = field(default_factory=dict)


class Tensor:
    """A constant's TensorProto, decoded only when a walk uses it (`decode`): an unused constant costs nothing,
    and a used one is sized from its shape, against a budget, before anything is allocated."""

    def __init__(self, proto, where: str):
        self.proto, self.where = proto, where

    def size(self) -> int:
        """The number of values the constant declares; GraphError for a negative or over-limit shape."""
        shape = [d.size for d in self.proto.tensor_shape.dim]
        if any(d < 0 for d in shape) or math.prod(shape) > MAX_CONST_ELEMENTS:
            raise GraphError(f"{self.where}: a constant of shape {shape} (at most {MAX_CONST_ELEMENTS:,} values)")
        return math.prod(shape)

    def decode(self):
        """The constant as a NumPy array (None for a dtype other than float32 and int32)."""
        t = self.proto
        dtype = _NUMPY.get(t.dtype)
        if dtype is None:
            return None
        count, shape = self.size(), [d.size for d in t.tensor_shape.dim]
        if t.tensor_content:
            if len(t.tensor_content) != count * np.dtype(dtype).itemsize:
                raise GraphError(f"{self.where}: a constant of shape {shape} holds {len(t.tensor_content)} bytes")
            return np.frombuffer(t.tensor_content, dtype=dtype).reshape(shape).copy()
        values = t.float_val if t.dtype == DT_FLOAT else t.int_val
        if len(values) > max(count, 1):
            raise GraphError(f"{self.where}: a constant of shape {shape} lists {len(values):,} values")
        values = np.fromiter(values, dtype=dtype, count=len(values))  # no Python list of them
        return np.resize(values if len(values) else np.zeros(1, dtype), count).reshape(shape)


def _decode_attr(a, where: str):
    kind = a.WhichOneof("value")
    if kind == "tensor":
        return Tensor(a.tensor, where)
    if kind == "shape":
        return [d.size for d in a.shape.dim] if len(a.shape.dim) <= MAX_ATTR_ITEMS else None
    if kind == "list":
        if max(len(a.list.i), len(a.list.f), len(a.list.s)) > MAX_ATTR_ITEMS:
            return None  # no attribute a network layer reads is this long: not decoded
        return list(a.list.i) or list(a.list.f) or [s.decode(errors="replace") for s in a.list.s]
    if kind == "s":
        return a.s.decode(errors="replace")
    return getattr(a, kind) if kind else None


def parse_graph(data: bytes, source: str = "<graph>", meta: bool = False) -> dict[str, Node]:
    """`{name: Node}` of a serialised GraphDef (`meta`: of a checkpoint's MetaGraphDef); GraphError if the
    bytes are not one."""
    graph = MetaGraphDef() if meta else GraphDef()
    try:
        graph.ParseFromString(data)
    except Exception as exc:  # protobuf's DecodeError and friends
        raise GraphError(f"{source}: not a TensorFlow {'MetaGraphDef' if meta else 'GraphDef'} ({exc})") from None
    if meta:
        graph = graph.graph_def
    if not graph.node:
        raise GraphError(f"{source}: the graph has no nodes (not a frozen TensorFlow .pb)")
    nodes = {}
    for n in graph.node:
        inputs = [i.split(":")[0].lstrip("^") for i in n.input if not i.startswith("^")]
        nodes[n.name] = Node(n.name, n.op, inputs,
                             {k: _decode_attr(v, f"{source}: node {n.name!r}") for k, v in n.attr.items()})
    return nodes


def read_graph(path) -> dict[str, Node]:
    """The nodes of a frozen `.pb` file."""
    path = Path(path)
    return parse_graph(path.read_bytes(), str(path))
