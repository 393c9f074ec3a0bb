"""Agent files: a camera policy's weights plus its DeepRacer-style model_metadata, in one `.pt`.

An agent file is a ``torch.save`` of a plain dict::

    {"format": "multirace-agent", "format_version": 1,
     "metadata": "<model_metadata JSON text>",
     "state_dict": {parameter name: tensor, ...}}

The metadata is DeepRacer's ``model_metadata.json`` (``sensor``,
``neural_network``, ``action_space``, ``action_space_type``, ``version``,
``training_algorithm``) plus ``name`` (the agent's name), ``image``
(``{"height", "width", "channels"}`` of the camera it expects) and optional
``training`` notes. ``sensor`` is DeepRacer's list (`sensors.suite`): one
camera, ``FRONT_FACING_CAMERA`` (1 grey or 3 colour channels),
``STEREO_CAMERAS`` (2 channels, [left, right]) or multirace's
``FRONT_FACING_CAMERA_TWO_FRAMES`` (2 channels, [now, the step before]), at most one range sensor,
``LIDAR`` (64 ranges) or ``SECTOR_LIDAR`` (8 binary sectors), and multirace's
own sensors such as ``SPEED`` (`sensors.registry`); the net reads each sensor
beside the camera as the registry's schema sizes it
(`SensorSuite.vector_inputs`). In a race an agent takes what it reads from the
race's observation (`Agent.reads`). The
network is rebuilt from its name (`nets.NETWORKS`), so a custom network
travels without Python source.

Loading never unpickles arbitrary objects, and never allocates more than the
file declares: only a regular file under `MAX_FILE_BYTES` is read (once: the
bytes that are checked are the bytes that are loaded); its pickle is scanned
first (`check_archive`): it may name only the globals an agent file needs
(`ALLOWED_GLOBALS`: no `bytearray` or other constructor that allocates at
will), and every tensor storage it declares must match its stored,
uncompressed record byte for byte, within `MAX_WEIGHT_BYTES` in all; then
``torch.load(..., weights_only=True)`` reads it. The network that the
metadata names is sized on torch's meta device before any weights are
allocated (`MAX_PARAMETERS`). Any failure while loading is an
`AgentFileError` (the entrant forfeits; the race goes on), and
`inspect_agent_isolated` inspects a file in a subprocess under an
address-space limit and a timeout.
Validation on load checks the metadata, the weights against the architecture,
the output shape against the action space, and a smoke inference (finite
output, within the time budget). Every error names the file and the field.
"""
from __future__ import annotations

import gc
import hashlib
import io
import json
import math
import os
import pickle
import pickletools
import re
import stat
import subprocess
import sys
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

from ..atomic import write_bytes
from ..environment.actions import ActionSpace, ActionSpaceError
from ..sensors.camera import observation_shape
from ..sensors.registry import BY_KIND, CAMERA_KEY, SENSORS
from ..sensors.suite import SensorSuite, declared_sensors, parse_sensors, suite_of
from .graphnet import GRAPH_FIELD, GraphNet, plan
from .nets import NETWORKS, CameraNet, num_outputs_for, parameter_count
from .entrant import TEACHER_PREFIX, Controller, Forfeit, teacher_spec

FORMAT = "multirace-agent"
FORMAT_VERSION = 1
DEFAULT_STEP_BUDGET = 1.0 / 15  # seconds: one 15 Hz frame (DeepRacer's control rate)
WARMUP_STEPS = 2  # first steps of a race not held to the time budget (allocator / cache warm-up)


class AgentFileError(ValueError):
    """An agent file is unreadable, unsafe or inconsistent; the message names the file and the problem."""


def make_metadata(action_space, network: str, name: str, image_shape=(120, 160, 1), version: str = "5",
                  training_algorithm: str = "dagger", lidar: bool = False, sensor=None, **extra) -> dict:
    """A model_metadata dict for an agent file: `sensor` is DeepRacer's list (default the single camera;
    `lidar=True` adds the LIDAR, as the env's shorthand)."""
    height, width, channels = (int(v) for v in image_shape)
    metadata = {
        "name": str(name),
        "sensor": declared_sensors(sensor, lidar).names,
        "image": {"height": height, "width": width, "channels": channels},
        "neural_network": network,
        "training_algorithm": training_algorithm,
        **action_space.to_metadata(),
        "version": str(version),
    }
    metadata.update(extra)
    return metadata


