"""Horizontal beams against the scene's boxes, in the plane: the LIDAR's ray cast without PyBullet.

Every body of the world is an upright box (cars and obstacles, kept flat),
and the LIDAR's beams are level at mid-car height, which meets every body's
side. So a beam's first hit is the nearest entry of a segment into one of the
boxes' rectangles (the slab test), computed for all beams and boxes in one
compiled call. A beam that starts inside another body (two cars pressed into
each other) meets it at once if it heads inwards from the side nearest its
start, and does not see it if it heads out, as PyBullet's rays do.
"""
from __future__ import annotations

import math

import numba
import numpy as np


def scene_boxes(world) -> np.ndarray:
    """The world's bodies that beams can meet, rows of (x, y, yaw, half length, half width): the cars on
    track (parked ones wait far below the scene) and the boxes."""
    spec = world.spec
    cars = world.poses[~world.parked]
    boxes = np.empty((len(cars) + len(world.obstacle_poses), 5))
    boxes[:len(cars), :3] = cars
    boxes[:len(cars), 3:] = (spec.length / 2, spec.width / 2)
    if len(world.obstacle_poses):
        from ..sim.world import OBSTACLE_SIZE

        boxes[len(cars):, :3] = world.obstacle_poses
        boxes[len(cars):, 3:] = (OBSTACLE_SIZE[0] / 2, OBSTACLE_SIZE[1] / 2)
    return boxes


@numba.njit(cache=True)
def _heads_inwards(p, d, half):
    """Whether a direction d from a point p inside a rectangle (box frame) heads away from its nearest side."""
    axis = 0 if abs(p[0]) / half[0] >= abs(p[1]) / half[1] else 1
    return d[axis] * p[axis] < 0.0


@numba.njit(cache=True)
def beam_fractions(starts, ends, boxes):
    """Hit fraction (0 at the start .. 1 at the end, 1 for no hit) of each beam (rows of starts and ends, (M, 2))
    against rectangles (B, 5) of (x, y, yaw, half length, half width): the nearest entry over all of them."""
    m = starts.shape[0]
    fractions = np.ones(m)
    for b in range(boxes.shape[0]):
        cos_b, sin_b = math.cos(boxes[b, 2]), math.sin(boxes[b, 2])
        half = (boxes[b, 3], boxes[b, 4])
        for k in range(m):
            # the beam in the box's frame
            rx, ry = starts[k, 0] - boxes[b, 0], starts[k, 1] - boxes[b, 1]
            dx, dy = ends[k, 0] - starts[k, 0], ends[k, 1] - starts[k, 1]
            p = (rx * cos_b + ry * sin_b, -rx * sin_b + ry * cos_b)
            d = (dx * cos_b + dy * sin_b, -dx * sin_b + dy * cos_b)
            enter, leave = -math.inf, math.inf
            for a in range(2):
                if abs(d[a]) < 1e-12:
                    if abs(p[a]) > half[a]:
                        enter, leave = math.inf, -math.inf  # parallel to this side and outside: a miss
                else:
                    t1, t2 = (-half[a] - p[a]) / d[a], (half[a] - p[a]) / d[a]
                    enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
            if enter > leave or leave < 0.0 or enter >= fractions[k]:
                continue
            if enter >= 0.0:
                fractions[k] = enter
            elif _heads_inwards(p, d, half):  # a beam that starts inside a body (pressed into this car)
                fractions[k] = 0.0
    return fractions
