"""The fast camera renderer: a perspective view of the flat track plus projected boxes.

The ground is flat, so the camera's view of it is a homography of the track's
top-down texture. It is cast row by row in one compiled call for all cameras
(`cast_ground`): the camera does not roll, so each image row below the horizon
sees the ground at one depth, and its pixels walk a straight line of the
texture in equal steps (the "mode 7" walk), nearest-texel like PyBullet's
TinyRenderer (the texture has 1 cm texels). Above the horizon the sky is
filled in. The same map as a 3x3 homography (`ground_homography`, for
`cv2.warpPerspective`) is kept for tools; the cast and the warp pick the same
texel but where a pixel falls on a texel boundary to within rounding. Other cars and the obstacles are
flat-coloured boxes, as in the PyBullet reference: a box's silhouette is the
convex hull of its corners (clipped at the near plane), filled far to near so
nearer boxes hide farther ones (`box_raster.draw_boxes`). Ground and boxes of
all cameras are drawn in one compiled call (`render_scene`) into one
(n, H, W, C) array; `render_car_cameras` poses the cameras of some cars in
that call too. The camera's own car is never drawn.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from .box_raster import draw_boxes
from .camera import NEAR_PLANE, NO_JITTER, CameraPose, CameraSpec, Renderer, pose_cameras
from ..sim.texture import TrackTexture
from ..sim.world import CAR_COLOURS, OBSTACLE_COLOUR, OBSTACLE_SIZE

_UINT8 = np.dtype(np.uint8)  # a dtype object: np.empty takes it faster than np.uint8


def _gray(rgb) -> int:
    r, g, b = rgb
    return int(round(0.299 * r + 0.587 * g + 0.114 * b))


class FastRenderer(Renderer):
    """Camera images from a row-by-row cast of the track's texture and a few filled polygons."""

    def __init__(self, spec: CameraSpec, texture: TrackTexture):
        super().__init__(spec)
        self.texture = texture
        self.K = spec.intrinsics()
        self._metres_per_texel = 1.0 / texture.ppm
        self._focal, self._cx, self._cy = float(self.K[0, 0]), float(self.K[0, 2]), float(self.K[1, 2])
        palette = texture.palette
        if spec.grayscale:
            self._ground = texture.gray
            self._floor = _gray(palette.floor)
            self._sky = _gray(palette.sky)
            car_colours = np.array([[_gray(c)] for c in CAR_COLOURS], np.uint8)
            obstacle_colour = np.array([_gray(OBSTACLE_COLOUR)], np.uint8)
        else:
            self._ground = texture.rgb
            self._floor = tuple(int(c) for c in palette.floor)
            self._sky = tuple(int(c) for c in palette.sky)
            car_colours = np.array(CAR_COLOURS, np.uint8)
            obstacle_colour = np.array(OBSTACLE_COLOUR, np.uint8)
        # render_scene's inputs, its constants packed in few arrays (each argument costs time in every call):
        # the bordered texture, (ppm, x0, y0, focal, cx, cy, near plane, the camera's forward, mount height, pitch
        # and stereo baseline) and the colours, one value per channel
        sky, floor = np.array(np.atleast_1d(self._sky), np.uint8), np.array(np.atleast_1d(self._floor), np.uint8)
        self._texels = bordered_texels(self._ground.reshape(*self._ground.shape[:2], -1), floor)
        self._image_shape = (spec.height, spec.width, spec.channels)
        x0, y0 = texture.origin
        self._view = np.array((texture.ppm, x0, y0, self._focal, self._cx, self._cy, NEAR_PLANE, spec.forward,
                               spec.mount_height, spec.pitch, spec.stereo_baseline), float)
        self._colours = np.concatenate([sky[None], floor[None], obstacle_colour[None], car_colours])
        self._sizes: np.ndarray | None = None  # car and obstacle (length, width, height): the car's from the world

    # ------------------------------------------------------------- ground
    def ground_homography(self, pose: CameraPose, first_row: int = 0) -> np.ndarray:
        """3x3 map from texture pixels to image pixels (the ground plane z = 0).

        With `first_row`, pixel rows are counted from that image row (for warping
        only the part of the image below the horizon).
        """
        return self._ground_maps(pose.eye[None], pose.rotation[None], np.array([first_row]))[0][0]

    def horizon_row(self, pose: CameraPose) -> int:
        """First image row below the horizon (rows above it show sky)."""
        return int(self._ground_maps(pose.eye[None], pose.rotation[None])[1][0])

    def _ground_maps(self, eyes: np.ndarray, rotations: np.ndarray, first_rows: np.ndarray | None = None):
        """Homographies (n, 3, 3) from texture pixels to image pixels and horizon rows (n,) of n cameras.

        Each homography counts rows from `first_rows[k]`, by default from the camera's horizon.
        """
        x0, y0 = self.texture.origin
        return _ground_maps(eyes, rotations, first_rows, self._metres_per_texel, float(x0), float(y0),
                            self._focal, self._cx, self._cy, self.spec.height)

    # ------------------------------------------------------------- render
    def render(self, world, car: int, pose: CameraPose) -> np.ndarray:
        return self.render_many(world, [car], pose.eye[None], pose.rotation[None])[0]

    def render_many(self, world, cars, eyes: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """Images (n, H, W, C) of several cameras at once, ground and boxes in one compiled call."""
        images = np.empty((len(cars),) + self._image_shape, _UINT8)
        render_scene(images, eyes, rotations, np.asarray(cars, dtype=np.int64), world.poses, world.parked,
                     world.obstacle_poses, self._texels, self._view, self._box_sizes(world), self._colours)
        return images

    def render_cars(self, world, cars, jitter: np.ndarray | None = None, stereo: bool = False) -> np.ndarray:
        """Images (n, H, W, C) of the cameras on `cars` (2n: the stereo pairs' left, then right cameras), posed
        (`camera.pose_cameras`) and drawn in one compiled call."""
        cars = np.asarray(cars, dtype=np.int64)
        images = np.empty((2 * len(cars) if stereo else len(cars),) + self._image_shape, _UINT8)
        render_car_cameras(images, cars, NO_JITTER if jitter is None else jitter, world.poses, world.parked,
                           world.obstacle_poses, self._texels, self._view, self._box_sizes(world), self._colours)
        return images

    def _box_sizes(self, world) -> np.ndarray:
        """The car's (from the world) and the obstacles' (length, width, height), (2, 3)."""
        if self._sizes is None:
            car = world.spec
            self._sizes = np.array(((car.length, car.width, car.height), OBSTACLE_SIZE), float)
        return self._sizes


@numba.njit(cache=True)
def render_car_cameras(images, cars, jitter, car_poses, parked, obstacle_poses, texels, view, sizes, colours):
    """`render_scene` of the cameras on cars (n,) (`camera.pose_cameras`, jitter (n, 3) or (0, 3)): the stereo
    pairs if `images` holds 2n images. view goes on with the camera's (forward, mount height, pitch, stereo
    baseline)."""
    stereo = images.shape[0] > cars.shape[0]
    eyes, rotations, camera_cars = pose_cameras(car_poses, cars, jitter, view[7], view[8], view[9], view[10], stereo)
    render_scene(images, eyes, rotations, camera_cars, car_poses, parked, obstacle_poses, texels, view, sizes,
                 colours)


@numba.njit(cache=True)
def render_scene(images, eyes, rotations, cars, car_poses, parked, obstacle_poses, texels, view, sizes, colours):
    """`cast_ground`, then `draw_boxes`: one call from Python per batch of cameras. texels is `bordered_texels`;
    view begins (ppm, x0, y0, focal, cx, cy, near plane); sizes (2, 3) the car's and the obstacles' (length,
    width, height); colours (3 + K, C) the sky, the floor, the obstacles and the K car colours."""
    ppm, x0, y0, focal, cx, cy, near = view[0], view[1], view[2], view[3], view[4], view[5], view[6]
    rows, columns = texels.shape[0] - 2, texels.shape[1] - 2
    cast_ground(images, texels.reshape(texels.size), rows, columns, eyes, rotations, ppm, x0, y0, focal, cx, cy,
                colours[0], colours[1])
    draw_boxes(images, eyes, rotations, cars, car_poses, parked, sizes[0], colours[3:], obstacle_poses, sizes[1],
               colours[2], focal, cx, cy, near)


def bordered_texels(texels: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """The texture (rows, columns, C) with a one-texel border of the floor colour, (rows + 2, columns + 2, C):
    the cast clamps every texel index into this border, so ground beyond the texture is floor without a test
    per pixel."""
    rows, columns, channels = texels.shape
    bordered = np.empty((rows + 2, columns + 2, channels), np.uint8)
    bordered[:] = floor
    bordered[1:-1, 1:-1] = texels
    return bordered


@numba.njit(cache=True)
def cast_ground(images, flat_texels, rows, columns, eyes, rotations, ppm, x0, y0, focal, cx, cy, sky, floor):
    """Fill images (n, H, W, C) with the sky above each camera's horizon and the ground texture below it.

    flat_texels is `bordered_texels` of a (rows, columns, C) top-down texture, flattened; its texel (u, v) is
    centred at world (x0 + u / ppm, y0 - v / ppm); rotations (n, 3, 3) have rows right, down, forward. The ray
    of pixel (x, y) has the direction right (x - cx) / f + down (y - cy) / f + forward and meets the ground at
    eye - eye_z / dir_z dir. Without roll (right_z = 0) dir_z, hence the depth, is the same along a row and
    the texel walks a straight line in equal steps; a rolled camera takes a division per pixel. The sky is
    filled a slice per channel and the ground's pixels written element by element (a view per row costs more
    than it saves at this size), their texel indices unsigned (no test for a negative index per lookup).
    """
    n, height, width, channels = images.shape
    inv_f = 1.0 / focal
    index = np.empty(width, np.uint32)  # unsigned: a lookup without a test for negative indices
    steps = np.arange(width).astype(np.float32)
    for k in range(n):
        r = rotations[k]
        ez = eyes[k, 2]
        east, south = eyes[k, 0] - x0, y0 - eyes[k, 1]
        pitch_down = math.asin(max(-1.0, min(1.0, -r[2, 2])))
        horizon = min(max(math.ceil(cy - focal * math.tan(pitch_down)), 0), height)
        for c in range(channels):
            images[k, :horizon, :, c] = sky[c]
        ax, ay, az = r[0, 0] * inv_f, r[0, 1] * inv_f, r[0, 2] * inv_f  # the direction's change per pixel
        for y in range(horizon, height):
            down = (y - cy) * inv_f
            bx = r[2, 0] + r[1, 0] * down - ax * cx  # the direction at x = 0
            by = r[2, 1] + r[1, 1] * down - ay * cx
            bz = r[2, 2] + r[1, 2] * down - az * cx
            if az == 0.0:
                if _walk_row(index, steps, bz, ez, east, south, bx, by, ax, ay, ppm, rows, columns):
                    for c in range(channels):  # the whole row beyond the texture
                        images[k, y, :, c] = floor[c]
                    continue
            else:
                _divide_row(index, bz, az, ez, east, south, bx, by, ax, ay, ppm, rows, columns)
            if channels == 1:
                for x in range(width):
                    images[k, y, x, 0] = flat_texels[index[x]]
            else:
                for x in range(width):
                    for c in range(channels):
                        images[k, y, x, c] = flat_texels[index[x] * channels + c]


@numba.njit(cache=True, fastmath=True)
def _walk_row(index, steps, bz, ez, east, south, bx, by, ax, ay, ppm, rows, columns):
    """The texels of one image row of a camera without roll: a straight walk through the texture in equal
    steps. In single precision (vectorised; a texel is 1 cm, the walk's rounding far below it) and within
    the bordered texture: the walk's coordinates are clamped into the border before the conversion, unless
    both ends of the row lie inside it (the walk is monotonic, so then all of it does). Returns whether the
    whole row lies in the border (floor colour), leaving `index` as it was."""
    width = index.shape[0]
    if bz >= 0.0:  # the row looks at or above the horizon: no ground, floor colour
        return True
    scale = -ez / bz * ppm  # texels per unit of the ray's direction, on the ground
    # + 0.5, then truncation: the nearest texel; + 1: the border's offset
    u0, du = np.float32(east * ppm + scale * bx + 1.5), np.float32(scale * ax)
    v0, dv = np.float32(south * ppm - scale * by + 1.5), np.float32(-scale * ay)
    zero, last_u, last_v = np.float32(0.0), np.float32(columns + 1), np.float32(rows + 1)
    stride = np.int32(columns + 2)
    first, last = steps[0], steps[width - 1]
    u_first, u_last, v_first, v_last = u0 + du * first, u0 + du * last, v0 + dv * first, v0 + dv * last
    u_low, u_high = min(u_first, u_last), max(u_first, u_last)
    v_low, v_high = min(v_first, v_last), max(v_first, v_last)
    if u_high < 1 or u_low >= last_u or v_high < 1 or v_low >= last_v:  # every texel in the border
        return True
    if zero <= u_low and u_high <= last_u and zero <= v_low and v_high <= last_v:
        for x in range(width):
            step = steps[x]
            index[x] = np.int32(v0 + dv * step) * stride + np.int32(u0 + du * step)
        return False
    for x in range(width):
        step = steps[x]
        u = np.int32(min(max(u0 + du * step, zero), last_u))
        v = np.int32(min(max(v0 + dv * step, zero), last_v))
        index[x] = v * stride + u
    return False


@numba.njit(cache=True)
def _divide_row(index, bz, az, ez, east, south, bx, by, ax, ay, ppm, rows, columns):
    """The texels of one image row of a rolled camera: the depth changes along the row, a division per pixel."""
    for x in range(index.shape[0]):
        dz = bz + az * x
        if dz >= 0.0:
            index[x] = 0
            continue
        scale = -ez / dz * ppm
        u = min(max(east * ppm + scale * (bx + ax * x) + 0.5, -1.0), columns)  # clamped before the conversion
        v = min(max(south * ppm - scale * (by + ay * x) + 0.5, -1.0), rows)
        index[x] = (int(math.floor(v)) + 1) * (columns + 2) + int(math.floor(u)) + 1


@numba.njit  # not cached: races never call it (bench, explain), so its cache index would stay missing and the
# first-compile notice (environment/kernels.py) would show on every run
def _ground_maps(eyes, rotations, first_rows, metres_per_texel, x0, y0, focal, cx, cy, height):
    """K [r1 r2 t] A per camera, with r1, r2 the rotation's first two columns, t = -R eye and A
    the texture-to-world map (x = x0 + u * metres_per_texel, y = y0 - v * metres_per_texel)."""
    n = eyes.shape[0]
    homographies, horizons = np.empty((n, 3, 3)), np.empty(n, np.int64)
    ground = np.empty((3, 3))  # [r1 r2 t] A of one camera
    for k in range(n):
        r, eye = rotations[k], eyes[k]
        pitch_down = math.asin(max(-1.0, min(1.0, -r[2, 2])))
        horizons[k] = min(max(math.ceil(cy - focal * math.tan(pitch_down)), 0), height)
        first_row = horizons[k] if first_rows is None else first_rows[k]
        for i in range(3):
            t = -(r[i, 0] * eye[0] + r[i, 1] * eye[1] + r[i, 2] * eye[2])
            ground[i, 0], ground[i, 1] = r[i, 0] * metres_per_texel, -r[i, 1] * metres_per_texel
            ground[i, 2] = r[i, 0] * x0 + r[i, 1] * y0 + t
        for j in range(3):
            homographies[k, 0, j] = focal * ground[0, j] + cx * ground[2, j]
            homographies[k, 1, j] = focal * ground[1, j] + (cy - first_row) * ground[2, j]
            homographies[k, 2, j] = ground[2, j]
    return homographies, horizons