def save_agent(path, net: CameraNet, metadata: dict, verify: bool = False) -> Path:
    """Write `net`'s weights and `metadata` (a model_metadata dict) as an agent file; returns the path.

    The metadata is checked against the net (network name, image shape, outputs)
    before anything is written; with `verify`, the bytes too, by every check the loader makes.
    """
    path = Path(path)
    metadata = dict(metadata)
    metadata.setdefault("name", path.stem)
    metadata.setdefault("neural_network", net.network)
    h, w, c = net.image_shape
    metadata.setdefault("image", {"height": h, "width": w, "channels": c})
    try:
        reads = net_sensors(net, declared_camera(metadata))
    except ValueError as exc:
        raise AgentFileError(f"{path}: {exc}") from None
    metadata.setdefault("sensor", reads.names)
    metadata.setdefault("version", "5")
    _, space, network, image_shape, sensors = check_metadata(metadata, str(path))
    if network != net.network or tuple(image_shape) != tuple(net.image_shape):
        raise AgentFileError(f"{path}: metadata says {network} on {image_shape} images but the net is "
                             f"{net.network} on {net.image_shape}")
    if sensors != reads:
        raise AgentFileError(f"{path}: metadata field 'sensor' {metadata['sensor']!r} does not match the net, "
                             f"which reads {reads.names}")
    if num_outputs_for(space) != net.num_outputs:
        raise AgentFileError(f"{path}: the net has {net.num_outputs} outputs but the action space needs "
                             f"{num_outputs_for(space)}")
    return write_agent_file(path, metadata, net, verify)


def declared_camera(metadata: dict) -> str | None:
    """The camera kind a metadata's ``sensor`` list names (None where it names none that parses: the metadata's
    check reports it)."""
    try:
        return parse_sensors(metadata["sensor"]).camera
    except (KeyError, ValueError):
        return None


def net_sensors(net: CameraNet, camera: str | None = None) -> SensorSuite:
    """The sensors a net reads: its `camera` (a `SensorSuite` camera kind; default: a stereo pair on 2-channel
    images, else the single camera), which must give the net's channels; per vector input the registry's
    sensor of that key and size (LIDAR 64 inputs, SECTOR_LIDAR 8, SPEED 1)."""
    channels = net.image_shape[2]
    kind = camera or ("stereo" if channels == 2 else "mono")
    expected = camera_channels(kind)
    if not (channels == expected if expected else channels in (1, 3)):
        raise ValueError(f"the net reads {channels}-channel images; {BY_KIND[kind].name} gives "
                         f"{expected or '1 (grey) or 3 (colour)'}")
    sensors = [BY_KIND[kind]]
    for key, size in net.vector_inputs.items():
        fits = [sensor for sensor in SENSORS if sensor.key == key and sensor.inputs == size]
        if not fits:
            known = ", ".join(f"{s.name} {s.inputs}" for s in SENSORS if s.key == key) or "none"
            raise ValueError(f"the net reads {size} {key!r} inputs; the sensors of that key give: {known}")
        sensors.append(fits[0])
    return suite_of(sensors)


def camera_channels(kind: str) -> int | None:
    """The channels a camera kind's images have: 2 for a stereo pair or two frames, None for the single camera
    (1 grey or 3 colour)."""
    return BY_KIND[kind].channels


def agent_file_bytes(metadata: dict, net) -> bytes:
    """The bytes of an agent file of `net`'s parameters and `metadata`."""
    state = {k: v.detach().cpu().contiguous().clone() for k, v in net.state_dict().items()}
    payload = {"format": FORMAT, "format_version": FORMAT_VERSION,
               "metadata": json.dumps(without_machine_paths(metadata), indent=2, sort_keys=True), "state_dict": state}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return buffer.getvalue()


def write_agent_file(path, metadata: dict, net, verify: bool = False) -> Path:
    """Write an agent file (atomically) of `net`'s parameters and `metadata`, already checked; with `verify`,
    its bytes pass every check of the loader (`agent_from_bytes`) before anything is written."""
    data = agent_file_bytes(metadata, net)
    if verify:
        agent_from_bytes(data, Path(path))
    return write_bytes(path, data)


# ------------------------------------------------------------------ loading
MAX_FILE_BYTES = 256 * 2**20  # an agent file larger than this is refused unread
MAX_WEIGHT_BYTES = 256 * 2**20  # all tensor storages of one file together
MAX_PICKLE_BYTES = 4 * 2**20  # the pickled structure (names, shapes, metadata text) without the weights
MAX_PARAMETERS = 50_000_000  # a network the metadata names may have at most this many parameters
ALLOWED_GLOBALS = {"collections OrderedDict", "torch._utils _rebuild_tensor_v2", "torch._utils _rebuild_parameter"}
STORAGE_BYTES = {"FloatStorage": 4, "DoubleStorage": 8, "HalfStorage": 2, "BFloat16Storage": 2, "LongStorage": 8,
                 "IntStorage": 4, "ShortStorage": 2, "CharStorage": 1, "ByteStorage": 1, "BoolStorage": 1}
ALLOWED_GLOBALS |= {f"torch {name}" for name in STORAGE_BYTES}
_VALUE_OPS = {"SHORT_BINUNICODE", "BINUNICODE", "BINUNICODE8", "UNICODE", "SHORT_BINSTRING", "BINSTRING",
              "BININT", "BININT1", "BININT2", "LONG1", "LONG4", "INT", "LONG", "GLOBAL"}
