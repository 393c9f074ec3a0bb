"""Which objects each car sees: DeepRacer's `object_in_camera` and `closest_objects`, compiled.

The reward params list every object on the track (boxes and the other cars)
for every car; the per-car scan for the one in camera view and the nearest
ones behind and ahead is done for all cars in one numba call.
"""
from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def objects_seen(objects, car_poses, car_s, track_length, tan_half_fov, camera_range):
    """For each car i: whether any other object is in its camera view, and the closest ones.

    objects (4, M) are the objects' rows: the car each is (-1 for a box), x, y and arc length on the centre
    line; car_poses (n, 3) of (x, y, yaw) and car_s (n,) of the cars. Returns (n, 3): per car, 1 if an
    object is in camera view (else 0), then the indices of the nearest object behind and ahead along the
    track, counted in the object list without car i itself (as DeepRacer's params give them).
    """
    owners, xs, ys, along = objects[0], objects[1], objects[2], objects[3]
    n = car_poses.shape[0]
    seen = np.zeros((n, 3), np.int64)
    for i in range(n):
        cos_i, sin_i = math.cos(car_poses[i, 2]), math.sin(car_poses[i, 2])
        best_ahead = best_behind = math.inf
        k = 0  # position in the list without car i
        for j in range(owners.shape[0]):
            if owners[j] == i:
                continue
            dx, dy = xs[j] - car_poses[i, 0], ys[j] - car_poses[i, 1]
            forward, sideways = dx * cos_i + dy * sin_i, dy * cos_i - dx * sin_i
            if 0 < forward < camera_range and abs(sideways) < forward * tan_half_fov:
                seen[i, 0] = 1
            ahead = (along[j] - car_s[i]) % track_length
            if ahead < best_ahead:
                best_ahead, seen[i, 2] = ahead, k
            if track_length - ahead < best_behind:
                best_behind, seen[i, 1] = track_length - ahead, k
            k += 1
    return seen
