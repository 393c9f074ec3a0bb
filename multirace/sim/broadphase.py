"""Which bodies can touch within a step (the conservative test that decides whether PyBullet must run), and
how cars move in a step that does not need it (`drive_cars`: the whole step of the dynamic model in one call).

Cars move by their motion model; PyBullet is only needed where two bodies can
meet. The test mirrors PyBullet's own broad phase: each body is its
axis-aligned bounding box, padded, swept over the step at the velocity set for
the step. It can say "may touch" for bodies that will not, but never
"cannot" for bodies PyBullet would pair. The pad is wider than PyBullet's own
pairing distance, so PyBullet holds no pair of bodies that the shortcut moves:
a body put back in place while PyBullet holds a pair for it changes how that
pair's later contacts resolve.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from .dynamics import drive


@numba.njit(cache=True)
def _half_extents(length, width, yaw):
    """Half sizes along x and y of the axis-aligned box around a length x width rectangle turned by yaw."""
    c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
    return 0.5 * (length * c + width * s), 0.5 * (length * s + width * c)


@numba.njit(cache=True)
def may_touch(car_poses, car_velocity, box_poses, car_size, box_size, step_time, pad):
    """Whether any two bodies' padded bounding boxes can overlap over `step_time` seconds.

    car_poses (n, 3) are the cars' (x, y, yaw) and car_velocity (n, 2 or more) their x, y velocities (held over
    the step; further columns are not read);
    box_poses (m, 3) the boxes' (at rest); car_size and box_size (length, width). Each body's axis-aligned
    box is grown by `pad` on every side; two boxes can overlap only if, along both axes, the gap between
    their centres is at most the sum of their half sizes and pads plus the relative speed along the axis
    times the step.
    """
    n = car_poses.shape[0]
    for i in range(n):
        hx_i, hy_i = _half_extents(car_size[0], car_size[1], car_poses[i, 2])
        for j in range(i + 1, n):
            hx_j, hy_j = _half_extents(car_size[0], car_size[1], car_poses[j, 2])
            if (abs(car_poses[i, 0] - car_poses[j, 0]) <= hx_i + hx_j + 2 * pad
                    + step_time * abs(car_velocity[i, 0] - car_velocity[j, 0])
                    and abs(car_poses[i, 1] - car_poses[j, 1]) <= hy_i + hy_j + 2 * pad
                    + step_time * abs(car_velocity[i, 1] - car_velocity[j, 1])):
                return True
        for k in range(box_poses.shape[0]):
            hx_k, hy_k = _half_extents(box_size[0], box_size[1], box_poses[k, 2])
            if (abs(car_poses[i, 0] - box_poses[k, 0]) <= hx_i + hx_k + 2 * pad + step_time * abs(car_velocity[i, 0])
                    and abs(car_poses[i, 1] - box_poses[k, 1]) <= hy_i + hy_k + 2 * pad
                    + step_time * abs(car_velocity[i, 1])):
                return True
    return False


@numba.njit(cache=True)
def move_freely(poses, velocity, rows, substeps, dt):
    """Move the cars `rows` as PyBullet moves a body that touches nothing: each of `substeps` physics steps
    adds velocity x dt to the position; the heading turns by the yaw rate x the whole step, kept in [-pi, pi]."""
    for k in range(rows.shape[0]):
        i = rows[k]
        x, y = poses[i, 0], poses[i, 1]
        for _ in range(substeps):
            x += velocity[i, 0] * dt
            y += velocity[i, 1] * dt
        yaw = poses[i, 2] + velocity[i, 2] * dt * substeps
        if yaw > math.pi:
            yaw -= 2 * math.pi
        elif yaw < -math.pi:
            yaw += 2 * math.pi
        poses[i, 0], poses[i, 1], poses[i, 2] = x, y, yaw


@numba.njit(cache=True)
def drive_cars(poses, motion, velocity, drive_speed, parked, stale, pushes, commands, grip, motor, params,
               box_poses, car_size, box_size, substeps, dt, pad, shortcut):
    """One action step of the cars not `parked` under the dynamic model, in one compiled call (each call from
    Python costs per argument): their tyre model (`dynamics.drive`; `drive_speed` is their new forward speed), then,
    with `shortcut`, if no two bodies can touch within the step (`may_touch`), their free move (`move_freely`),
    marking them `stale`. Returns whether they moved; if not, PyBullet must step them at the velocities set.

    numba's cache keys this kernel on this file alone: a change to `dynamics.drive` (compiled into it) needs a
    change here too, or a cached copy runs the old tyre model (last: `dynamics` compiled without FMA
    contraction)."""
    rows = np.flatnonzero(~parked)
    step_time = dt * substeps
    drive(poses, motion, velocity, rows, pushes, commands, grip, motor, params, step_time)
    for i in rows:
        drive_speed[i] = motion[i, 0]
    if not shortcut:
        return False
    if rows.shape[0] == parked.shape[0]:  # none parked: no copies
        touch = may_touch(poses, velocity, box_poses, car_size, box_size, step_time, pad)
    else:
        touch = may_touch(poses[rows], velocity[rows], box_poses, car_size, box_size, step_time, pad)
    if touch:
        return False
    move_freely(poses, velocity, rows, substeps, dt)
    for i in rows:
        stale[i] = True
    return True