_CODE_OPS = {"STACK_GLOBAL", "INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "EXT1", "EXT2", "EXT4", "PERSID"}


def read_agent_bytes(path) -> bytes:
    """The bytes of an agent file: a regular file under `MAX_FILE_BYTES`, read once (no FIFOs, devices
    or folders: they could block or never end)."""
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such agent file") from None
    except OSError as exc:
        raise AgentFileError(f"{path}: cannot be read ({exc.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise AgentFileError(f"{path}: is a directory, not an agent file")
    if not stat.S_ISREG(info.st_mode):
        raise AgentFileError(f"{path}: not a regular file (a device, FIFO or socket); agent files are files")
    if info.st_size > MAX_FILE_BYTES:
        raise AgentFileError(f"{path}: {info.st_size / 2**20:.0f} MB, over the {MAX_FILE_BYTES // 2**20} MB "
                             "limit of an agent file")
    try:
        with open(path, "rb") as handle:
            data = handle.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise AgentFileError(f"{path}: cannot be read ({exc.strerror})") from None
    if len(data) > MAX_FILE_BYTES:
        raise AgentFileError(f"{path}: over the {MAX_FILE_BYTES // 2**20} MB limit of an agent file")
    return data


def check_archive(data: bytes, source: str) -> None:
    """Refuse a torch archive whose pickle names anything but the allowed globals, or whose declared
    tensor storages do not match their stored records (a patched element count would allocate at will)."""
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
        pickles = [i for i in archive.infolist() if i.filename.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise AgentFileError(f"{source}: not an agent file (no single data.pkl in the torch archive)")
        if pickles[0].file_size > MAX_PICKLE_BYTES:
            raise AgentFileError(f"{source}: its metadata and structure take {pickles[0].file_size / 2**20:.1f} MB, "
                                 f"over the {MAX_PICKLE_BYTES // 2**20} MB limit (weights are stored apart)")
        prefix = pickles[0].filename[: -len("data.pkl")]
        records = {i.filename: i for i in archive.infolist()}
        code = archive.read(pickles[0])
    except AgentFileError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError, KeyError) as exc:
        _refuse_code(data, source)  # a bare pickle (torch's legacy format) that names code is refused as such
        raise AgentFileError(f"{source}: unreadable or truncated agent file ({type(exc).__name__}: not the torch "
                             "zip archive agent files are)") from None
    memo, marks, last, total = {}, [], None, 0
    try:
        for op, arg, _ in pickletools.genops(code):
            name = op.name
            if name in _CODE_OPS or (name == "GLOBAL" and arg not in ALLOWED_GLOBALS):
                _refuse_code(code, source)
            if name in _VALUE_OPS:
                last = arg
            elif name in ("BINGET", "LONG_BINGET", "GET"):
                last = memo.get(arg)
            elif name in ("BINPUT", "LONG_BINPUT", "PUT"):
                memo[arg] = last
                continue
            elif name == "MEMOIZE":
                memo[len(memo)] = last
                continue
            elif name == "MARK":
                marks.append([])
                continue
            elif name == "TUPLE":
                last = tuple(marks.pop()) if marks else None
            elif name == "BINPERSID":
                total += _storage_bytes(last, records, prefix, source)
                if total > MAX_WEIGHT_BYTES:
                    raise AgentFileError(f"{source}: its tensors declare over {MAX_WEIGHT_BYTES // 2**20} MB")
                last = None
            else:
                last = None
                if name in ("SETITEMS", "APPENDS", "DICT", "LIST", "FROZENSET", "ADDITEMS", "POP_MARK") and marks:
                    marks.pop()
                continue
            if marks:
                marks[-1].append(last)
    except AgentFileError:
        raise
    except Exception as exc:  # a malformed pickle stream
        raise AgentFileError(f"{source}: unreadable agent file (its pickle: {type(exc).__name__})") from None


def _refuse_code(data: bytes, source: str) -> None:
    """AgentFileError if `data`, read as a pickle stream, names a global or opcode that would run code."""
    try:
        for op, arg, _ in pickletools.genops(data):
            if op.name in _CODE_OPS or (op.name == "GLOBAL" and arg not in ALLOWED_GLOBALS):
                what = arg if op.name == "GLOBAL" else f"the {op.name} opcode"
                raise AgentFileError(f"{source}: refused: the file's pickle names {what!r}; agent files may hold "
                                     "only tensors and metadata (nothing in it was run)")
    except AgentFileError:
        raise
    except Exception:  # not a pickle stream at all
        return


def _storage_bytes(pid, records: dict, prefix: str, source: str) -> int:
    """Bytes of one declared tensor storage, checked against its stored record."""
    if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage" and isinstance(pid[2], str)
            and isinstance(pid[4], int) and pid[4] >= 0):
        raise AgentFileError(f"{source}: refused: a tensor storage of the wrong form in its pickle")
    kind = str(pid[1]).rpartition(" ")[2]
    record = records.get(f"{prefix}data/{pid[2]}")
    size = pid[4] * STORAGE_BYTES.get(kind, 0)
    if record is None or record.compress_type != zipfile.ZIP_STORED or record.file_size != size:
        raise AgentFileError(f"{source}: refused: tensor storage {pid[2]!r} declares {pid[4]} elements but its "
                             "record does not hold exactly that many (stored, uncompressed)")
    return size


def read_payload(path) -> dict:
    """The raw dict of an agent file, loaded safely (see the module docstring); AgentFileError if unreadable
    or unsafe."""
    return payload_from_bytes(read_agent_bytes(path), Path(path))


def payload_from_bytes(data: bytes, path: Path) -> dict:
    """The raw dict of an agent file's bytes, checked (`check_archive`) and then loaded weights-only."""
    check_archive(data, str(path))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()
        detail = next((line.strip() for line in first if "Unsupported" in line or "global" in line.lower()),
                      first[0] if first else "")
        if "operand" in detail and "global" not in detail.lower():  # an opcode the safe loader lacks: garbage
            raise AgentFileError(f"{path}: unreadable agent file: not a weights-only torch file ({detail}); "
                                 "nothing in it was run") from None
        raise AgentFileError(f"{path}: refused: the file's pickle holds more than tensors and plain data "
                             f"(it would import or call code; agent files may hold only tensors and "
                             f"metadata): {detail}") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError, ValueError, KeyError, IndexError) as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        message = f"{type(exc).__name__}: {message.split('. ')[0][:160]}"
        raise AgentFileError(f"{path}: unreadable or truncated agent file ({message})") from None
    except Exception as exc:  # anything else torch.load may raise on garbage
        raise AgentFileError(f"{path}: unreadable agent file ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict):
        raise AgentFileError(f"{path}: not an agent file (expected a dict, found {type(payload).__name__})")
    if payload.get("format") != FORMAT:
        raise AgentFileError(f"{path}: field 'format' is {payload.get('format')!r}, expected {FORMAT!r} "
                             "(save agents with multirace.racing.agentfile.save_agent)")
    if payload.get("format_version") != FORMAT_VERSION:
        raise AgentFileError(f"{path}: field 'format_version' is {payload.get('format_version')!r}, "
                             f"this multirace reads version {FORMAT_VERSION}")
    return payload


def parse_metadata(payload: dict, source: str) -> dict:
    """The metadata dict of a payload (JSON text inside the file)."""
    raw = payload.get("metadata")
    if raw is None:
        raise AgentFileError(f"{source}: field 'metadata' is missing")
    if not isinstance(raw, str):
        raise AgentFileError(f"{source}: field 'metadata' must be model_metadata JSON text")
    try:
        metadata = json.loads(raw, parse_int=_json_int)
    except json.JSONDecodeError as exc:
        raise AgentFileError(f"{source}: field 'metadata' is not valid JSON ({exc})") from None
    except RecursionError:
        raise AgentFileError(f"{source}: field 'metadata' is nested too deeply") from None
    if not isinstance(metadata, dict):
        raise AgentFileError(f"{source}: field 'metadata' must be a JSON object")
    field = _long_number_field(metadata)
    if field is not None:
        raise AgentFileError(f"{source}: metadata field {field!r} is a number of over "
                             f"{sys.get_int_max_str_digits():,} digits")
    return without_machine_paths(metadata)


# an absolute path's folders: at a word's start (not inside a URL or a relative path), or right after
# "teacher:" (an entrant spec naming an RL teacher file, as a student's training metadata records it)
_ABSOLUTE_PATH = re.compile(r"(?:(?<=teacher:)|(?<![\w.:/~-]))(?:/|~/|[A-Za-z]:[\\/])(?:[^\s/\\'\"]+[/\\])+"
                            r"(?=[^\s/\\'\"]+)")


def without_machine_paths(value):
    """`value` (metadata: dicts, lists, strings) with every absolute path cut to its file name: a training
    command run on one machine (`--action-space /home/me/agents/space.json`) must not carry that machine's
    folders into `agent inspect`, an exported model_metadata.json or another machine's files."""
    if isinstance(value, str):
        return _ABSOLUTE_PATH.sub("", value)
    if isinstance(value, dict):
        return {key: without_machine_paths(item) for key, item in value.items()}
    if isinstance(value, list):
        return [without_machine_paths(item) for item in value]
    return value


class _LongNumber(str):
    """A JSON integer of more digits than Python converts (`sys.get_int_max_str_digits`), kept as its text."""


def _json_int(text: str):
    return _LongNumber(text) if len(text.lstrip("-")) > sys.get_int_max_str_digits() > 0 else int(text)


def _long_number_field(metadata: dict) -> str | None:
    """The top-level field of `metadata` holding a `_LongNumber` (at any depth), if any."""
    for field, value in metadata.items():
        stack = [value]
        while stack:
            item = stack.pop()
            if isinstance(item, _LongNumber):
                return field
            if isinstance(item, dict):
                stack.extend(item.values())
            elif isinstance(item, list):
                stack.extend(item)
    return None


def metadata_sensors(metadata: dict, source: str) -> SensorSuite:
    """The sensors a model_metadata declares (field ``sensor``); AgentFileError naming the file and field."""
    if metadata.get("sensor") is None:
        raise AgentFileError(f"{source}: metadata field 'sensor' is missing")
    try:
        return parse_sensors(metadata["sensor"], f"{source}: metadata field 'sensor'")
    except ValueError as exc:
        raise AgentFileError(str(exc)) from None


def check_metadata(metadata: dict, source: str):
    """Validate a model_metadata dict; returns (metadata, ActionSpace, network name, image shape, SensorSuite)."""
    sensors = metadata_sensors(metadata, source)
    image = metadata.get("image")
    if not isinstance(image, dict):
        raise AgentFileError(f"{source}: metadata field 'image' is missing or not "
                             "{'height', 'width', 'channels'}")
    try:
        shape = tuple(int(image[k]) for k in ("height", "width", "channels"))
    except (KeyError, TypeError, ValueError):
        raise AgentFileError(f"{source}: metadata field 'image' needs integer 'height', 'width' and "
                             f"'channels', got {image!r}") from None
    if not (32 <= shape[0] <= 1080 and 32 <= shape[1] <= 1920 and shape[2] in (1, 2, 3)):
        raise AgentFileError(f"{source}: metadata field 'image' {image!r} out of range "
                             "(32-1080 x 32-1920 pixels, 1 to 3 channels)")
    if (shape[2] == 2) != (camera_channels(sensors.camera) == 2):
        reads = {"stereo": "STEREO_CAMERAS, a grey pair of 2 channels [left, right]",
                 "frames": "FRONT_FACING_CAMERA_TWO_FRAMES, 2 grey channels [now, the step before]"}.get(
            sensors.camera, "a single camera of 1 (grey) or 3 (colour) channels; 2 channels are STEREO_CAMERAS "
                            "or FRONT_FACING_CAMERA_TWO_FRAMES")
        raise AgentFileError(f"{source}: metadata field 'image' has {shape[2]} channel(s) but field 'sensor' "
                             f"{metadata['sensor']!r} declares {reads}")
    network = metadata.get("neural_network")
    if GRAPH_FIELD in metadata:  # an imported DeepRacer network (`graphnet`): any name DeepRacer gave it
        if not isinstance(network, str) or not network:
            raise AgentFileError(f"{source}: metadata field 'neural_network' must name the imported network")
    elif network not in NETWORKS:
        raise AgentFileError(f"{source}: metadata field 'neural_network' is {network!r}; known networks: "
                             f"{', '.join(NETWORKS)}")
    try:
        space = ActionSpace(metadata, f"{source}: metadata")
    except ActionSpaceError as exc:
        raise AgentFileError(str(exc)) from None
    name = metadata.get("name")
    if name is not None and (not isinstance(name, str) or not name.strip()):
        raise AgentFileError(f"{source}: metadata field 'name' must be a non-empty string")
    return metadata, space, network, shape, sensors


class Agent:
    """A loaded, validated agent: net (eval mode), metadata, action space, the sensors it reads."""

    def __init__(self, path: Path, net: CameraNet, metadata: dict, space: ActionSpace, sha256: str,
                 sensors: SensorSuite):
        self.path, self.net, self.metadata, self.action_space, self.sha256 = path, net, metadata, space, sha256
        self.sensors = sensors
        self.name = metadata.get("name") or path.stem

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return self.net.image_shape

    @property
    def lidar_samples(self) -> int:
        return self.net.lidar_samples

    def reads(self, observation):
        """What the agent reads of a race env's observation (see `race_suite`): its camera image as the env
        gives it (`camera.observation_shape`: (H, W) when grey; (H, W, 1) is taken too), a single-camera
        agent the left image of a stereo pair; each of its other sensors' values (`Sensor.reads`: a
        SECTOR_LIDAR agent reduces a 64-beam scan to its sectors). ValueError if the observation does not
        match its model_metadata."""
        values = observation if isinstance(observation, dict) else {CAMERA_KEY: observation}
        image = np.asarray(values.get(CAMERA_KEY))
        height, width, channels = self.image_shape
        if channels == 1 and image.shape in ((height, width, 1), (height, width, 2)):  # grey, or a pair's first image
            image = image[:, :, 0]
        if image.shape != observation_shape(self.image_shape) or image.dtype != np.uint8:
            raise ValueError(f"observation {image.shape} {image.dtype} does not match the {height}x{width}x{channels} "
                             f"uint8 images the agent reads (field 'image' of its model_metadata)")
        if not self.sensors.vectors:
            return image
        read = {CAMERA_KEY: image}
        for sensor in self.sensors.vectors:
            value = values.get(sensor.key)
            value = np.asarray(sensor.reads(value) if value is not None else [], np.float32)
            if value.shape != (sensor.inputs,):
                raise ValueError(f"{sensor.name} observation of shape {value.shape} does not match the agent's "
                                 f"{sensor.inputs} inputs (sensor {self.sensors.names} in its model_metadata)")
            read[sensor.key] = value
        return read

    def outputs(self, observation) -> np.ndarray:
        """The net's raw output row for one observation as `reads` gives it (an image, or with sensors beside
        the camera a {"camera", key, ...} dict)."""
        with torch.no_grad():
            if isinstance(observation, dict):
                out = self.net({key: torch.from_numpy(np.ascontiguousarray(value))
                                for key, value in observation.items()})
            else:
                out = self.net(torch.from_numpy(np.ascontiguousarray(observation)))
        return out.numpy()

    def decide(self, output: np.ndarray):
        """The greedy action for an output row: argmax index, or the [steer, speed] mean (`ActionSpace.greedy`)."""
        return self.action_space.greedy(output)


def load_agent(path, step_budget: float | None = DEFAULT_STEP_BUDGET, smoke_runs: int = 5) -> Agent:
    """Load and validate an agent file (see the module docstring); AgentFileError names the problem.

    The smoke inference runs on a blank image (up to `smoke_runs` tries); the
    fastest must finish within `step_budget` seconds (None: no time check).
    Any failure while loading (a RecursionError, MemoryError, an odd tensor...)
    is an AgentFileError, so a bad file forfeits its entrant and never stops a
    race; only a missing file is a FileNotFoundError.
    """
    try:
        return _load_agent(Path(path), step_budget, smoke_runs)
    except (AgentFileError, FileNotFoundError):
        raise
    except Exception as exc:
        raise AgentFileError(f"{path}: cannot be loaded ({type(exc).__name__}: {str(exc)[:200]})") from None


def _load_agent(path: Path, step_budget: float | None, smoke_runs: int) -> Agent:
    return agent_from_bytes(read_agent_bytes(path), path, step_budget, smoke_runs)


def agent_from_bytes(data: bytes, path: Path, step_budget: float | None = None, smoke_runs: int = 1) -> Agent:
    """The agent in an agent file's bytes, with every check `load_agent` makes (so a writer can refuse what
    no loader would read before it writes anything); AgentFileError naming `path` and the field."""
    if len(data) > MAX_FILE_BYTES:
        raise AgentFileError(f"{path}: over the {MAX_FILE_BYTES // 2**20} MB limit of an agent file")
    payload = payload_from_bytes(data, path)
    source = str(path)
    metadata, space, network, shape, sensors = check_metadata(parse_metadata(payload, source), source)
    state = payload.get("state_dict")
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise AgentFileError(f"{source}: field 'state_dict' must map parameter names to tensors")
    net = _build_net(metadata, space, network, shape, sensors, state, source)
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()][1:4]
        vectors = " and ".join(f"{sensor.inputs} {sensor.unit}" for sensor in sensors.vectors)
        with_vectors = f" and {vectors} (metadata field 'sensor')" if vectors else ""
        raise AgentFileError(f"{source}: weights do not match the {network} architecture for "
                             f"{shape[0]}x{shape[1]}x{shape[2]} images{with_vectors}: {' '.join(lines)}") from None
    net.eval()
    agent = Agent(path, net, metadata, space, hashlib.sha256(data).hexdigest(), sensors)
    smoke_test(agent, step_budget, smoke_runs)
    return agent


