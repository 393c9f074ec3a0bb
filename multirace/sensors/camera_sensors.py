"""The cameras as sensors: DeepRacer's ``FRONT_FACING_CAMERA`` (one camera) and ``STEREO_CAMERAS`` (a grey pair),
and multirace's ``FRONT_FACING_CAMERA_TWO_FRAMES`` (one grey camera, this step's image and the previous one's).

All fill the observation key ``camera`` with uint8 images
(`camera.observation_shape`): (H, W) grey, (H, W, 3) colour, (H, W, 2) for
the stereo pair [left, right] or for the two frames [now, a step before].
``observation`` and ``LEFT_CAMERA`` are DeepRacer's older names for the
single camera. One frame shows where a car ahead is, not how fast it goes;
two frames a step apart show that too (Atari agents read four for the same
reason), which DeepRacer's cars cannot give a model: an agent that reads them
races in multirace but does not export to DeepRacer.
"""
from __future__ import annotations

import numpy as np
from gymnasium import spaces

from .camera import CameraSpec, observation_shape
from .sensor import Sensor, SensorView


def render_cameras(view: SensorView, stereo: bool):
    """The cars' camera images (H, W, C) from the renderer (a list, or one (n, H, W, C) array), the stereo
    pairs' left images first, then the right ones; perturbed by the episode's randomisation, if any."""
    images = view.renderer.render_cars(view.world, view.cars, view.camera_jitter, stereo)
    if view.perturb is not None:
        images = [view.perturb(image) for image in images]
    return images


def grey_images(view: SensorView) -> list[np.ndarray]:
    """The cars' single grey camera images (H, W), one per car: a list, or one (n, H, W) array."""
    images = render_cameras(view, stereo=False)
    return images[..., 0] if isinstance(images, np.ndarray) else [image[:, :, 0] for image in images]


class FrontCamera(Sensor):
    """One front camera: grey (H, W) images, or (H, W, 3) in colour."""

    name, aliases, key, kind, unit = "FRONT_FACING_CAMERA", ("observation", "LEFT_CAMERA"), "camera", "mono", "images"
    channels = None  # the env's: 1 grey or 3 colour

    def space(self, camera: CameraSpec) -> spaces.Box:
        return spaces.Box(0, 255, observation_shape((camera.height, camera.width, camera.channels)), np.uint8)

    def observe(self, view: SensorView):
        """The cars' images, one per car: a list, or one array of them (grey: (n, H, W))."""
        if not view.camera.grayscale:
            return render_cameras(view, stereo=False)
        return grey_images(view)


class StereoCameras(Sensor):
    """Two grey cameras side by side (`CameraSpec.stereo_baseline` apart): (H, W, 2) images [left, right]."""

    name, key, kind, unit = "STEREO_CAMERAS", "camera", "stereo", "stereo images"
    covers = ("FRONT_FACING_CAMERA",)  # a single camera reads the pair's left image
    channels = 2

    def space(self, camera: CameraSpec) -> spaces.Box:
        if not camera.grayscale:
            raise ValueError("sensor: STEREO_CAMERAS are a pair of grey cameras; use grayscale=True")
        return spaces.Box(0, 255, (camera.height, camera.width, 2), np.uint8)

    def observe(self, view: SensorView) -> list[np.ndarray]:
        images = render_cameras(view, stereo=True)
        n = len(view.cars)
        return [np.concatenate([left, right], axis=2) for left, right in zip(images[:n], images[n:])]


class TwoFrameCamera(Sensor):
    """One grey front camera read twice: (H, W, 2) images [this step's, the previous observation's]. The first
    observation after a reset (or after the car was put somewhere else) pairs the image with itself."""

    name, key, kind, unit = "FRONT_FACING_CAMERA_TWO_FRAMES", "camera", "frames", "two-frame images"
    covers = ("FRONT_FACING_CAMERA",)  # a single camera reads this step's image
    channels = 2
    on_deepracer = False

    def space(self, camera: CameraSpec) -> spaces.Box:
        if not camera.grayscale:
            raise ValueError("sensor: FRONT_FACING_CAMERA_TWO_FRAMES is a grey camera; use grayscale=True")
        return spaces.Box(0, 255, (camera.height, camera.width, 2), np.uint8)

    def observe(self, view: SensorView) -> list[np.ndarray]:
        last = view.last_images
        pairs = []
        for car, image in zip(view.cars.tolist(), grey_images(view)):
            pair = np.empty((*image.shape, 2), np.uint8)
            pair[:, :, 0] = image
            pair[:, :, 1] = last.get(car, image)
            last[car] = pair[:, :, 0].copy()  # (the agent may change the observation it is given)
            pairs.append(pair)
        return pairs
