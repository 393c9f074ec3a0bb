"""The front camera: its mounting, its optics, and the renderer interface.

A renderer turns the world's current state into a car's camera image,
``renderer.render(world, car, pose) -> uint8 (H, W, C)``, or the images of
several cars at once from the batched poses of `camera_poses`
(``renderer.render_many(world, cars, eyes, rotations)``). Two implement it:
`pybullet_renderer.PyBulletRenderer` (TinyRenderer, the reference) and
`fast_renderer.FastRenderer` (a perspective warp of the flat track, the default).

Camera frame convention (OpenCV): x right, y down, z forward.
"""
from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

NEAR_PLANE = 0.01
FAR_PLANE = 60.0


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """Image size and mounting of the front camera."""

    height: int = 120
    width: int = 160
    grayscale: bool = True
    hfov: float = 1.13  # rad, horizontal field of view
    forward: float = 0.165  # m ahead of the body centre (at the front bumper)
    mount_height: float = 0.14  # m above the ground
    pitch: float = math.radians(15.0)  # tilted down
    stereo_baseline: float = 0.06  # m between the two cameras of STEREO_CAMERAS (the Evo's pair, estimated)

    @property
    def channels(self) -> int:
        return 1 if self.grayscale else 3

    @property
    def focal(self) -> float:
        """Focal length in pixels (square pixels)."""
        return (self.width / 2) / math.tan(self.hfov / 2)

    @property
    def vfov(self) -> float:
        """Vertical field of view, radians."""
        return 2 * math.atan((self.height / 2) / self.focal)

    def intrinsics(self) -> np.ndarray:
        """3x3 pinhole matrix K with the principal point at the image centre."""
        f = self.focal
        return np.array([[f, 0.0, self.width / 2], [0.0, f, self.height / 2], [0.0, 0.0, 1.0]])


def observation_shape(image_shape) -> tuple[int, ...]:
    """The env's observation array for camera images of (height, width, channels): (H, W) for one grey
    channel (an image PIL and PettingZoo save as it is), else (H, W, C)."""
    height, width, channels = (int(v) for v in image_shape)
    return (height, width) if channels == 1 else (height, width, channels)


def image_shape_of(observation_shape) -> tuple[int, int, int]:
    """(height, width, channels) of camera observations of `observation_shape`: (H, W) is one grey channel."""
    shape = tuple(int(v) for v in observation_shape)
    return (*shape, 1) if len(shape) == 2 else shape


@dataclasses.dataclass(frozen=True)
class CameraPose:
    """Where a camera is and how it is turned (world frame)."""

    eye: np.ndarray  # (3,) position
    rotation: np.ndarray  # (3, 3) rows: camera x (right), y (down), z (forward) in world axes

    @property
    def forward(self) -> np.ndarray:
        return self.rotation[2]

    @property
    def down(self) -> np.ndarray:
        return self.rotation[1]


def camera_pose(spec: CameraSpec, car_pose, jitter=(0.0, 0.0, 0.0)) -> CameraPose:
    """Pose of the camera on a car at (x, y, yaw); `jitter` adds (yaw, pitch, height) offsets."""
    eyes, rotations = camera_poses(spec, np.asarray([car_pose], dtype=float), np.asarray([jitter], dtype=float))
    return CameraPose(eye=eyes[0], rotation=rotations[0])


def camera_poses(spec: CameraSpec, car_poses: np.ndarray, jitter: np.ndarray | None = None):
    """Cameras of several cars at once: eyes (n, 3) and rotations (n, 3, 3) (rows: right, down, forward).

    `car_poses` is (n, 3) of (x, y, yaw); `jitter`, if given, (n, 3) of (yaw,
    pitch, height) offsets.
    """
    if jitter is None:
        jitter = np.zeros((len(car_poses), 3))
    return _camera_poses(car_poses, jitter, spec.forward, spec.mount_height, spec.pitch)


@numba.njit(cache=True)
def _camera_poses(car_poses, jitter, forward, mount_height, pitch):
    n = car_poses.shape[0]
    eyes, rotations = np.empty((n, 3)), np.empty((n, 3, 3))
    for k in range(n):
        x, y, yaw = car_poses[k, 0], car_poses[k, 1], car_poses[k, 2]
        cam_yaw, cam_pitch = yaw + jitter[k, 0], pitch + jitter[k, 1]
        eyes[k, 0], eyes[k, 1] = x + forward * math.cos(yaw), y + forward * math.sin(yaw)
        eyes[k, 2] = mount_height + jitter[k, 2]
        cp, sp = math.cos(cam_pitch), math.sin(cam_pitch)
        cy, sy = math.cos(cam_yaw), math.sin(cam_yaw)
        rotations[k, 0, 0], rotations[k, 0, 1], rotations[k, 0, 2] = sy, -cy, 0.0  # right
        rotations[k, 1, 0], rotations[k, 1, 1], rotations[k, 1, 2] = -sp * cy, -sp * sy, -cp  # down = forward x right
        rotations[k, 2, 0], rotations[k, 2, 1], rotations[k, 2, 2] = cp * cy, cp * sy, -sp  # forward
    return eyes, rotations


class Renderer:
    """Interface: draws one car's camera image from the world's state."""

    def __init__(self, spec: CameraSpec):
        self.spec = spec

    def render(self, world, car: int, pose: CameraPose) -> np.ndarray:
        """uint8 image (H, W, C) seen from `pose` by car `car` (which is not drawn)."""
        raise NotImplementedError

    def render_many(self, world, cars: list[int], eyes: np.ndarray, rotations: np.ndarray):
        """Images of several cars' cameras, posed as `camera_poses` returns: a list of (H, W, C) images or one
        (n, H, W, C) array (renderers may batch this)."""
        return [self.render(world, car, CameraPose(eye=eye, rotation=rotation))
                for car, eye, rotation in zip(cars, eyes, rotations)]

    def close(self) -> None:
        """Release what the renderer holds."""


def stereo_poses(spec: CameraSpec, eyes: np.ndarray, rotations: np.ndarray):
    """The stereo pair of each camera pose: eyes (2n, 3) and rotations (2n, 3, 3), the n left cameras
    first, then the n right ones, each half the baseline to its side, looking the same way."""
    offsets = rotations[:, 0, :] * (spec.stereo_baseline / 2)  # along each camera's right axis
    return np.concatenate([eyes - offsets, eyes + offsets]), np.concatenate([rotations, rotations])