def _build_net(metadata: dict, space: ActionSpace, network: str, shape: tuple, sensors: SensorSuite, state: dict,
               source: str):
    """The untrained net the metadata describes (a `CameraNet`, or a `GraphNet` with ``deepracer_graph``), sized
    on torch's meta device first (`MAX_PARAMETERS`); AgentFileError naming the field that does not fit."""
    expected = num_outputs_for(space)
    head = state.get("head.weight")
    if isinstance(head, torch.Tensor) and head.dim() == 2 and head.shape[0] != expected:
        raise AgentFileError(f"{source}: output shape: the net outputs {head.shape[0]} values but the "
                             f"{space.kind} action space needs {expected}")
    value_head = any(k.startswith("value_head.") for k in state)

    def make():
        if GRAPH_FIELD in metadata:
            return _graph_net(metadata, space, shape, sensors, source)
        return CameraNet(network, shape, expected, value_head=value_head, vector_inputs=sensors.vector_inputs)

    try:
        with torch.device("meta"):  # sized before anything is allocated
            planned = parameter_count(make())
        if planned > MAX_PARAMETERS:
            raise AgentFileError(f"{source}: the {network} network on {shape[0]}x{shape[1]}x{shape[2]} images "
                                 f"has {planned:,} parameters, over the limit of {MAX_PARAMETERS:,}")
        return make()
    except AgentFileError:
        raise
    except ValueError as exc:
        raise AgentFileError(f"{source}: metadata field 'image': {exc}") from None


