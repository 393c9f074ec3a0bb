"""The DeepRacer car: its dimensions, steering and speed limits, and action noise.

The car's reference point (its PyBullet base) is the centre of the body,
midway between the axles. DeepRacer reports `x, y` as the point 0.14 m ahead
of the rear axle; `CarSpec.reported_point_offset` converts between the two.
The kinematic bicycle (Ackermann) model that drives it is in `world.World.step`.
"""
from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class CarSpec:
    """Physical constants of a 1/18-scale DeepRacer car (metres, kg, radians)."""

    wheelbase: float = 0.164  # front to rear axle
    track: float = 0.16  # left to right wheel centres
    wheel_radius: float = 0.035
    length: float = 0.32  # body, bumper to bumper
    width: float = 0.20
    height: float = 0.12
    mass: float = 1.5
    max_steer: float = math.radians(30.0)
    min_speed: float = 0.1  # m/s, DeepRacer's commanded speed range
    max_speed: float = 4.0
    speed_time_constant: float = 0.08  # s, first-order lag of the drive train
    grip_time_constant: float = 0.06  # s, how fast tyres cancel a push or spin
    steer_noise: float = 0.01  # rad, DeepRacer adds N(0, 0.01 rad) to steering
    speed_noise: float = 0.1  # m/s, DeepRacer adds N(0, 0.1 m/s) to speed

    @property
    def reported_point_offset(self) -> float:
        """Distance from the body centre to DeepRacer's reported (x, y) point."""
        return 0.14 - self.wheelbase / 2

    def wheel_offsets(self) -> tuple[tuple[float, float], ...]:
        """(forward, left) positions of the four wheel contact points from the centre."""
        half_l, half_t = self.wheelbase / 2, self.track / 2
        return ((half_l, half_t), (half_l, -half_t), (-half_l, half_t), (-half_l, -half_t))

    def clamp_command(self, steer: float, speed: float) -> tuple[float, float]:
        """Clip a command to the car's steering and speed range."""
        steer = min(max(steer, -self.max_steer), self.max_steer)
        speed = min(max(speed, self.min_speed), self.max_speed)
        return steer, speed

