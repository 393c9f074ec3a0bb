"""The car's motion: a single-track (bicycle) model with tyre forces and a drive train with limits.

One compiled kernel (`drive`) advances every car over one action step, in
substeps of `DynamicsParams.dt` seconds. State per car, in its own frame: forward speed
`u`, sideways speed `v` (+ left) and yaw rate `r`. The model:

- Drive train: the commanded speed is a target; the longitudinal force that
  chases it is limited to the motor's acceleration (`accel`, lower at speed:
  the force falls linearly to zero at `top_speed`) and the brakes'
  deceleration (`brake`), and is shared by all four wheels (4WD).
- Tyres: each axle's lateral force is a saturating curve of its slip angle,
  ``mu Fz sin(C atan(B alpha))`` (Pacejka's shape), reduced by the
  longitudinal force the axle carries (friction circle): past the grip limit
  the car slides, its path radius grows and it can spin. The rear tyres grip
  a little more than the front ones (`rear_grip`), so past the limit the car
  slides wide (understeer) rather than spinning, as a set-up RC car does.
- Yaw: ``Iz r' = lf Fyf cos(delta) - lr Fyr``.
- Below `kinematic_speed` the tyre model is ill-conditioned (slip angles of a
  barely moving car), so the motion blends to the kinematic bicycle
  (no slip) between `kinematic_speed` and twice that speed.

`advance` returns a car's new state and its displacement over the step
(forward, left, yaw in the car's frame at the start), which `drive` turns
into the body velocity PyBullet integrates; PyBullet owns the contacts, and
whatever a contact adds to a body's velocity is fed back into the state.
"""
from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from .car import GRAVITY



@dataclasses.dataclass(frozen=True)
class DynamicsParams:
    """The numbers the kernel needs, from a `CarSpec` (see there for where each comes from)."""

    mass: float
    yaw_inertia: float
    front_axle: float  # lf: centre of mass to the front axle, m
    rear_axle: float  # lr
    mu: float
    rear_grip: float  # the rear tyres' friction over the front's
    tyre_b: float
    tyre_c: float
    accel: float
    brake: float
    top_speed: float
    drive_time_constant: float
    kinematic_speed: float
    dt: float

    def as_array(self) -> np.ndarray:
        return np.array([self.mass, self.yaw_inertia, self.front_axle, self.rear_axle, self.mu, self.tyre_b,
                         self.tyre_c, self.accel, self.brake, self.top_speed, self.drive_time_constant,
                         self.kinematic_speed, self.dt, self.rear_grip])


