"""The DeepRacer car: its dimensions, steering and speed limits, and action noise.

The car's reference point (its PyBullet base) is the centre of the body,
midway between the axles. DeepRacer reports `x, y` as the point 0.14 m ahead
of the rear axle; `CarSpec.reported_point_offset` converts between the two.
Its motion: `dynamics` (a single-track model with tyres and a drive train, the
default) or the kinematic bicycle of earlier versions (`World(dynamics="kinematic")`).
"""
from __future__ import annotations

import dataclasses
import math

GRAVITY = 9.81  # m/s^2


@dataclasses.dataclass(frozen=True)
class CarSpec:
    """Physical constants of a 1/18-scale DeepRacer car (metres, kg, radians)."""

    wheelbase: float = 0.164  # front to rear axle
    track: float = 0.16  # left to right wheel centres
    wheel_radius: float = 0.035
    length: float = 0.32  # body, bumper to bumper
    width: float = 0.20
    height: float = 0.12
    mass: float = 1.5  # kg, the DeepRacer car's published mass
    max_steer: float = math.radians(30.0)
    min_speed: float = 0.1  # m/s, DeepRacer's commanded speed range
    max_speed: float = 4.0
    speed_time_constant: float = 0.08  # s, first-order lag of the drive train (kinematic model)
    grip_time_constant: float = 0.06  # s, how fast tyres cancel a push or spin (kinematic model)
    # ---- the dynamic model (sim/dynamics.py)
    yaw_inertia: float = 0.0178  # kg m^2: the 1.5 kg body as a uniform 0.32 x 0.20 m slab, m (l^2 + w^2) / 12
    mu: float = 1.0  # tyre-road friction: the peak lateral acceleration is mu g. Calibrated (README, "Car
    #                   physics"): the racing-line lap sits just under DeepRacer's record laps on every track
    #                   with a record; foam tyres on a printed vinyl track grip about this well
    rear_grip: float = 1.15  # rear tyres' friction over the front's: understeer past the limit, not a spin
    tyre_b: float = 10.0  # Pacejka stiffness factor: the lateral force peaks near 9 degrees of slip ...
    tyre_c: float = 1.4  # ... and falls off past it (shape factor), as a small rubber tyre's does
    accel: float = 6.0  # m/s^2, the motor's launch acceleration, falling to 0 at top_speed: 0-3 m/s in ~1.1 s
    brake: float = 6.0  # m/s^2, braking (motor braking on all four wheels), within the tyres' grip
    top_speed: float = 4.5  # m/s, where the motor's force runs out (DeepRacer commands at most 4.0 m/s)
    drive_time_constant: float = 0.1  # s, how hard the speed control chases the commanded speed
    kinematic_speed: float = 0.5  # m/s: below it the kinematic bicycle, blended to the tyre model by 2x this
    dynamics_dt: float = 1.0 / 600  # s, the kernel's substep (the tyres' time constant is a few ms)
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
        max_steer, min_speed, max_speed = self.max_steer, self.min_speed, self.max_speed
        # conditional expressions, not min(max()): the same values at a fraction of the cost (every car and step)
        steer = -max_steer if steer < -max_steer else max_steer if steer > max_steer else steer
        speed = min_speed if speed < min_speed else max_speed if speed > max_speed else speed
        return steer, speed

