"""The front camera: its mounting, its optics, and the renderer interface.

A renderer turns the world's current state into a car's camera image,
``renderer.render(world, car, pose) -> uint8 (H, W, C)``, or the images of
several cars at once from the batched poses of `camera_poses`
(``renderer.render_many(world, cars, eyes, rotations)``), or of the cameras
on some cars straight from the world (``renderer.render_cars(world, cars)``,
posed by `pose_cameras`, stereo pairs too). Two implement it:
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
    eyes, rotations, _ = car_cameras(spec, car_poses, np.arange(len(car_poses)), jitter)
    return eyes, rotations


NO_JITTER = np.zeros((0, 3))  # `pose_cameras`' jitter of cameras as mounted


def car_cameras(spec: CameraSpec, car_poses: np.ndarray, cars, jitter: np.ndarray | None = None,
                stereo: bool = False):
    """The cameras on `cars` (indices into `car_poses`, (N, 3) of (x, y, yaw)): eyes, rotations and the car of
    each camera, as `pose_cameras` returns them; `jitter`, if given, (n, 3) of (yaw, pitch, height) offsets."""
    return pose_cameras(car_poses, np.asarray(cars, np.int64), NO_JITTER if jitter is None else jitter, spec.forward,
                        spec.mount_height, spec.pitch, spec.stereo_baseline, stereo)


@numba.njit(cache=True)
def pose_cameras(car_poses, cars, jitter, forward, mount_height, pitch, stereo_baseline, stereo):
    """Eyes (m, 3), rotations (m, 3, 3) (rows: right, down, forward) and the car each camera rides on (m,) of the
    cameras on cars (n,); jitter (n, 3) offsets or (0, 3) for none. `stereo`: each camera's pair, half the
    baseline to either side along its right axis and looking the same way, the n left cameras first, then the
    n right ones (m = 2n); else m = n."""
    n = cars.shape[0]
    m = 2 * n if stereo else n
    eyes, rotations, camera_cars = np.empty((m, 3)), np.empty((m, 3, 3)), np.empty(m, np.int64)
    for k in range(n):
        car = cars[k]
        x, y, yaw = car_poses[car, 0], car_poses[car, 1], car_poses[car, 2]
        jitter_yaw = jitter_pitch = jitter_height = 0.0  # none: + 0.0, as zero offsets add
        if jitter.shape[0]:
            jitter_yaw, jitter_pitch, jitter_height = jitter[k, 0], jitter[k, 1], jitter[k, 2]
        cam_yaw, cam_pitch = yaw + jitter_yaw, pitch + jitter_pitch
        eyes[k, 0], eyes[k, 1] = x + forward * math.cos(yaw), y + forward * math.sin(yaw)
        eyes[k, 2] = mount_height + jitter_height
        cp, sp = math.cos(cam_pitch), math.sin(cam_pitch)
        cy, sy = math.cos(cam_yaw), math.sin(cam_yaw)
        rotations[k, 0, 0], rotations[k, 0, 1], rotations[k, 0, 2] = sy, -cy, 0.0  # right
        rotations[k, 1, 0], rotations[k, 1, 1], rotations[k, 1, 2] = -sp * cy, -sp * sy, -cp  # down = forward x right
        rotations[k, 2, 0], rotations[k, 2, 1], rotations[k, 2, 2] = cp * cy, cp * sy, -sp  # forward
        camera_cars[k] = car
    if stereo:
        half = stereo_baseline / 2
        for k in range(n):
            for i in range(3):
                offset = rotations[k, 0, i] * half
                eyes[n + k, i], eyes[k, i] = eyes[k, i] + offset, eyes[k, i] - offset
            rotations[n + k] = rotations[k]
            camera_cars[n + k] = cars[k]
    return eyes, rotations, camera_cars


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

    def render_cars(self, world, cars: np.ndarray, jitter: np.ndarray | None = None, stereo: bool = False):
        """Images of the cameras on `cars` (jittered by `jitter`, (n, 3), if given; `stereo`: the n left cameras
        of the pairs, then the n right ones), as `render_many` returns them."""
        eyes, rotations, camera_cars = car_cameras(self.spec, world.poses, cars, jitter, stereo)
        return self.render_many(world, camera_cars, eyes, rotations)

    def close(self) -> None:
        """Release what the renderer holds."""

