"""The optional LIDAR: DeepRacer's 64-beam scanner, cast against the scene's boxes (`beams`).

DeepRacer's ``LIDAR`` sensor (``sensor: ["FRONT_FACING_CAMERA", "LIDAR"]`` in
model_metadata) gives 64 ranges over 300 degrees (-150 to +150 degrees, 0 straight
ahead, counter-clockwise: the first beam looks back over the right shoulder),
with 0.01 m of Gaussian noise, clipped to 0.15 .. 1.0 m (no echo reads 1.0).
Its beams see what the camera cannot: a car alongside, or one so close ahead
that it is below the camera's view.

The scanner sits at the body centre at mid-body height, so its horizontal
beams meet other cars' bodies and obstacle boxes (never the flat track).
Each beam starts at the edge of the car's own body, which it must not see.
The beams are cast in the plane against the bodies' rectangles in one
compiled call (`beams.beam_fractions`); they read what PyBullet's
`rayTestBatch` reads (`World.cast_rays`, the reference), to rounding, but
where a beam starts inside another body (see `beams`).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..sim.car import CarSpec

SENSOR_NAME = "LIDAR"
SECTORS = 8  # DeepRacer's SECTOR_LIDAR: the 64 beams in 8 sectors of 8 ...
SECTOR_DISTANCE = 0.5  # m: ... each 1.0 where its nearest echo is nearer than this, else 0.0


@dataclasses.dataclass(frozen=True)
class LidarSpec:
    """DeepRacer's LIDAR constants (markov/sensors/constants.py and its clipping filter)."""

    samples: int = 64
    min_angle: float = -2.61799  # rad, first beam
    max_angle: float = 2.61799  # rad, last beam
    min_range: float = 0.15  # m; nearer echoes read this
    max_range: float = 1.0  # m; farther echoes (and none) read this
    noise_stddev: float = 0.01  # m

    def angles(self) -> np.ndarray:
        """Beam angles in the car frame, radians, 0 straight ahead, positive to the left."""
        return np.linspace(self.min_angle, self.max_angle, self.samples)


def body_edge_distance(spec: CarSpec, angles: np.ndarray) -> np.ndarray:
    """Distance from the body centre to the edge of its footprint along each beam angle."""
    cos, sin = np.abs(np.cos(angles)), np.abs(np.sin(angles))
    with np.errstate(divide="ignore"):
        along = np.where(cos > 1e-9, (spec.length / 2) / cos, np.inf)
        across = np.where(sin > 1e-9, (spec.width / 2) / sin, np.inf)
    return np.minimum(along, across)


class Lidar:
    """Scans for several cars at once: `scan(world, cars, rng) -> (len(cars), samples)` float32 metres."""

    def __init__(self, car_spec: CarSpec, spec: LidarSpec = LidarSpec()):
        self.spec = spec
        self.angles = spec.angles()
        self.height = car_spec.height / 2
        self.start = body_edge_distance(car_spec, self.angles) + 1e-3  # just outside the own body

    def scan(self, world, cars, rng: np.random.Generator | None = None) -> np.ndarray:
        """Ranges seen by `cars` (indices into `world.poses`); `rng` adds DeepRacer's noise."""
        spec = self.spec
        poses = world.poses[np.asarray(cars)]
        headings = poses[:, 2:3] + self.angles  # (N, samples), world frame
        directions = np.stack([np.cos(headings), np.sin(headings)], axis=-1)
        centres = poses[:, None, :2]
        starts = centres + directions * self.start[None, :, None]
        ends = centres + directions * spec.max_range
        from .beams import beam_fractions, scene_boxes  # here: a race without a LIDAR never loads (or compiles) them

        fractions = beam_fractions(starts.reshape(-1, 2), ends.reshape(-1, 2), scene_boxes(world))
        fractions = fractions.reshape(len(poses), spec.samples)
        ranges = self.start + fractions * (spec.max_range - self.start)
        if rng is not None and spec.noise_stddev:
            ranges = ranges + rng.normal(0.0, spec.noise_stddev, ranges.shape)
        return np.clip(ranges, spec.min_range, spec.max_range).astype(np.float32)

    def echoes(self, pose, ranges) -> np.ndarray:
        """World points (k, 3) of the beams of one scan that met something (below max range), from pose (x, y, yaw)."""
        ranges = np.asarray(ranges, np.float64)
        hit = ranges < self.spec.max_range - 2 * self.spec.noise_stddev
        x, y, yaw = pose
        headings = yaw + self.angles[hit]
        return np.column_stack([x + ranges[hit] * np.cos(headings), y + ranges[hit] * np.sin(headings),
                                np.full(int(hit.sum()), self.height)])


def sector_lidar(ranges: np.ndarray) -> np.ndarray:
    """DeepRacer's SECTOR_LIDAR from LIDAR scans (..., 64): (..., 8) float32 of 1.0 (something nearer than
    `SECTOR_DISTANCE` in that sector of consecutive beams) or 0.0."""
    ranges = np.asarray(ranges, np.float32)
    sectors = ranges.reshape(*ranges.shape[:-1], SECTORS, ranges.shape[-1] // SECTORS).min(axis=-1)
    return (sectors < SECTOR_DISTANCE).astype(np.float32)
