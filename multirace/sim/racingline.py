"""The racing line of a track and the fastest speed along it: every track's reference lap.

`plan_racing_line(track, spec)`:

1. the line: the centre line resampled every `SPACING` metres, each point free
   to move sideways within the road less `MARGIN` (the car's half width and a
   safety margin from the edge); the line of least curvature (the sum of
   squared second differences of its points) is a convex quadratic with
   box bounds, solved with SciPy's L-BFGS-B;
2. the speed profile: at each point the grip limit ``sqrt(mu g / curvature)``
   (front tyres, which saturate first), capped at DeepRacer's top command
   (4.0 m/s), then a forward pass with the drive train's acceleration and a
   backward pass with its braking, both within the friction circle that the
   cornering leaves, repeated around the closed loop until it settles.

The line is cached per track object and car spec.
"""
from __future__ import annotations

import dataclasses
import math
import weakref
from typing import TYPE_CHECKING

import numpy as np

from .car import GRAVITY, CarSpec

if TYPE_CHECKING:
    from .tracks import Track

SPACING = 0.1  # m between the line's points
MARGIN = 0.15  # m from the road edge to the car's centre line: the car's half width and 5 cm to spare
SMOOTHING = 0.3  # m, the Gaussian that takes the kinks out of the waypoints' polygon
GRIP_USE = 0.95  # share of the tyres' grip the speed profile plans to use
_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@dataclasses.dataclass(frozen=True)
class RacingLine:
    """A closed line around a track with its speed profile; index i sits at centre-line arc length i * spacing."""

    points: np.ndarray  # (n, 2) world x, y
    offsets: np.ndarray  # (n,) lateral offset from the centre line, + left
    curvature: np.ndarray  # (n,) 1/m, signed (+ turning left)
    speed: np.ndarray  # (n,) m/s, the fastest the car can drive there
    distance: np.ndarray  # (n,) m along the line from point i to point i + 1
    spacing: float

    @property
    def lap_time(self) -> float:
        """Seconds for one lap at the speed profile (from a flying start)."""
        mean_speed = 0.5 * (self.speed + np.roll(self.speed, -1))
        return float(np.sum(self.distance / mean_speed))

    def index_at(self, s: float) -> int:
        """The point at centre-line arc length `s`."""
        return int(round(s / self.spacing)) % len(self.points)


def plan_racing_line(track: Track, spec: CarSpec = CarSpec(), margin: float = MARGIN) -> RacingLine:
    """The least-curvature line of `track` and the fastest speed profile along it (cached)."""
    key = (spec, margin)
    per_track = _CACHE.setdefault(track, {})
    if key not in per_track:
        per_track[key] = _plan(track, spec, margin)
    return per_track[key]


def _plan(track: Track, spec: CarSpec, margin: float) -> RacingLine:
    n = max(8, int(round(track.length / SPACING)))
    spacing = track.length / n
    raw = np.array([track.point_at(s)[:2] for s in np.arange(n) * spacing])
    centre = _smooth_closed(raw, SMOOTHING / spacing)  # the waypoints' polygon without its kinks
    tangent = np.roll(centre, -1, axis=0) - np.roll(centre, 1, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1), 1e-12)[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    low, high = np.empty(n), np.empty(n)
    hint = None
    for i, (x, y) in enumerate(centre):
        proj = track.project(x, y, hint)  # the smoothed point sits `proj.lateral` off the track's centre line
        hint = proj.segment
        low[i], high[i] = -(proj.right_width - margin) - proj.lateral, proj.left_width - margin - proj.lateral
    squeeze = high < low  # a road narrower than the car plus margins: keep to its middle
    low[squeeze] = high[squeeze] = 0.5 * (low[squeeze] + high[squeeze])
    offsets = _least_curvature(centre, normal, low, high)
    points = centre + offsets[:, None] * normal
    curvature = _curvature(points)
    distance = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    speed = _speed_profile(curvature, distance, spec)
    return RacingLine(points=points, offsets=offsets, curvature=curvature, speed=speed, distance=distance,
                      spacing=spacing)


def _smooth_closed(points: np.ndarray, sigma: float) -> np.ndarray:
    """A closed polyline's points smoothed with a circular Gaussian of `sigma` points."""
    half = int(math.ceil(3 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / max(sigma, 1e-9)) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([points[-half:], points, points[:half]]) if half else points
    return np.column_stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)])


