"""Compiled drawing of the scene's boxes (cars and obstacles) into camera images.

One numba-compiled call draws every box every camera sees: bounding-sphere
culling, far-to-near order per camera, the box's eight corners in the camera
frame, clipping at the near plane, projection, the convex hull of the
projected outline and a scanline fill of it in the box's flat colour. Doing
this per (camera, box) pair in Python and numpy cost about a quarter of an
env step; compiled, it costs a few microseconds. The first call compiles (a
few seconds), and the machine code is cached beside this file for later runs.

Conventions match the fast renderer: camera frame x right, y down, z forward;
pixel (u, v) has its centre at coordinates (u, v).
"""
from __future__ import annotations

import math

import numba
import numpy as np

PIXEL_LIMIT = 4096.0  # projected points are clamped to +-4096 pixels
# corner k of a box lies on the side given by the bits of k (along = bit 0, across = bit 1,
# up = bit 2) of its centre; the 12 edges join corners one bit apart
_SIGNS = np.array([[1.0 if k & bit else -1.0 for bit in (1, 2, 4)] for k in range(8)])
_EDGES = np.array([(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit], dtype=np.int64)


@numba.njit(cache=True)
def draw_boxes(images, eyes, rotations, camera_cars, car_poses, parked, car_size, car_colours,
               obstacle_poses, obstacle_size, obstacle_colour, focal, cx, cy, near):
    """Fill the cars and obstacles every camera sees, far to near, in place.

    images (n, H, W, C) uint8; eyes (n, 3) and rotations (n, 3, 3) (rows: right,
    down, forward) of the cameras; camera_cars (n,) the car each camera rides
    on (its own box is not drawn); car_poses (N, 3) and obstacle_poses (M, 3)
    of (x, y, yaw), boxes standing on the ground; parked (N,) cars out of the
    scene; sizes (length, width, height); car_colours (K, C) (car i has colour
    i % K) and obstacle_colour (C,) uint8.
    """
    width = images.shape[2]
    limit = (width / 2 + 1) / focal
    spread = math.sqrt(1 + limit * limit)
    num_cars = car_poses.shape[0]
    num_boxes = num_cars + obstacle_poses.shape[0]
    car_radius = 0.5 * math.sqrt(car_size[0] ** 2 + car_size[1] ** 2 + car_size[2] ** 2)
    obstacle_radius = 0.5 * math.sqrt(obstacle_size[0] ** 2 + obstacle_size[1] ** 2 + obstacle_size[2] ** 2)
    visible = np.empty(num_boxes, np.int64)
    depths = np.empty(num_boxes)
    corners = np.empty((8, 3))
    outline = np.empty((20, 2))
    hull = np.empty((21, 2))
    spans = np.empty((2, images.shape[1]))  # each image row's (left, right) ends of the polygon being filled
    for c in range(images.shape[0]):
        rotation, eye = rotations[c], eyes[c]
        count = 0
        for b in range(num_boxes):
            is_car = b < num_cars
            if is_car and (parked[b] or b == camera_cars[c]):
                continue
            pose = car_poses[b] if is_car else obstacle_poses[b - num_cars]
            radius, half_height = (car_radius, car_size[2] / 2) if is_car else (obstacle_radius, obstacle_size[2] / 2)
            dx, dy, dz = pose[0] - eye[0], pose[1] - eye[1], half_height - eye[2]
            depth = rotation[2, 0] * dx + rotation[2, 1] * dy + rotation[2, 2] * dz
            across = rotation[0, 0] * dx + rotation[0, 1] * dy + rotation[0, 2] * dz
            # bounding-sphere culling: in front of the near plane and inside the horizontal view
            if depth + radius > near and abs(across) - radius * spread < max(depth, 0.0) * limit:
                k = count  # insert it far to near (the sort stable, as numpy's for so few)
                while k > 0 and depths[k - 1] < depth:
                    visible[k], depths[k] = visible[k - 1], depths[k - 1]
                    k -= 1
                visible[k], depths[k] = b, depth
                count += 1
        for k in range(count):
            b = visible[k]
            is_car = b < num_cars
            pose = car_poses[b] if is_car else obstacle_poses[b - num_cars]
            _box_corners(pose, car_size if is_car else obstacle_size, rotation, eye, corners)
            points = _clipped_outline(corners, near, focal, cx, cy, outline)
            if points >= 3:
                colour = car_colours[b % car_colours.shape[0]] if is_car else obstacle_colour
                _fill_convex(images[c], hull, _convex_hull(outline, points, hull), colour, spans)


@numba.njit(cache=True)
def _box_corners(pose, size, rotation, eye, corners):
    """The 8 corners of a box standing at pose (x, y, yaw), in the camera frame."""
    cos_yaw, sin_yaw = math.cos(pose[2]), math.sin(pose[2])
    for k in range(8):
        along, side, up = _SIGNS[k, 0] * size[0] / 2, _SIGNS[k, 1] * size[1] / 2, (_SIGNS[k, 2] + 1) * size[2] / 2
        world = (pose[0] + along * cos_yaw - side * sin_yaw - eye[0],
                 pose[1] + along * sin_yaw + side * cos_yaw - eye[1],
                 up - eye[2])
        for i in range(3):
            corners[k, i] = rotation[i, 0] * world[0] + rotation[i, 1] * world[1] + rotation[i, 2] * world[2]


@numba.njit(cache=True)
def _project(x, y, z, focal, cx, cy, outline, m):
    outline[m, 0] = min(max(cx + focal * x / z, -PIXEL_LIMIT), PIXEL_LIMIT)
    outline[m, 1] = min(max(cy + focal * y / z, -PIXEL_LIMIT), PIXEL_LIMIT)


@numba.njit(cache=True)
def _clipped_outline(corners, near, focal, cx, cy, outline):
    """Project the corners in front of the near plane and the points where edges cross it; returns their count."""
    m = 0
    for k in range(8):
        if corners[k, 2] >= near:
            _project(corners[k, 0], corners[k, 1], corners[k, 2], focal, cx, cy, outline, m)
            m += 1
    for e in range(_EDGES.shape[0]):
        i, j = _EDGES[e, 0], _EDGES[e, 1]
        if (corners[i, 2] >= near) != (corners[j, 2] >= near):
            t = (near - corners[i, 2]) / (corners[j, 2] - corners[i, 2])
            _project(corners[i, 0] + t * (corners[j, 0] - corners[i, 0]),
                     corners[i, 1] + t * (corners[j, 1] - corners[i, 1]), near, focal, cx, cy, outline, m)
            m += 1
    return m


@numba.njit(cache=True)
def _cross(o, a, b):
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


@numba.njit(cache=True)
def _convex_hull(points, count, hull):
    """Andrew's monotone chain over points[:count]; writes the hull's vertices in order, returns their count."""
    for i in range(1, count):  # insertion sort by (x, y): count is at most 20
        x, y = points[i, 0], points[i, 1]
        j = i - 1
        while j >= 0 and (points[j, 0] > x or (points[j, 0] == x and points[j, 1] > y)):
            points[j + 1, 0], points[j + 1, 1] = points[j, 0], points[j, 1]
            j -= 1
        points[j + 1, 0], points[j + 1, 1] = x, y
    size = 0
    for i in range(count):  # lower chain
        while size >= 2 and _cross(hull[size - 2], hull[size - 1], points[i]) <= 0:
            size -= 1
        hull[size, 0], hull[size, 1] = points[i, 0], points[i, 1]
        size += 1
    lower = size + 1
    for i in range(count - 2, -1, -1):  # upper chain
        while size >= lower and _cross(hull[size - 2], hull[size - 1], points[i]) <= 0:
            size -= 1
        hull[size, 0], hull[size, 1] = points[i, 0], points[i, 1]
        size += 1
    return size - 1  # the last point repeats the first


@numba.njit(cache=True)
def _fill_convex(image, polygon, count, colour, spans):
    """Fill the pixels whose centres lie inside a convex polygon (vertices polygon[:count]).

    Each row's span runs from the least to the greatest x at which the polygon's edges cross it, found edge by
    edge over the rows each edge spans (its ends included) rather than row by row over every edge: the same
    crossings, from the same expression. spans (2, H) is scratch."""
    if count < 3:
        return
    height, width, gray = image.shape[0], image.shape[1], image.shape[2] == 1
    top, bottom = polygon[0, 1], polygon[0, 1]
    for i in range(1, count):
        top, bottom = min(top, polygon[i, 1]), max(bottom, polygon[i, 1])
    first_row, last_row = max(int(math.ceil(top)), 0), min(int(math.floor(bottom)), height - 1)
    if first_row > last_row:
        return
    spans[0, first_row:last_row + 1] = math.inf
    spans[1, first_row:last_row + 1] = -math.inf
    for i in range(count):
        j = i + 1 if i + 1 < count else 0  # not (i + 1) % count: an integer division per edge
        x0, y0 = polygon[i, 0], polygon[i, 1]
        x1, y1 = polygon[j, 0], polygon[j, 1]
        low, high = max(int(math.ceil(min(y0, y1))), first_row), min(int(math.floor(max(y0, y1))), last_row)
        if y0 != y1:
            run, rise = x1 - x0, y1 - y0
            for row in range(low, high + 1):
                x = x0 + (row - y0) * run / rise
                spans[0, row], spans[1, row] = min(spans[0, row], x), max(spans[1, row], x)
        elif low <= high:  # a level edge lying on a row
            spans[0, low], spans[1, low] = min(spans[0, low], x0, x1), max(spans[1, low], x0, x1)
    for row in range(first_row, last_row + 1):
        left, right = spans[0, row], spans[1, row]
        if left > right or right < 0 or left > width - 1:
            continue
        first, last = max(int(math.ceil(left)), 0), min(int(math.floor(right)), width - 1)
        if gray:
            image[row, first:last + 1, 0] = colour[0]  # contiguous: compiles to a memset
        else:
            image[row, first:last + 1, :] = colour
