"""Camera policy networks, selectable by DeepRacer-style network name.

Every network takes camera images as the env gives them, uint8 (H, W) grey or
(H, W, C) (a batch is (B, H, W) or (B, H, W, C); `channels_first`), scales them
to [0, 1] and outputs one row per image:

- discrete action space: one logit per action;
- continuous action space: 4 numbers, ``[mean_steer, mean_speed, log_std_steer,
  log_std_speed]``, the means in DeepRacer units (degrees, m/s) as the env's Box
  action space uses them.

``net(obs)`` gives those outputs; with ``value_head=True`` the module also has
``net.value(obs)`` (B,) and ``net.forward_all(obs) -> (outputs, value)`` sharing
one trunk pass (for PPO). Networks (``NETWORKS``):

- ``DEEP_CONVOLUTIONAL_NETWORK_SHALLOW``: DeepRacer's shallow net, conv 32 8x8
  stride 4, conv 64 4x4/2, conv 64 3x3/1, fully connected 512 (about 5.8 M
  parameters, 23 MB, at 120x160).
- ``MULTIRACE_SMALL_CNN`` (our default): a 2x average pool, conv 16 5x5/2,
  conv 32 3x3/2, conv 32 3x3/2, conv 64 3x3/1, fully connected 128 (about 0.2 M
  parameters, under 1 MB at 120x160).

- ``MULTIRACE_TINY_CNN`` (PPO training's default): a 4x average pool (30x40),
  conv 16 5x5/2, conv 32 3x3/2, conv 32 3x3/1, fully connected 128 (about
  0.11 M parameters); about 3x cheaper than the small net to train and run.

Beside the camera a net may read vector sensors (`sensors.registry`): its
``vector_inputs`` are the schema's {observation key: values per step}
(`SensorSuite.vector_inputs`, e.g. ``{"lidar": 64, "speed": 1}``;
``lidar_samples=n`` is the shorthand for ``{"lidar": n}``). Such a net takes
observations as the env gives them, ``{"camera": images, "lidar": ranges,
...}``: each vector goes through two fully connected layers of 64 (named after
its key: DeepRacer's own LIDAR embedder is dense layers too), whose outputs
join the flattened convolution features, in the schema's order, before the
hidden layer. `add_vector_inputs` widens a net into one that reads more
vectors and starts out acting exactly as it did.

A network is fully determined by (name, image shape, vector inputs, number of
outputs, value head), which is what an agent file's metadata records; weights
are loaded into it as plain tensors.
"""
from __future__ import annotations

import functools
import itertools

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

SMALL = "MULTIRACE_SMALL_CNN"
SHALLOW = "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"
TINY = "MULTIRACE_TINY_CNN"
DEFAULT_NETWORK = SMALL
CONTINUOUS_OUTPUTS = 4  # mean steer, mean speed, log-std steer, log-std speed
VECTOR_HIDDEN = 64  # width of the two layers each vector input goes through


class AveragePool(nn.AvgPool2d):
    """`nn.AvgPool2d(k)` computed as a fixed depthwise convolution: the same numbers, faster on CPU.

    (torch's CPU average pool is several times slower than this convolution on small batches of
    single-channel images.) The kernel is not saved with the weights, so agent files are unchanged.
    """

    def __init__(self, kernel: int, channels: int):
        super().__init__(kernel)
        self.register_buffer("weight", torch.full((channels, 1, kernel, kernel), 1.0 / kernel**2), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, self.weight, stride=self.kernel_size, groups=self.weight.shape[0])


def _shallow_trunk(channels: int) -> tuple[nn.Module, int]:
    trunk = nn.Sequential(
        nn.Conv2d(channels, 32, 8, stride=4), nn.ReLU(),
        nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
        nn.Conv2d(64, 64, 3, stride=1), nn.ReLU(),
        nn.Flatten(),
    )
    return trunk, 512


def _small_trunk(channels: int) -> tuple[nn.Module, int]:
    trunk = nn.Sequential(
        AveragePool(2, channels),
        nn.Conv2d(channels, 16, 5, stride=2), nn.ReLU(),
        nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=2), nn.ReLU(),
        nn.Conv2d(32, 64, 3, stride=1), nn.ReLU(),
        nn.Flatten(),
    )
    return trunk, 128


def _tiny_trunk(channels: int) -> tuple[nn.Module, int]:
    trunk = nn.Sequential(
        AveragePool(4, channels),
        nn.Conv2d(channels, 16, 5, stride=2), nn.ReLU(),
        nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
        nn.Flatten(),
    )
    return trunk, 128


NETWORKS = {SHALLOW: _shallow_trunk, SMALL: _small_trunk, TINY: _tiny_trunk}


