"""The fast camera renderer: a perspective warp of the flat track plus projected boxes.

The ground is flat, so the camera's view of it is a homography of the track's
top-down texture: one `cv2.warpPerspective` per frame. Above the horizon the
sky is filled in. Other cars and the obstacles are boxes: their front-facing
faces are clipped against the near plane, projected and filled far to near, so
nearer boxes hide farther ones. The camera's own car is never drawn.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .camera import NEAR_PLANE, CameraPose, CameraSpec, Renderer
from .texture import TrackTexture
from .world import CAR_COLOURS, OBSTACLE_COLOUR, OBSTACLE_SIZE

SUBPIXEL_BITS = 4
# Corners of the unit box (+-0.5, +-0.5, 0..1) and its six faces (outward order)
_UNIT_CORNERS = np.array([[sx * 0.5, sy * 0.5, sz] for sz in (0.0, 1.0) for sy in (-1, 1) for sx in (-1, 1)])
_FACES = (
    (0, 1, 3, 2),  # bottom
    (4, 6, 7, 5),  # top
    (0, 4, 5, 1),  # y = -0.5
    (2, 3, 7, 6),  # y = +0.5
    (0, 2, 6, 4),  # x = -0.5
    (1, 5, 7, 3),  # x = +0.5
)


def _gray(rgb) -> int:
    r, g, b = rgb
    return int(round(0.299 * r + 0.587 * g + 0.114 * b))


def box_corners(poses: np.ndarray, size) -> np.ndarray:
    """World corners (M, 8, 3) of boxes of `size` (length, width, height) at (x, y, yaw) poses."""
    length, width, height = size
    local = _UNIT_CORNERS * np.array([length, width, height])
    cos, sin = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x = poses[:, None, 0] + cos[:, None] * local[None, :, 0] - sin[:, None] * local[None, :, 1]
    y = poses[:, None, 1] + sin[:, None] * local[None, :, 0] + cos[:, None] * local[None, :, 1]
    z = np.broadcast_to(local[None, :, 2], x.shape)
    return np.stack([x, y, z], axis=-1)


def clip_near(polygon: np.ndarray, near: float) -> np.ndarray:
    """Clip a camera-frame polygon (K, 3) to z >= near (Sutherland-Hodgman, one plane)."""
    out = []
    count = len(polygon)
    for k in range(count):
        a, b = polygon[k], polygon[(k + 1) % count]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out)


class FastRenderer(Renderer):
    """Camera images from one texture warp per frame and a few filled polygons."""

    def __init__(self, spec: CameraSpec, texture: TrackTexture):
        super().__init__(spec)
        self.texture = texture
        self.K = spec.intrinsics()
        self._tex_from_world = np.linalg.inv(texture.pixel_from_world_matrix())
        palette = texture.palette
        if spec.grayscale:
            self._ground = texture.gray
            self._floor = _gray(palette.floor)
            self._sky = _gray(palette.sky)
            self._car_colours = [_gray(c) for c in CAR_COLOURS]
            self._obstacle_colour = _gray(OBSTACLE_COLOUR)
        else:
            self._ground = texture.rgb
            self._floor = tuple(int(c) for c in palette.floor)
            self._sky = tuple(int(c) for c in palette.sky)
            self._car_colours = [tuple(int(v) for v in c) for c in CAR_COLOURS]
            self._obstacle_colour = tuple(int(c) for c in OBSTACLE_COLOUR)
        self._scene_key = None
        self._scene = None

    # ------------------------------------------------------------- ground
    def ground_homography(self, pose: CameraPose) -> np.ndarray:
        """3x3 map from image pixels to texture pixels (the warp's inverse map)."""
        R = pose.rotation
        image_from_world = self.K @ np.column_stack([R[:, 0], R[:, 1], -R @ pose.eye])
        image_from_tex = image_from_world @ self._tex_from_world
        return np.linalg.inv(image_from_tex)

    def horizon_row(self, pose: CameraPose) -> int:
        """First image row below the horizon (rows above it show sky)."""
        forward = pose.rotation[2]
        pitch_down = math.asin(max(-1.0, min(1.0, -forward[2])))
        row = self.K[1, 2] - self.K[1, 1] * math.tan(pitch_down)
        return int(min(max(math.ceil(row), 0), self.spec.height))

    # ------------------------------------------------------------- render
    def render(self, world, car: int, pose: CameraPose) -> np.ndarray:
        spec = self.spec
        image = cv2.warpPerspective(
            self._ground, self.ground_homography(pose), (spec.width, spec.height),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
            borderValue=self._floor)
        if image.ndim == 2:
            image = image[:, :, None]
        image[: self.horizon_row(pose)] = self._sky
        self._draw_boxes(image, world, car, pose)
        return image

    def _scene_boxes(self, world):
        """Corners and colours of every box in the scene (computed once per world step)."""
        key = (id(world), world.poses.tobytes(), world.obstacle_poses.tobytes(), world.parked.tobytes())
        if key != self._scene_key:
            cars = box_corners(world.poses, (world.spec.length, world.spec.width, world.spec.height))
            obstacles = box_corners(world.obstacle_poses, OBSTACLE_SIZE)
            corners = np.concatenate([cars, obstacles]) if len(obstacles) else cars
            owners = list(range(world.num_cars)) + [-1] * len(obstacles)
            colours = [self._car_colours[i % len(self._car_colours)] for i in range(world.num_cars)]
            colours += [self._obstacle_colour] * len(obstacles)
            hidden = list(world.parked) + [False] * len(obstacles)
            self._scene = (corners, owners, colours, hidden)
            self._scene_key = key
        return self._scene

    def _draw_boxes(self, image, world, car, pose) -> None:
        corners, owners, colours, hidden = self._scene_boxes(world)
        if not len(corners):
            return
        R = pose.rotation
        cam = (corners - pose.eye) @ R.T  # (M, 8, 3) camera-frame corners
        z = cam[:, :, 2]
        f, cx, cy = self.K[0, 0], self.K[0, 2], self.K[1, 2]
        half_w = self.spec.width / 2 + 1
        # cull boxes wholly behind the near plane or wholly left/right of the view
        visible = (z.max(axis=1) > NEAR_PLANE)
        zc = np.maximum(z, NEAR_PLANE)
        u = cam[:, :, 0] / zc * f
        visible &= ~((u.max(axis=1) < -half_w) & (cam[:, :, 0].max(axis=1) < 0))
        visible &= ~((u.min(axis=1) > half_w) & (cam[:, :, 0].min(axis=1) > 0))
        order = np.argsort(-np.linalg.norm(corners.mean(axis=1) - pose.eye, axis=1))
        scale = float(1 << SUBPIXEL_BITS)
        eye = pose.eye
        for m in order:
            if not visible[m] or owners[m] == car or hidden[m]:
                continue
            box = corners[m]
            centre = box.mean(axis=0)
            for face in _FACES:
                face_world = box[list(face)]
                normal = np.cross(face_world[1] - face_world[0], face_world[3] - face_world[0])
                if np.dot(normal, face_world[0] - centre) < 0:
                    normal = -normal
                if np.dot(normal, face_world[0] - eye) >= 0:
                    continue  # faces away from the camera
                poly = clip_near(cam[m, list(face)], NEAR_PLANE)
                if len(poly) < 3:
                    continue
                px = np.empty((len(poly), 2))
                px[:, 0] = cx + f * poly[:, 0] / poly[:, 2]
                px[:, 1] = cy + f * poly[:, 1] / poly[:, 2]
                px = np.clip(px, -4096, 4096)
                cv2.fillConvexPoly(image, np.round(px * scale).astype(np.int32), colours[m],
                                   lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
