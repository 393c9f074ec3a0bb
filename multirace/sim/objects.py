"""The objects on the track as the reward params list them, and which of them each car sees, compiled.

The reward params list every object on the track (boxes and the other cars)
for every car: `object_table` builds the list's columns and, for every
learning car, DeepRacer's `object_in_camera` and `closest_objects`
(`objects_seen`) in one numba call.
"""
from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def object_table(boxes, points, located, speeds, car_poses, learners, track_length, tan_half_fov, camera_range,
                 columns, left, seen):
    """The object list of the reward params: the boxes, then the cars `located` (N,) this step, in order, written
    into `columns`, `left` and `seen` (arrays the caller keeps: none is made per call); returns its length M.

    boxes (B, 5) and points (N, 5) are rows of (x, y, arc length on the centre line, lateral offset left of it,
    yaw): each box's, and each car's reported point where it was last located; speeds (N,) the cars' drive
    speeds (a box's is 0), car_poses (N, 3) their (x, y, yaw). Fills the list's columns (6, B + N; the first M
    columns): x, y, speed, heading in degrees, distance from the centre line, arc length; whether each is left
    of the centre line (B + N,; the first M); and per learning car (the first `learners`) `objects_seen`'s three
    values and its own place in the list (-1: not in it), (learners, 4).
    """
    num_boxes = boxes.shape[0]
    seen[:, 3] = -1
    seen[:, :3] = objects_seen(boxes, points, located, car_poses[:learners], track_length, tan_half_fov,
                               camera_range)
    k = 0
    for j in range(num_boxes + points.shape[0]):
        if j < num_boxes:
            row, speed = boxes[j], 0.0
        else:
            car = j - num_boxes
            if not located[car]:
                continue
            row, speed = points[car], speeds[car]
            if car < learners:
                seen[car, 3] = k
        columns[0, k], columns[1, k], columns[2, k] = row[0], row[1], speed
        columns[3, k], columns[4, k], columns[5, k] = math.degrees(row[4]), abs(row[3]), row[2]
        left[k] = row[3] > 0
        k += 1
    return k


@numba.njit(cache=True)
def objects_seen(boxes, points, located, car_poses, track_length, tan_half_fov, camera_range):
    """For each of the first n cars (n = len(car_poses)): whether any other object is in its camera view, and the
    closest ones.

    The objects are the boxes, boxes (B, 3+) of (x, y, arc length on the centre line, ...), then the cars `located`
    (N,) this step, at their points (N, 3+) of the same (the reported point where each was last located: a
    parked car's last place); car_poses (n, 3) of (x, y, yaw). Returns (n, 3): per car i, 1 if an object is
    in camera view (else 0), then the indices of the nearest object behind and ahead along the track, counted
    in the object list without car i itself (as DeepRacer's params give them).
    """
    n, num_boxes = car_poses.shape[0], boxes.shape[0]
    seen = np.zeros((n, 3), np.int64)
    for i in range(n):
        x_i, y_i, s_i = car_poses[i, 0], car_poses[i, 1], points[i, 2]
        cos_i, sin_i = math.cos(car_poses[i, 2]), math.sin(car_poses[i, 2])
        best_ahead = best_behind = math.inf
        k = 0  # position in the list without car i
        for j in range(num_boxes + points.shape[0]):
            if j < num_boxes:
                x, y, s = boxes[j, 0], boxes[j, 1], boxes[j, 2]
            else:
                car = j - num_boxes
                if car == i or not located[car]:
                    continue
                x, y, s = points[car, 0], points[car, 1], points[car, 2]
            dx, dy = x - x_i, y - y_i
            forward, sideways = dx * cos_i + dy * sin_i, dy * cos_i - dx * sin_i
            if 0 < forward < camera_range and abs(sideways) < forward * tan_half_fov:
                seen[i, 0] = 1
            ahead = (s - s_i) % track_length
            if ahead < best_ahead:
                best_ahead, seen[i, 2] = ahead, k
            if track_length - ahead < best_behind:
                best_behind, seen[i, 1] = track_length - ahead, k
            k += 1
    return seen