@functools.lru_cache(maxsize=None)
def input_pool(network: str) -> int:
    """The kernel of the average pool `network`'s trunk starts with (1: none). Training workers may send
    images pooled that far (`pool_image`), as the net's first layer would see them."""
    first = NETWORKS[network](1)[0][0]
    return int(first.kernel_size) if isinstance(first, AveragePool) else 1


def pool_image(image: np.ndarray, k: int) -> np.ndarray:
    """One uint8 image (H, W) or (H, W, C) as int16 sums of its k x k pixel blocks, (H/k, W/k[, C]): what
    `CameraNet.features(..., pooled=True)` reads for a net whose `input_pool` is k."""
    from .pooling import block_sums

    height, width = image.shape[:2]
    channels = image.shape[2] if image.ndim == 3 else 1
    sums = block_sums(np.ascontiguousarray(image).reshape(height, width * channels), k, channels)
    return sums.reshape(height // k, width // k, *image.shape[2:])


def channels_first(images, image_shape) -> torch.Tensor:
    """uint8 camera images (H, W), (H, W, C), (N, H, W) or (N, H, W, C) as the (N, C, H, W) batch a net
    of `image_shape` (H, W, C) convolves; (H, W) and (N, H, W) are one grey channel."""
    x = torch.as_tensor(images)
    height, width, channels = image_shape
    grey = channels == 1 and tuple(x.shape[-2:]) == (height, width) and x.dim() in (2, 3)
    if not grey and (tuple(x.shape[-3:]) != (height, width, channels) or x.dim() not in (3, 4)):
        raise ValueError(f"images of shape {tuple(x.shape)}: the net reads {height}x{width}x{channels} images")
    # flattened first, so every layout of the same pixels gets the same strides (and the same convolution)
    return x.reshape(-1, height * width * channels).view(-1, height, width, channels).permute(0, 3, 1, 2)


RESERVED = ("camera", "conv", "fc", "head", "value_head", "vector_inputs", "network")  # not vector keys


class CameraNet(nn.Module):
    """A camera CNN: convolutional trunk, one hidden fully connected layer, output (and value) head."""

    def __init__(self, network: str = DEFAULT_NETWORK, image_shape=(120, 160, 1), num_outputs: int = 10,
                 value_head: bool = False, lidar_samples: int = 0, vector_inputs: dict | None = None):
        super().__init__()
        if network not in NETWORKS:
            raise ValueError(f"neural_network: unknown network {network!r}; known: {', '.join(NETWORKS)}")
        height, width, channels = (int(v) for v in image_shape)
        if min(height, width) < 32 or channels not in (1, 2, 3):
            raise ValueError(f"image shape {image_shape}: need at least 32x32 pixels and 1 (grey), 2 (stereo "
                             "grey pair) or 3 (colour) channels")
        if int(num_outputs) < 1:
            raise ValueError(f"num_outputs: must be positive, got {num_outputs}")
        self.network = network
        self.image_shape = (height, width, channels)
        self.num_outputs = int(num_outputs)
        self.conv, hidden = NETWORKS[network](channels)
        try:
            with torch.no_grad():
                flat = self.conv(torch.zeros(1, channels, height, width)).shape[1]
        except RuntimeError:
            raise ValueError(f"image shape {image_shape}: too small for {network}") from None
        self.vector_inputs = _vector_inputs(lidar_samples, vector_inputs)
        for key, size in self.vector_inputs.items():  # one branch per key, named after it ("lidar.0.weight")
            self.add_module(key, nn.Sequential(nn.Linear(size, VECTOR_HIDDEN), nn.ReLU(),
                                               nn.Linear(VECTOR_HIDDEN, VECTOR_HIDDEN), nn.ReLU()))
            flat += VECTOR_HIDDEN
        if "lidar" not in self.vector_inputs:
            self.lidar = None
        self.fc = nn.Sequential(nn.Linear(flat, hidden), nn.ReLU())
        self.head = nn.Linear(hidden, self.num_outputs)
        self.value_head = nn.Linear(hidden, 1) if value_head else None

    @property
    def lidar_samples(self) -> int:
        """The LIDAR values it reads per step (0: none)."""
        return self.vector_inputs.get("lidar", 0)

    @property
    def has_value(self) -> bool:
        return self.value_head is not None

    def features(self, obs, pooled: bool = False) -> torch.Tensor:
        """The hidden features of uint8 images, one or a batch (see `channels_first`).

        A net with vector inputs takes ``{"camera": images, key: values (B, n) or (n,), ...}``. With `pooled`,
        the images are the block sums of `pool_image` (the net's own first pool done already): the same
        features, without the pool's cost.
        """
        vectors = {}
        if self.vector_inputs:
            if not isinstance(obs, dict) or not all(key in obs for key in self.vector_inputs):
                raise ValueError(f"this net needs {{'camera': images, {', '.join(map(repr, self.vector_inputs))}: "
                                 "values}} observations")
            vectors = {key: torch.as_tensor(obs[key], dtype=torch.float32) for key in self.vector_inputs}
            obs = obs["camera"]
        if pooled:
            k = input_pool(self.network)
            height, width, channels = self.image_shape
            x = channels_first(obs, (height // k, width // k, channels)).float().mul_(1.0 / (255 * k * k))
            for layer in itertools.islice(self.conv, 1, None):  # the trunk after its pool (no slice: a new module)
                x = layer(x)
        else:
            x = self.conv(channels_first(obs, self.image_shape).float().div_(255.0))
        if vectors:
            x = torch.cat([x, *(self.get_submodule(key)(values.reshape(x.shape[0], self.vector_inputs[key]))
                                for key, values in vectors.items())], dim=1)
        return self.fc(x)

    def forward(self, obs, pooled: bool = False) -> torch.Tensor:
        """Action logits (discrete) or [mean steer, mean speed, log-std steer, log-std speed] (`pooled`: see
        `features`)."""
        return self.head(self.features(obs, pooled))

    def value(self, obs) -> torch.Tensor:
        """State value estimate, shape (B,)."""
        if self.value_head is None:
            raise RuntimeError("this network was built without a value head")
        return self.value_head(self.features(obs)).squeeze(-1)

    def forward_all(self, obs, pooled: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(outputs, value or None) from one pass through the trunk (`pooled`: see `features`)."""
        h = self.features(obs, pooled)
        value = self.value_head(h).squeeze(-1) if self.value_head is not None else None
        return self.head(h), value


def _vector_inputs(lidar_samples: int, vector_inputs: dict | None) -> dict[str, int]:
    """{key: size} of a net's vector inputs, from the schema's dict or the LIDAR shorthand; ValueError if bad."""
    inputs = dict(vector_inputs or {})
    if lidar_samples:
        if int(lidar_samples) < 0 or inputs.get("lidar", lidar_samples) != lidar_samples:
            raise ValueError(f"lidar_samples: must be 0 (no LIDAR) or positive, got {lidar_samples}")
        inputs = {"lidar": int(lidar_samples), **inputs}
    for key, size in inputs.items():
        if not key.isidentifier() or key in RESERVED or int(size) < 1:
            raise ValueError(f"vector input {key!r}: {size} values; a net's vector inputs are named by their "
                             f"observation keys (not {', '.join(RESERVED)}) and read at least one value")
    return {key: int(size) for key, size in inputs.items()}


def add_vector_inputs(net: CameraNet, inputs: dict[str, int]) -> CameraNet:
    """A copy of `net` that also reads the vector `inputs` ({key: size}, new keys only), whose new branches
    start with zero weight into the hidden layer: its outputs equal the old net's for any values, until
    training gives them a say. The branches keep the order of `inputs` after the net's own."""
    added = {key: size for key, size in inputs.items() if key not in net.vector_inputs}
    if not added or len(added) != len(inputs):
        raise ValueError(f"the net already reads {sorted(set(inputs) & set(net.vector_inputs))}; "
                         f"add only new vector inputs, not {sorted(inputs)}")
    wide = CameraNet(net.network, net.image_shape, net.num_outputs, net.has_value,
                     vector_inputs={**net.vector_inputs, **added})
    state = net.state_dict()
    old = state["fc.0.weight"]
    weight = torch.zeros_like(wide.fc[0].weight)
    weight[:, :old.shape[1]] = old
    state["fc.0.weight"] = weight
    state.update({k: v for k, v in wide.state_dict().items() if k.split(".")[0] in added})
    wide.load_state_dict(state)
    return wide


def add_lidar_inputs(net: CameraNet, lidar_samples: int) -> CameraNet:
    """A copy of camera-only `net` with a LIDAR branch whose inputs start with zero weight (`add_vector_inputs`)."""
    if net.lidar is not None:
        raise ValueError("the net already has a LIDAR branch")
    return add_vector_inputs(net, {"lidar": lidar_samples})


def num_outputs_for(action_space) -> int:
    """Output size a net needs for an `actions.ActionSpace`."""
    return len(action_space.actions) if action_space.discrete else CONTINUOUS_OUTPUTS


def build_net(network: str = DEFAULT_NETWORK, image_shape=(120, 160, 1), action_space=None,
              value_head: bool = False, lidar_samples: int = 0, vector_inputs: dict | None = None) -> CameraNet:
    """A freshly initialised net for an action space (default: the 10-action DeepRacer space); `vector_inputs`
    are the schema's {key: size} of the sensors beside the camera (`SensorSuite.vector_inputs`)."""
    from ..environment.actions import load_action_space

    space = load_action_space(action_space)
    return CameraNet(network, image_shape, num_outputs_for(space), value_head=value_head,
                     lidar_samples=lidar_samples, vector_inputs=vector_inputs)


def parameter_count(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