def _graph_net(metadata: dict, space: ActionSpace, shape: tuple, sensors: SensorSuite, source: str) -> GraphNet:
    """A `GraphNet` from metadata field ``deepracer_graph``, checked against fields 'image' and 'sensor'."""
    spec = metadata[GRAPH_FIELD]
    try:
        plan(spec)  # its size, from the shapes alone, before anything is built
    except ValueError as exc:
        raise AgentFileError(f"{source}: metadata field '{GRAPH_FIELD}' is not a network spec multirace can run "
                             f"({exc})") from None
    try:
        net = GraphNet(spec, space)
    except (ValueError, KeyError, IndexError, TypeError, AttributeError) as exc:
        raise AgentFileError(f"{source}: metadata field '{GRAPH_FIELD}' is not a network spec ({exc})") from None
    if tuple(net.image_shape) != tuple(shape):
        raise AgentFileError(f"{source}: metadata field '{GRAPH_FIELD}' reads {net.image_shape} images but field "
                             f"'image' says {shape}")
    if sorted(net.sensors) != sorted(sensors.names) or net.lidar_samples != sensors.range_inputs:
        raise AgentFileError(f"{source}: metadata field '{GRAPH_FIELD}' has inputs {net.sensors} "
                             f"({net.lidar_samples} ranges) but field 'sensor' declares {sensors.names}")
    return net


