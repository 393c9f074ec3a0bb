"""``SPEED``: the car's own drive speed, a multirace sensor for research (the worked example of `registry`).

DeepRacer's cars have no speed sensor (their model_metadata ``sensor`` list
knows only cameras and LIDARs), so an agent that reads ``SPEED`` races in
multirace but cannot be exported to DeepRacer. It fills the observation key
``speed`` with one float32: the car's speed along its body in m/s, the
``speed`` of its `CarState` in ``env.race_state`` after the same step.
"""
from __future__ import annotations

import numpy as np

from .sensor import SensorView, VectorSensor


class Speed(VectorSensor):
    """The car's drive speed, m/s: float32 (1,)."""

    name, key, kind, unit = "SPEED", "speed", "speed", "SPEED value"
    inputs, low, high = 1, -np.inf, np.inf
    on_deepracer = False

    def observe(self, view: SensorView) -> np.ndarray:
        return view.world.drive_speed[view.cars].astype(np.float32).reshape(-1, 1)
