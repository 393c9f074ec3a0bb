"""The reference renderer: PyBullet's TinyRenderer over the physics scene.

The ground is a textured mesh (the track texture) over a large plain floor,
added to the world's PyBullet client on first use; cars and boxes are the
world's own bodies with their visual shapes. Slow (milliseconds per frame), but
independent of our own projection code, which is what the parity test needs.
"""
from __future__ import annotations

import math
import os
import tempfile

import cv2
import numpy as np

from .camera import FAR_PLANE, NEAR_PLANE, CameraPose, CameraSpec, Renderer
from ..sim.texture import TrackTexture
from ..sim.world import pybullet

FLOOR_EXTENT = 200.0  # metres of plain floor around the track texture


class PyBulletRenderer(Renderer):
    """Camera images from `pybullet.getCameraImage` with the TinyRenderer."""

    def __init__(self, spec: CameraSpec, texture: TrackTexture):
        super().__init__(spec)
        self.texture = texture
        self._ground_client: int | None = None
        self._projection = pybullet.computeProjectionMatrixFOV(
            math.degrees(spec.vfov), spec.width / spec.height, NEAR_PLANE, FAR_PLANE)

    def _add_ground(self, client: int) -> None:
        tex = self.texture
        x0, y1 = tex.origin
        x1, y0 = x0 + tex.world_size[0], y1 - tex.world_size[1]
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "track.png")
            cv2.imwrite(path, cv2.cvtColor(tex.rgb, cv2.COLOR_RGB2BGR))
            texture_id = pybullet.loadTexture(path, physicsClientId=client)
        vertices = [[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]]
        uvs = [[0, 0], [1, 0], [1, 1], [0, 1]]
        shape = pybullet.createVisualShape(pybullet.GEOM_MESH, vertices=vertices, indices=[0, 1, 2, 0, 2, 3],
                                           uvs=uvs, normals=[[0, 0, 1]] * 4, physicsClientId=client)
        body = pybullet.createMultiBody(0, -1, shape, [0, 0, 0], physicsClientId=client)
        pybullet.changeVisualShape(body, -1, textureUniqueId=texture_id, rgbaColor=[1, 1, 1, 1],
                                   physicsClientId=client)
        floor_colour = [c / 255 for c in tex.palette.floor] + [1]
        floor = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=[FLOOR_EXTENT, FLOOR_EXTENT, 0.001],
                                           rgbaColor=floor_colour, physicsClientId=client)
        pybullet.createMultiBody(0, -1, floor, [0, 0, -0.003], physicsClientId=client)
        self._ground_client = client

    def _camera_image(self, world, pose: CameraPose, segmentation: bool):
        client = world.connect()
        world.sync()  # the cars where they are, also after steps that moved them without PyBullet
        if self._ground_client != client:
            self._add_ground(client)
        spec = self.spec
        target = pose.eye + pose.forward
        view = pybullet.computeViewMatrix(pose.eye.tolist(), target.tolist(), (-pose.down).tolist())
        flags = 0 if segmentation else pybullet.ER_NO_SEGMENTATION_MASK
        _, _, rgba, _, seg = pybullet.getCameraImage(
            spec.width, spec.height, view, self._projection, renderer=pybullet.ER_TINY_RENDERER,
            lightAmbientCoeff=1.0, lightDiffuseCoeff=0.0, lightSpecularCoeff=0.0, shadow=0,
            flags=flags, physicsClientId=client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(spec.height, spec.width, 4)[:, :, :3]
        return rgb, seg

    def segmentation(self, world, pose: CameraPose) -> np.ndarray:
        """(H, W) int array of the PyBullet body id seen at each pixel (-1: background)."""
        _, seg = self._camera_image(world, pose, segmentation=True)
        return np.asarray(seg, dtype=np.int64).reshape(self.spec.height, self.spec.width)

    def render(self, world, car: int, pose: CameraPose) -> np.ndarray:
        rgb, _ = self._camera_image(world, pose, segmentation=False)
        if self.spec.grayscale:
            return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None]
        return np.ascontiguousarray(rgb)