def smoke_test(agent: Agent, step_budget: float | None, runs: int = 5) -> None:
    """One inference on a blank image (and blank readings of its other sensors: a LIDAR scan without echoes):
    right shape, finite, within budget.

    Timed in CPU time on one torch thread (as `AgentController` runs, see `inference_clock`); up to
    `runs` tries, the fastest counts.
    """
    source = str(agent.path)
    blank = agent.reads({CAMERA_KEY: np.zeros(observation_shape(agent.image_shape), np.uint8),
                         **{sensor.key: sensor.blank() for sensor in agent.sensors.vectors}})
    fastest = math.inf
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for _ in range(max(1, runs)):
            try:
                out, elapsed = timed_inference(agent, blank)
            except Exception as exc:
                raise AgentFileError(f"{source}: smoke inference failed ({type(exc).__name__}: {exc})") from None
            fastest = min(fastest, elapsed)
            if step_budget is None or fastest <= step_budget:
                break
    finally:
        torch.set_num_threads(threads)
    expected = num_outputs_for(agent.action_space)
    if out.shape != (1, expected):
        raise AgentFileError(f"{source}: output shape {tuple(out.shape)} does not match the action space "
                             f"(expected (1, {expected}))")
    if not np.all(np.isfinite(out)):
        raise AgentFileError(f"{source}: smoke inference gave non-finite output (NaN or inf)")
    if step_budget is not None and fastest > step_budget:
        raise AgentFileError(f"{source}: smoke inference took {fastest * 1000:.1f} ms, over the "
                             f"{step_budget * 1000:.1f} ms step budget")


