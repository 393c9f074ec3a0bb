"""The schema of one sensor: a named input with its space and its values, the entries of `registry`.

A `Sensor` is stateless (what one must remember between steps, the env keeps
in the view: `SensorView.last_images`): its DeepRacer-style name (the model_metadata
``sensor`` list's word for it), the observation key it fills (a car carries
one sensor per key: ``camera``, ``lidar``, ...), the number of float32 values
it gives per step (0 for a camera image), its gymnasium space for the env's
camera spec (`space`), and its values for the env's camera cars this step
(`observe`, from a `SensorView`: the world, the last published ``RaceState``
and the env's renderer and noise streams).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np
from gymnasium import spaces

from ..sim.car import CarSpec
from .camera import CameraSpec


class SensorView(NamedTuple):
    """What a sensor may read when the env observes: the world after the step and the env's sensor kit (a named
    tuple: the env builds one every step)."""

    world: Any  # sim.world.World: poses, drive speeds, bodies
    cars: np.ndarray  # the camera cars (indices into the world's cars), one observation each
    camera: CameraSpec
    car_spec: CarSpec
    noise: np.random.Generator  # the sensors' own noise stream (LIDAR noise), so a reading changes no other draw
    renderer: Any = None  # renders the camera images (None when nothing is rendered)
    camera_jitter: np.ndarray | None = None  # (cars, 3) camera mount offsets of this episode (domain randomisation)
    perturb: Callable[[np.ndarray], np.ndarray] | None = None  # image perturbation of this episode, per image
    race_state: Any = None  # the RaceState published after the previous reset or step (None before the first)
    last_images: dict | None = None  # {car: its camera image of the previous observation}, kept by the env for
    # sensors that read two frames (they update it); emptied at every reset and for cars put somewhere else


class Sensor:
    """One named input of a car: its schema (`space`) and its values (`observe`)."""

    name: str = ""  # model_metadata's name, e.g. "LIDAR"
    aliases: tuple[str, ...] = ()  # older names read as this sensor
    key: str = ""  # the observation dict key it fills, e.g. "lidar"
    kind: str = ""  # its short name in a `SensorSuite`, e.g. "sector"
    inputs: int = 0  # float32 values per step; 0 for a camera image
    unit: str = ""  # what its values are, for messages ("LIDAR ranges")
    covers: tuple[str, ...] = ()  # sensors of the same key whose readings this one's values give (`reads`)
    on_deepracer: bool = True  # DeepRacer's cars carry it (only these export to DeepRacer)

    def space(self, camera: CameraSpec) -> spaces.Space:
        """Its gymnasium space in an env whose camera is `camera`."""
        raise NotImplementedError

    def observe(self, view: SensorView):
        """Its values for `view.cars`, one row (or image) per car."""
        raise NotImplementedError

    def reads(self, value):
        """What a car with this sensor reads of the value a race env gives under its key (the race may carry a
        sensor that covers this one: a 64-beam scan for SECTOR_LIDAR)."""
        return value

    def blank(self):
        """A reading of nothing at all, as a race env gives it (for smoke tests)."""
        raise NotImplementedError


class VectorSensor(Sensor):
    """A sensor of `inputs` float32 values between `low` and `high`; `empty` is its reading of nothing."""

    low: float = 0.0
    high: float = 1.0
    empty: float = 0.0

    def space(self, camera: CameraSpec) -> spaces.Box:
        return spaces.Box(self.low, self.high, (self.inputs,), np.float32)

    def blank(self) -> np.ndarray:
        return np.full(self.inputs, self.empty, np.float32)
