"""Top-down track texture: asphalt road, white borders, dashed centre line.

Both camera renderers draw the ground from this one image, so they agree by
construction; the top-down race view reuses it too. Pixel (row, col) of the
texture maps to world (x, y) by `TrackTexture.world_to_pixel`, with north up.
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .tracks import Track

PIXELS_PER_METRE = 100.0
MARGIN = 3.0  # metres of floor drawn around the track
BORDER_WIDTH = 0.05  # DeepRacer's white border tape, metres
CENTRE_DASH = 0.30  # dash and gap length of the centre line, metres


@dataclasses.dataclass(frozen=True)
class Palette:
    """Colours (RGB) of the scene; domain randomisation swaps these."""

    floor: tuple[int, int, int] = (110, 160, 90)
    road: tuple[int, int, int] = (68, 68, 72)
    border: tuple[int, int, int] = (240, 240, 240)
    centre: tuple[int, int, int] = (235, 190, 40)
    sky: tuple[int, int, int] = (255, 255, 255)  # PyBullet TinyRenderer's clear colour


DEFAULT_PALETTE = Palette()


class TrackTexture:
    """The rasterised top view of a track, in RGB and grayscale."""

    def __init__(self, track: Track, palette: Palette = DEFAULT_PALETTE, ppm: float = PIXELS_PER_METRE):
        self.track = track
        self.palette = palette
        self.ppm = ppm
        lo, hi = track.bounds
        self.origin = (float(lo[0] - MARGIN), float(hi[1] + MARGIN))  # world (x, y) of pixel (0, 0)
        self.width = int(np.ceil((hi[0] - lo[0] + 2 * MARGIN) * ppm))
        self.height = int(np.ceil((hi[1] - lo[1] + 2 * MARGIN) * ppm))
        self.rgb = self._draw()
        self.gray = cv2.cvtColor(self.rgb, cv2.COLOR_RGB2GRAY)
        # metres per pixel: world extent of the image
        self.world_size = (self.width / ppm, self.height / ppm)

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """World (x, y) metres -> texture (col, row) pixels, as float."""
        xy = np.asarray(xy, dtype=np.float64)
        col = (xy[..., 0] - self.origin[0]) * self.ppm
        row = (self.origin[1] - xy[..., 1]) * self.ppm
        return np.stack([col, row], axis=-1)

    def _draw(self) -> np.ndarray:
        p = self.palette
        img = np.empty((self.height, self.width, 3), np.uint8)
        img[:] = p.floor
        shift = 4  # sub-pixel precision for cv2 drawing
        scale = float(1 << shift)

        def pts(xy):
            return np.round(self.world_to_pixel(xy) * scale).astype(np.int32)

        inner, outer = pts(self.track.inner), pts(self.track.outer)
        quads = [np.array([inner[i], inner[i + 1], outer[i + 1], outer[i]]) for i in range(len(inner) - 1)]
        cv2.fillPoly(img, quads, p.road, lineType=cv2.LINE_AA, shift=shift)
        border_px = max(1, int(round(BORDER_WIDTH * self.ppm)))
        for line in (inner, outer):
            cv2.polylines(img, [line], True, p.border, border_px, cv2.LINE_AA, shift=shift)
        self._draw_dashes(img, pts, max(1, border_px // 2 + 1))
        return img

    def _draw_dashes(self, img, pts, thickness) -> None:
        track = self.track
        n_dashes = int(track.length // (2 * CENTRE_DASH))
        for k in range(n_dashes):
            s0 = k * 2 * CENTRE_DASH
            samples = np.linspace(s0, s0 + CENTRE_DASH, 6)
            xy = np.array([track.point_at(s)[:2] for s in samples])
            cv2.polylines(img, [pts(xy)], False, self.palette.centre, thickness, cv2.LINE_AA, shift=4)