@numba.njit(cache=True)
def advance(u, v, r, delta, target, grip, motor, params, step_time):
    """Advance one car over `step_time` seconds from its state (u, v, r) under its command (steer `delta` rad,
    `target` speed m/s); grip and motor scale its friction and motor force (randomisation; 1.0 nominal).
    Returns (u, v, r, x, y, yaw): its new state and its displacement (forward m, left m, yaw rad) in its
    starting frame."""
    mass, iz, lf, lr, mu0, b_tyre, c_tyre = params[0], params[1], params[2], params[3], params[4], params[5], params[6]
    accel0, brake, top, tau, v_kin, dt_max = params[7], params[8], params[9], params[10], params[11], params[12]
    rear_grip = params[13]
    wheelbase = lf + lr
    substeps = max(1, int(math.ceil(step_time / dt_max - 1e-9)))
    dt = step_time / substeps
    mu, accel = mu0 * grip, accel0 * motor
    mu_rear = mu * rear_grip
    fz_front = mass * GRAVITY * lr / wheelbase
    fz_rear = mass * GRAVITY * lf / wheelbase
    # what the steering sets for the whole step (computed once: the same values in every substep)
    cos_d, sin_d = math.cos(delta), math.sin(delta)
    tan_d = math.tan(delta)
    beta = math.atan(lr / wheelbase * tan_d)
    cos_beta, tan_beta = math.cos(beta), math.tan(beta)
    x, y, yaw = 0.0, 0.0, 0.0
    for _ in range(substeps):
        # drive train: chase the target speed within the motor's and the brakes' limits
        want = mass * (target - u) / tau
        if want > 0.0:
            limit = mass * accel * max(0.0, 1.0 - u / top)
            fx = min(want, limit)
        else:
            fx = max(want, -mass * brake)
        fx_front, fx_rear = 0.5 * fx, 0.5 * fx
        # tyres: saturating lateral force, reduced by the longitudinal force (friction circle)
        cap_f = math.sqrt(max((mu * fz_front) ** 2 - fx_front ** 2, 0.0))
        cap_r = math.sqrt(max((mu_rear * fz_rear) ** 2 - fx_rear ** 2, 0.0))
        fx_front = max(min(fx_front, mu * fz_front), -mu * fz_front)
        fx_rear = max(min(fx_rear, mu_rear * fz_rear), -mu_rear * fz_rear)
        u_safe = max(abs(u), 0.05)
        alpha_f = delta - math.atan2(v + lf * r, u_safe)
        alpha_r = -math.atan2(v - lr * r, u_safe)
        fy_front = cap_f * math.sin(c_tyre * math.atan(b_tyre * alpha_f))
        fy_rear = cap_r * math.sin(c_tyre * math.atan(b_tyre * alpha_r))
        du = (fx_front * cos_d - fy_front * sin_d + fx_rear) / mass + v * r
        dv = (fx_front * sin_d + fy_front * cos_d + fy_rear) / mass - u * r
        dr = (lf * (fx_front * sin_d + fy_front * cos_d) - lr * fy_rear) / iz
        u_dyn, v_dyn, r_dyn = u + du * dt, v + dv * dt, r + dr * dt
        # kinematic bicycle at walking pace: no slip, yaw rate from the steering geometry
        speed = math.hypot(u, v)
        u_kin = u + (fx_front + fx_rear) / mass * dt
        r_kin = u_kin * cos_beta * tan_d / wheelbase
        v_kin_state = u_kin * tan_beta
        w = min(max((speed - v_kin) / v_kin, 0.0), 1.0)  # 0: kinematic .. 1: dynamic
        u = w * u_dyn + (1.0 - w) * u_kin
        v = w * v_dyn + (1.0 - w) * v_kin_state
        r = w * r_dyn + (1.0 - w) * r_kin
        if u < 0.0 and target >= 0.0 and speed < 0.05:  # brakes hold a stopped car; no reversing
            u = 0.0
        # integrate the pose in the starting frame
        cy, sy = math.cos(yaw), math.sin(yaw)
        x += (u * cy - v * sy) * dt
        y += (u * sy + v * cy) * dt
        yaw += r * dt
    return u, v, r, x, y, yaw


@numba.njit(cache=True)
def drive(poses, motion, velocity, rows, pushes, commands, grip, motor, params, step_time):
    """Advance the cars `rows` over one action step and set the world velocities that carry them there.

    poses (n, 3) of (x, y, yaw); motion (n, 3) of (u, v, r), updated in place after adding each car's push
    (pushes (n, 3): x, y, yaw rate in the world frame, what contacts added since the last step); commands (n, 2)
    of (steer rad, target speed m/s); velocity (n, 3) receives (x, y, yaw rate) in the world frame: the step's
    displacement over its time.
    """
    for i in rows:
        cos_y, sin_y = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        push_x, push_y = pushes[i, 0], pushes[i, 1]
        u, v, r, forward, left, turn = advance(motion[i, 0] + (push_x * cos_y + push_y * sin_y),
                                               motion[i, 1] + (-push_x * sin_y + push_y * cos_y),
                                               motion[i, 2] + pushes[i, 2], commands[i, 0], commands[i, 1],
                                               grip[i], motor[i], params, step_time)
        motion[i, 0], motion[i, 1], motion[i, 2] = u, v, r
        forward, left = forward / step_time, left / step_time
        velocity[i, 0] = forward * cos_y - left * sin_y
        velocity[i, 1] = forward * sin_y + left * cos_y
        velocity[i, 2] = turn / step_time
