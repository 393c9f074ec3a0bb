"""TensorFlow training checkpoints (``NAME.ckpt.index`` + ``NAME.ckpt.data-00000-of-00001``) read without TensorFlow.

The ``.index`` is a LevelDB-format table (TensorFlow's tensor bundle): a 48-byte
footer points to an index block, whose entries point to data blocks, whose
entries map each variable's name to a ``BundleEntryProto`` (dtype, shape,
shard, offset, size); the empty name holds the ``BundleHeaderProto``. The
weights are the raw little-endian bytes at (offset, size) of the shard's
``.data`` file. Only uncompressed blocks (what TensorFlow writes) are read.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from .tfgraph import DT_FLOAT, BundleEntryProto, BundleHeaderProto, GraphError

MAGIC = 0xDB4775248B80FB57
MAX_INDEX_BYTES = 64 * 2**20
MAX_TENSOR_BYTES = 512 * 2**20


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(data) or shift > 63:
            raise GraphError("truncated varint")
        byte = data[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7


def _block(data: bytes, offset: int, size: int, source: str) -> list[tuple[bytes, bytes]]:
    """The (key, value) entries of one table block."""
    if offset + size + 5 > len(data):
        raise GraphError(f"{source}: a block runs past the end of the file")
    if data[offset + size] != 0:
        raise GraphError(f"{source}: compressed blocks are not supported (TensorFlow writes them uncompressed)")
    block = data[offset:offset + size]
    restarts = struct.unpack_from("<I", block, len(block) - 4)[0]
    end = len(block) - 4 - 4 * restarts
    entries, pos, key = [], 0, b""
    while pos < end:
        shared, pos = _varint(block, pos)
        unshared, pos = _varint(block, pos)
        length, pos = _varint(block, pos)
        key = key[:shared] + block[pos:pos + unshared]
        pos += unshared
        entries.append((key, block[pos:pos + length]))
        pos += length
    return entries


def read_index(path) -> dict[str, dict]:
    """`{variable name: {"dtype", "shape", "shard", "offset", "size"}}` of a checkpoint's `.index` file."""
    path = Path(path)
    if path.stat().st_size > MAX_INDEX_BYTES:
        raise GraphError(f"{path}: larger than {MAX_INDEX_BYTES // 2**20} MB; not a checkpoint index")
    data = path.read_bytes()
    if len(data) < 48 or struct.unpack_from("<Q", data, len(data) - 8)[0] != MAGIC:
        raise GraphError(f"{path}: not a TensorFlow checkpoint index (no table magic)")
    footer = data[-48:]
    _, pos = _varint(footer, 0)  # the metaindex block, unused
    _, pos = _varint(footer, pos)
    index_offset, pos = _varint(footer, pos)
    index_size, pos = _varint(footer, pos)
    tensors = {}
    try:
        for _, handle in _block(data, index_offset, index_size, str(path)):
            offset, pos = _varint(handle, 0)
            size, _ = _varint(handle, pos)
            for key, value in _block(data, offset, size, str(path)):
                if not key:
                    BundleHeaderProto.FromString(value)  # the header: checked to parse
                    continue
                entry = BundleEntryProto.FromString(value)
                tensors[key.decode()] = {"dtype": entry.dtype, "shape": [d.size for d in entry.shape.dim],
                                         "shard": entry.shard_id, "offset": entry.offset, "size": entry.size}
    except GraphError:
        raise
    except Exception as exc:  # struct, protobuf and decoding errors of a damaged file
        raise GraphError(f"{path}: unreadable checkpoint index ({type(exc).__name__}: {exc})") from None
    return tensors


class Checkpoint:
    """A checkpoint's variables, read on demand: `checkpoint[name]` is a float32 array."""

    def __init__(self, prefix):
        self.prefix = Path(prefix)
        self.index = read_index(f"{self.prefix}.index")
        self.shards = {}

    def __contains__(self, name) -> bool:
        return name in self.index

    def __getitem__(self, name: str) -> np.ndarray:
        entry = self.index[name]
        if entry["dtype"] != DT_FLOAT:
            raise GraphError(f"{self.prefix}: variable {name!r} is not float32")
        expected = 4 * int(np.prod(entry["shape"]))
        if entry["size"] != expected or entry["size"] > MAX_TENSOR_BYTES:
            raise GraphError(f"{self.prefix}: variable {name!r} of shape {entry['shape']} has {entry['size']} bytes")
        shard = entry["shard"]
        if shard not in self.shards:
            found = sorted(self.prefix.parent.glob(f"{self.prefix.name}.data-{shard:05d}-of-*"))
            if not found:
                raise GraphError(f"{self.prefix}: no .data-{shard:05d}-of-* file beside the index")
            self.shards[shard] = found[0]
        with open(self.shards[shard], "rb") as f:
            f.seek(entry["offset"])
            raw = f.read(entry["size"])
        if len(raw) != entry["size"]:
            raise GraphError(f"{self.shards[shard]}: truncated at variable {name!r}")
        return np.frombuffer(raw, "<f4").reshape(entry["shape"]).copy()


def checkpoint_prefix(folder) -> Path:
    """The newest checkpoint of a DeepRacer `model/` folder: the one `.coach_checkpoint` names, else the only one."""
    folder = Path(folder)
    named = folder / ".coach_checkpoint"
    if named.is_file():
        name = named.read_text().strip()
        prefix = folder / name
        if Path(f"{prefix}.index").is_file():
            return prefix
    indexes = sorted(folder.glob("*.ckpt.index"))
    if len(indexes) != 1:
        raise GraphError(f"{folder}: {len(indexes)} checkpoints (*.ckpt.index) and no .coach_checkpoint naming one")
    return indexes[0].with_suffix("")