def _least_curvature(centre, normal, low, high) -> np.ndarray:
    """Offsets within [low, high] that minimise the squared second differences of the line's points:
    a convex quadratic with box bounds, solved with L-BFGS-B on its exact gradient."""
    from scipy.optimize import minimize
    from scipy.sparse import coo_matrix

    n = len(centre)
    rows, cols, values = [], [], []
    prev, nxt = np.roll(np.arange(n), 1), np.roll(np.arange(n), -1)
    for axis in range(2):
        r = np.arange(n) * 2 + axis
        for index, weight in ((prev, 1.0), (np.arange(n), -2.0), (nxt, 1.0)):
            rows.append(r)
            cols.append(index)
            values.append(weight * normal[index, axis])
    matrix = coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(2 * n, n)).tocsr()
    target = -(centre[prev] - 2 * centre + centre[nxt]).reshape(-1)
    hessian, linear = (matrix.T @ matrix).tocsr(), -(matrix.T @ target)

    def cost(x):
        hx = hessian @ x
        return 0.5 * x @ hx + linear @ x, hx + linear

    result = minimize(cost, np.clip(np.zeros(n), low, high), jac=True, method="L-BFGS-B",
                      bounds=list(zip(low, high)), options={"maxiter": 50000, "ftol": 1e-15, "gtol": 1e-12})
    return np.clip(result.x, low, high)


def _curvature(points: np.ndarray) -> np.ndarray:
    """Signed curvature at each point of a closed line (circle through it and its neighbours), lightly smoothed."""
    a, b, c = np.roll(points, 1, axis=0), points, np.roll(points, -1, axis=0)
    ab, bc, ca = b - a, c - b, a - c
    cross = ab[:, 0] * bc[:, 1] - ab[:, 1] * bc[:, 0]
    lengths = np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) * np.linalg.norm(ca, axis=1)
    kappa = 2.0 * cross / np.maximum(lengths, 1e-12)
    kernel = np.array([1.0, 2.0, 3.0, 2.0, 1.0]) / 9.0
    padded = np.concatenate([kappa[-2:], kappa, kappa[:2]])
    return np.convolve(padded, kernel, mode="valid")


def _speed_profile(curvature: np.ndarray, distance: np.ndarray, spec: CarSpec) -> np.ndarray:
    """The fastest speeds along a closed line: grip-limited in corners, drive-train-limited between."""
    grip = GRIP_USE * spec.mu * GRAVITY  # the front tyres saturate first (the rear grip more)
    top = spec.max_speed
    speed = np.minimum(top, np.sqrt(grip / np.maximum(np.abs(curvature), 1e-9)))
    n = len(speed)
    for _ in range(3):  # forward (accelerate) then backward (brake), around the loop until it settles
        for k in range(2 * n):
            i, j = k % n, (k + 1) % n
            lateral = speed[i] ** 2 * abs(curvature[i])
            spare = math.sqrt(max(grip ** 2 - lateral ** 2, 0.0))
            motor = spec.accel * max(0.0, 1.0 - speed[i] / spec.top_speed)
            reach = math.sqrt(speed[i] ** 2 + 2.0 * min(motor, spare) * distance[i])
            speed[j] = min(speed[j], reach)
        for k in range(2 * n, 0, -1):
            i, j = k % n, (k - 1) % n
            lateral = speed[i] ** 2 * abs(curvature[i])
            spare = math.sqrt(max(grip ** 2 - lateral ** 2, 0.0))
            reach = math.sqrt(speed[i] ** 2 + 2.0 * min(spec.brake, spare) * distance[j])
            speed[j] = min(speed[j], reach)
    return speed
