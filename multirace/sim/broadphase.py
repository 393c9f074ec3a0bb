"""Which bodies can touch within a step: the conservative test that decides whether PyBullet must run.

Cars move by their motion model; PyBullet is only needed where two bodies can
meet. Each body is taken as its bounding circle, moving at the velocity set
for the step, so the test can say "may touch" for bodies that will not, but
never "cannot" for bodies that will.
"""
from __future__ import annotations

import math

import numba


@numba.njit(cache=True)
def may_touch(car_xy, car_velocity, box_xy, car_radius, box_radius, step_time, margin):
    """Whether two bodies can come within `margin` of each other over `step_time` seconds (a broad phase).

    car_xy and car_velocity (n, 2) are the cars' centres and velocities (held over the step), box_xy (m, 2)
    the boxes' centres (at rest). Each body is its bounding circle; two circles can touch only if their
    centres are at most the sum of the radii plus the relative speed times the step (plus the margin) apart.
    """
    n = car_xy.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            reach = 2.0 * car_radius + margin + step_time * math.hypot(
                car_velocity[i, 0] - car_velocity[j, 0], car_velocity[i, 1] - car_velocity[j, 1])
            if math.hypot(car_xy[i, 0] - car_xy[j, 0], car_xy[i, 1] - car_xy[j, 1]) <= reach:
                return True
        for k in range(box_xy.shape[0]):
            reach = car_radius + box_radius + margin + step_time * math.hypot(car_velocity[i, 0], car_velocity[i, 1])
            if math.hypot(car_xy[i, 0] - box_xy[k, 0], car_xy[i, 1] - box_xy[k, 1]) <= reach:
                return True
    return False