INSPECT_MEMORY = 1536 * 2**20  # bytes of address space an isolated inspection may use
INSPECT_TIMEOUT = 120.0  # seconds


def inspect_agent_isolated(path, timeout: float = INSPECT_TIMEOUT, memory: int = INSPECT_MEMORY) -> dict:
    """`inspect_agent` in a subprocess held to `memory` bytes of address space and `timeout` seconds, so a
    hostile file can neither exhaust this process's memory nor hang it. Returns the same dict; a file that
    overruns the limits is reported invalid with the reason."""
    path = Path(path)
    if not os.path.lexists(path):
        raise FileNotFoundError(f"{path}: no such agent file")
    code = ("import json, resource, sys\n"  # the limit is set before torch or the file is loaded
            f"resource.setrlimit(resource.RLIMIT_AS, ({int(memory)}, {int(memory)}))\n"
            "from multirace.racing.agentfile import inspect_agent\n"
            "print(json.dumps(inspect_agent(sys.argv[1])))\n")
    failed = {"file": str(path), "sha256": None, "size_bytes": None, "valid": False}
    try:
        done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                              timeout=timeout, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return {**failed, "error": f"{path}: inspection did not finish within {timeout:g} s"}
    try:
        return json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        last = (done.stderr.strip().splitlines() or ["no output"])[-1][:200]
        return {**failed, "error": f"{path}: inspection failed within its {memory // 2**20} MB memory limit "
                                   f"(exit {done.returncode}: {last})"}


def inspect_agent(path) -> dict:
    """What `multirace agent inspect` prints: metadata, parameter count, sha256, validity (in this process;
    `inspect_agent_isolated` runs it under memory and time limits)."""
    path = Path(path)
    info = {"file": str(path), "sha256": None, "size_bytes": None}
    try:
        data = read_agent_bytes(path)
        info.update(sha256=hashlib.sha256(data).hexdigest(), size_bytes=len(data))
        agent = load_agent(path, step_budget=None)
    except AgentFileError as exc:
        info.update(valid=False, error=str(exc))
        try:
            info["metadata"] = parse_metadata(read_payload(path), str(path))
        except AgentFileError:
            pass
        return info
    info.update(valid=True, name=agent.name, network=agent.net.network,
                parameters=parameter_count(agent.net), outputs=agent.net.num_outputs,
                value_head=agent.net.has_value, metadata=agent.metadata)
    return info


def agent_summary(path) -> dict:
    """One line's worth of an agent file (what `multirace agent list` shows): name, network, parameters,
    sensors, action space, how it was made, size and path. Loads the metadata and weights safely, builds
    no net."""
    path = Path(path)
    payload = read_payload(path)
    metadata = parse_metadata(payload, str(path))
    space = ActionSpace(metadata, str(path))
    speeds = [speed for _, speed in space.actions] if space.discrete else [space.low[1], space.high[1]]
    training = metadata.get("training") if isinstance(metadata.get("training"), dict) else {}
    expert = str(training.get("expert") or "")
    if expert.startswith(TEACHER_PREFIX):  # a student of a privileged RL teacher: the teacher file's name
        expert = f"RL teacher {Path(teacher_spec(expert)[0]).name}"
    made = " ".join(part for part in (str(training.get("method") or ""), expert) if part)
    blended = training.get("blended")
    share = training.get("share_of_first")
    if isinstance(blended, list) and len(blended) == 2 and all(isinstance(part, dict) for part in blended) \
            and isinstance(share, (int, float)):
        first, second = (part.get("name") for part in blended)
        made += f", {share:g} {first} + {1 - share:g} {second}"
    minutes = training.get("minutes") or (training.get("wall_seconds") or 0) / 60
    if minutes:
        made += f", {minutes:.0f} min" if minutes >= 1 else f", {minutes:.1f} min"
    state = payload.get("state_dict") or {}
    return {"name": metadata.get("name", path.stem), "network": metadata.get("neural_network"),
            "parameters": sum(int(t.numel()) for t in state.values() if isinstance(t, torch.Tensor)),
            "sensor": metadata_sensors(metadata, str(path)).names,
            "actions": (f"{len(space.actions)} discrete" if space.discrete else "continuous")
                       + f", {min(speeds):g}-{max(speeds):g} m/s",
            "made_by": made or "-", "size_bytes": path.stat().st_size, "path": str(path)}


