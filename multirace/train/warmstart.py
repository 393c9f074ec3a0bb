"""Starting a net from an agent file (`--init`): the settings the file was built with, and its weights."""
from __future__ import annotations

import hashlib
from pathlib import Path

import torch

from ..racing.agentfile import metadata_sensors, parse_metadata, read_payload
from ..racing.nets import CameraNet, add_vector_inputs
from ..sensors.suite import SensorSuite


def load_init_agent(path, net) -> None:
    """Initialise the policy from an agent file (e.g. a DAgger imitation agent); the value head stays new.

    An agent can start a net that reads more vector sensors (a camera-only agent a LIDAR net): the inputs it
    lacks start with zero weight (`add_vector_inputs`), after the ones it has. A single grey camera's agent
    can start a net of 2-channel images (two frames, or a stereo pair): it reads the first channel as the
    agent read its image, the second starts with zero weight.
    """
    payload = read_payload(path)
    state = {k: v for k, v in payload["state_dict"].items() if not k.startswith("value_head.")}
    has = {key: size for key, size in net.vector_inputs.items() if any(k.startswith(f"{key}.") for k in state)}
    lacks = {key: size for key, size in net.vector_inputs.items() if key not in has}
    if lacks:
        if list(net.vector_inputs) != [*has, *lacks]:
            raise ValueError(f"--init {path}: the agent reads {list(has)} but the net reads "
                             f"{list(net.vector_inputs)}; new inputs can only follow the agent's")
        narrow = CameraNet(net.network, net.image_shape, net.num_outputs, value_head=net.has_value, vector_inputs=has)
        load_init_agent(path, narrow)
        net.load_state_dict(add_vector_inputs(narrow, lacks).state_dict())
        return
    state = _with_image_channels(state, net, path)
    missing, unexpected = net.load_state_dict(state, strict=False)
    if unexpected or any(not k.startswith("value_head.") for k in missing):
        raise ValueError(f"--init {path}: weights do not match the network ({missing or unexpected})")


def init_settings(path) -> dict:
    """The network, image and action space an --init agent file was built with, and its sensors unless it reads
    the single camera alone (such a file leaves them as configured: it can start a LIDAR or SPEED net)."""
    metadata = parse_metadata(read_payload(path), str(path))
    image = metadata["image"]
    settings = {"network": metadata["neural_network"], "action_space": {k: metadata[k] for k in
                ("action_space", "action_space_type")}, "camera": (image["height"], image["width"])}
    sensors = metadata_sensors(metadata, str(path))
    if sensors != SensorSuite():
        settings["sensor"] = sensors.names
    return settings


def init_lineage(path) -> dict:
    """What an agent started from, for its training notes: the init file's name, hash and own training notes
    (so the tracks it learnt on stay known to `multirace evaluate`)."""
    payload = read_payload(path)
    metadata = parse_metadata(payload, str(path))
    return {"file": Path(path).name, "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
            "name": metadata.get("name"), "training": metadata.get("training")}


def _with_image_channels(state: dict, net, path) -> dict:
    """`state` with its first convolution widened to `net`'s image channels where the agent read one grey
    channel and the net reads more: the new channels' weights are zero, so the net acts as the agent did."""
    first = next(name for name, value in net.conv.state_dict().items() if value.dim() == 4)
    key, wanted = f"conv.{first}", net.image_shape[2]
    weight = state.get(key)
    if weight is None or weight.shape[1] == wanted:
        return state
    if weight.shape[1] != 1:
        raise ValueError(f"--init {path}: the agent reads {weight.shape[1]}-channel images, the net {wanted}")
    widened = torch.zeros(weight.shape[0], wanted, *weight.shape[2:], dtype=weight.dtype)
    widened[:, :1] = weight
    return {**state, key: widened}
