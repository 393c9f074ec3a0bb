"""``bot:weave@SPEED``: a driver that does not hold its line, as a camera car in traffic does not.

Its line drifts from side to side and its speed dips without warning (a brake
in the middle of a straight), at SPEED m/s between the dips. Both follow a
fixed pattern of race time and of where the car is on the lap, so a race with
it is as reproducible as any other. It keeps the bots' courtesy behind a car
in its way. A rival for training racers to keep a margin: the shipped camera
agents weave and brake like this, the other bots do not.
"""
from __future__ import annotations

import dataclasses
import math

from .base import Bot, speed_in_traffic

DRIFT_SHARE = 0.6  # of the road's half-width on each side: how far out the line drifts
DRIFT_PERIODS = (1.9, 3.1)  # s: two sines, so the drift does not repeat lap after lap
DIP_PERIOD = 3.7  # s between speed dips (shifted along the lap)
DIP_DEPTH = 0.6  # share of its speed a dip takes off at its deepest


@dataclasses.dataclass
class WeaveBot(Bot):
    """Drifts across the road and dips its speed (`weave_command`), slowing behind a car."""

    kind = "weave"

    def steer(self, at):
        return weave_command(at, self.speed)


def weave_command(at, speed: float) -> tuple[float, float]:
    """(steering degrees, speed m/s) of a weaving driver at `speed` in the situation `at`."""
    t, s = at.time, at.proj.s
    drift = 0.5 * (math.sin(2 * math.pi * t / DRIFT_PERIODS[0] + s)
                   + math.sin(2 * math.pi * t / DRIFT_PERIODS[1] + 0.5 * s))  # -1 .. 1
    half = at.proj.left_width if drift > 0 else at.proj.right_width
    dip = max(0.0, math.sin(2 * math.pi * t / DIP_PERIOD + 0.7 * s)) ** 4
    pace = speed_in_traffic(speed * (1.0 - DIP_DEPTH * dip), at.traffic, at.spec)
    return at.pursue(max(pace, at.spec.min_speed), DRIFT_SHARE * half * drift)