def inference_clock():
    """The clock an inference step is judged by: CPU time, which a busy machine cannot inflate as it does
    wall-clock time (so machine load never decides a race). The calling thread's CPU time when torch runs
    on one thread (the league's and the race's setting), else the whole process's."""
    return time.thread_time if torch.get_num_threads() == 1 else time.process_time


def timed_inference(agent: Agent, obs) -> tuple[np.ndarray, float]:
    """The agent's outputs for `obs` and the seconds of `inference_clock` they took. The garbage collector
    is held off for the call: a collection of the whole process's heap (a long-lived league worker's, a
    test run's) would otherwise count against whichever agent's allocation set it off."""
    clock = inference_clock()
    collecting = gc.isenabled()
    gc.disable()
    try:
        start = clock()
        out = agent.outputs(obs)
        return out, clock() - start
    finally:
        if collecting:
            gc.enable()


# --------------------------------------------------------------- controller
class AgentController(Controller):
    """Drives a car with an agent file's policy, from the sensors its metadata declares.

    A file that exists but is bad does not stop the race: the load error is
    kept and the agent forfeits with that reason on its first step. Each step's
    inference must finish within `step_budget` seconds of CPU time (after `WARMUP_STEPS`
    steps); NaN or wrong-shaped output, an exception or an over-budget step
    forfeits. A missing file raises FileNotFoundError (a typo, not a bad agent).
    `threads` sets torch's intra-op threads (None leaves them).
    """

    def __init__(self, path, step_budget: float = DEFAULT_STEP_BUDGET, threads: int | None = 1,
                 warmup_steps: int = WARMUP_STEPS):
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such agent file")
        if threads is not None:
            torch.set_num_threads(int(threads))
        self.step_budget = float(step_budget)
        self.warmup_steps = int(warmup_steps)
        self.name = self.path.stem
        self.file_sha256 = None
        self.agent: Agent | None = None
        self.error: str | None = None
        try:
            self.agent = load_agent(self.path, step_budget=self.step_budget)
            self.name, self.file_sha256 = self.agent.name, self.agent.sha256
        except AgentFileError as exc:
            self.error = str(exc)
            try:
                self.file_sha256 = hashlib.sha256(read_agent_bytes(self.path)).hexdigest()
            except (AgentFileError, OSError):
                pass
            try:  # name the car after its metadata even when the file is bad, if that is readable
                meta = parse_metadata(read_payload(self.path), str(self.path))
                if isinstance(meta.get("name"), str) and meta["name"].strip():
                    self.name = meta["name"]
            except (AgentFileError, OSError):
                pass
        self.steps = 0
        self.step_times: list[float] = []

    @property
    def sensors(self) -> SensorSuite:
        """What the agent reads (a bad file reads the camera alone, until it forfeits)."""
        return SensorSuite() if self.agent is None else self.agent.sensors

    def reset(self, env, car: int) -> None:
        super().reset(env, car)
        self.steps = 0
        self.step_times = []

    def drive(self, state, car, observation=None):
        """The agent's command from its car's observation (its policy reads nothing else)."""
        if self.agent is None:
            raise Forfeit(f"bad agent file: {self.error}")
        self.steps += 1
        try:
            obs = self.agent.reads(observation)
        except ValueError as exc:
            raise Forfeit(str(exc)) from None
        try:
            out, elapsed = timed_inference(self.agent, obs)
        except Exception as exc:
            raise Forfeit(f"inference raised {type(exc).__name__}: {exc}") from None
        self.step_times.append(elapsed)
        expected = num_outputs_for(self.agent.action_space)
        if out.shape != (1, expected):
            raise Forfeit(f"output shape {tuple(out.shape)} does not match the action space (1, {expected})")
        if not np.all(np.isfinite(out)):
            raise Forfeit(f"non-finite output (NaN or inf) at step {self.steps}")
        if self.steps > self.warmup_steps and elapsed > self.step_budget:
            raise Forfeit(f"step {self.steps} inference took {elapsed * 1000:.1f} ms of CPU time, over the "
                          f"{self.step_budget * 1000:.1f} ms budget")
        try:
            steer, speed = self.agent.action_space.command(self.agent.decide(out[0]))
        except Exception as exc:
            raise Forfeit(f"could not turn output into a command ({type(exc).__name__}: {exc})") from None
        return float(steer), float(speed)
