"""The cars' camera images drawn again, in the replay writer, from what a replay records of the scene.

With the fast renderer and no domain randomisation, a car's camera image is a pure function of the scene:
the track (its texture), the camera, every car's pose, which cars are parked and where the boxes stand.
A replay records the poses of every step anyway, so there the race hands its writer only which cars are
parked at a camera step (`scene_of` decides at the race's start), and the writer draws the images itself
(`SceneCameras`), the same compiled renderer on the same inputs: the pixels the agents saw, without
copying 19 kB per car and frame out of the race. Elsewhere (the PyBullet renderer, randomised episodes,
stereo pairs, state observations) the images are carried as they are.
"""
from __future__ import annotations

import numpy as np

from ..sensors.camera import CameraSpec
from ..sensors.fast_renderer import FastRenderer
from ..sim.car import CarSpec
from ..sim.texture import TrackTexture

REDRAWN_CAMERAS = ("mono", "frames")  # sensor kinds whose recorded image is the car's one camera, this step


def scene_of(env) -> dict | None:
    """What `SceneCameras` needs to draw `env`'s camera observations again (picklable), or None where they are
    not exactly the fast renderer's images of the recorded poses."""
    if (env.renderer_name != "fast" or env.observation != "camera" or env.randomization.enabled
            or env.sensors.camera not in REDRAWN_CAMERAS or env.renderer is None):
        return None
    return {"camera": env.camera, "car_spec": env.car_spec, "track": env.track, "palette": env.texture.palette,
            "obstacle_poses": env.world.obstacle_poses.copy()}


class _Scene:
    """The world as the renderer reads it (`FastRenderer.render_cars`): poses, parked cars, boxes, car size."""

    def __init__(self, spec: CarSpec, obstacle_poses: np.ndarray):
        self.spec, self.obstacle_poses = spec, obstacle_poses
        self.poses = self.parked = None


class SceneCameras:
    """Draws the cars' camera images of a recorded step (the writer's side of `scene_of`)."""

    def __init__(self, camera: CameraSpec, car_spec: CarSpec, track, palette, obstacle_poses: np.ndarray):
        self.renderer = FastRenderer(camera, TrackTexture(track, palette))
        self._scene = _Scene(car_spec, np.ascontiguousarray(obstacle_poses, np.float64))
        self._grey = camera.grayscale

    def draw(self, cars, poses: np.ndarray, parked) -> np.ndarray:
        """The camera images of `cars` with every car at `poses` (n, 3: x, y, yaw) and `parked` (n bools) off the
        scene, as the env observed them: (k, H, W) grey or (k, H, W, 3) RGB."""
        scene = self._scene
        scene.poses = np.ascontiguousarray(poses, np.float64)
        scene.parked = np.asarray(parked, np.bool_)
        images = self.renderer.render_cars(scene, cars)
        return images[..., 0] if self._grey else images
