"""Seeded procedural tracks: valid closed DeepRacer-style loops for training diversity.

`generate_track(seed)` draws a closed centre line as a smooth star-shaped
curve ``r(theta) = R * (1 + sum_k a_k cos(k theta + phi_k))`` (harmonics 2-4),
optionally squashed into an ellipse, resampled at about DeepRacer's waypoint
spacing (0.15-0.2 m); the borders are the centre line offset by half a
DeepRacer width (0.762 m, 0.914 m or 1.067 m, the widths of the real tracks),
and the track runs counter-clockwise with "inner" on the left, as the
bundled tracks do. Curves whose tightest bend is below `MIN_RADIUS` (so the
inner border would fold), or that the track validator rejects, are redrawn
from a derived seed, so every seed gives a valid `Track`. Same seed, same
track.

Use: ``multirace.parallel_env(track=generate_track(3))`` or
``multirace train --set procedural_tracks=8`` (generated tracks added to the
training tracks).
"""
from __future__ import annotations

import math

import numpy as np

from ..atomic import AtomicOutput
from .tracks import Track, TrackError

WIDTHS = (0.762, 0.914, 1.067)  # metres: DeepRacer track widths (reinvent_base; 36 in; 42 in)
MIN_RADIUS = 0.9  # metres: tightest bend of the centre line allowed
LENGTH_RANGE = (14.0, 34.0)  # metres of centre line
SPACING = 0.18  # metres between waypoints (the real tracks: 0.15-0.23)


def _centre_line(rng: np.random.Generator, length: float) -> np.ndarray:
    theta = np.linspace(0.0, 2 * math.pi, 2000, endpoint=False)
    r = np.ones_like(theta)
    for k in (2, 3, 4):
        r += rng.uniform(0.0, 0.28 / k ** 0.5) * np.cos(k * theta + rng.uniform(0, 2 * math.pi))
    squash = rng.uniform(0.55, 1.0)
    x, y = r * np.cos(theta), squash * r * np.sin(theta)
    rot = rng.uniform(0, 2 * math.pi)
    x, y = x * math.cos(rot) - y * math.sin(rot), x * math.sin(rot) + y * math.cos(rot)
    pts = np.stack([x, y], axis=1)
    seg = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    pts *= length / seg.sum()
    # resample at even arc length
    closed = np.vstack([pts, pts[:1]])
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    n = max(40, int(round(cum[-1] / SPACING)))
    s = np.linspace(0.0, cum[-1], n, endpoint=False)
    return np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], axis=1)


def _min_radius(pts: np.ndarray) -> float:
    """Smallest radius of curvature of a closed polyline (circumradius of consecutive triples)."""
    a, b, c = np.roll(pts, 1, axis=0), pts, np.roll(pts, -1, axis=0)
    ab, bc, ca = (np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    radius = ab * bc * ca / np.maximum(2 * cross, 1e-12)
    return float(radius.min())


def track_rows(centre: np.ndarray, width: float) -> np.ndarray:
    """DeepRacer (N+1, 6) rows for a closed counter-clockwise centre line and a constant width."""
    area = 0.5 * np.sum(centre[:, 0] * np.roll(centre[:, 1], -1) - np.roll(centre[:, 0], -1) * centre[:, 1])
    if area < 0:
        centre = centre[::-1]
    tangent = np.roll(centre, -1, axis=0) - np.roll(centre, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # points inside a CCW loop
    inner = centre + left * width / 2
    outer = centre - left * width / 2
    rows = np.hstack([centre, inner, outer])
    return np.vstack([rows, rows[:1]])


def generate_track(seed: int = 0, width: float | None = None, length: float | None = None,
                   name: str | None = None, reverse: bool = False, max_tries: int = 200) -> Track:
    """A valid closed track from `seed` (reproducible); width and length drawn unless given."""
    for attempt in range(max_tries):
        rng = np.random.default_rng([int(seed), attempt])
        w = float(width) if width is not None else float(rng.choice(WIDTHS))
        total = float(length) if length is not None else float(rng.uniform(*LENGTH_RANGE))
        centre = _centre_line(rng, total)
        if _min_radius(centre) < max(MIN_RADIUS, 0.6 * w + 0.3):
            continue
        try:
            return Track(track_rows(centre, w), name=name or f"generated_{seed}", source=f"<trackgen seed {seed}>",
                         reverse=reverse)
        except TrackError:
            continue
    raise TrackError(f"<trackgen seed {seed}>: no valid track in {max_tries} tries (width {width}, "
                     f"length {length})")


def save_track(track: Track, path) -> None:
    """Write a generated track as a DeepRacer .npy file (usable as --track PATH)."""
    rows = track.rows[::-1] if track.reverse else track.rows
    with AtomicOutput(path) as tmp, open(tmp, "wb") as f:
        np.save(f, np.asarray(rows, dtype=np.float64))
