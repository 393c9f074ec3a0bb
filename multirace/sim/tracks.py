"""Track geometry for DeepRacer `.npy` waypoint files.

A DeepRacer track file is a float64 array of shape (N, 6) whose rows are
``[center_x, center_y, inner_x, inner_y, outer_x, outer_y]`` in metres; closed
loops repeat the first row as the last. This module loads and validates such
files, and answers the geometric questions the simulator asks every step:
where a point projects on the centre line (arc length, lateral offset, the
waypoints around it, local width), whether a wheel is on the road, where the
start grid and the lanes are.

Conventions: arc length ``s`` runs from waypoint 0 in the driving direction;
lateral offset is positive to the LEFT of the driving direction. Widths are
measured from the borders, not assumed symmetric around the centre line.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numba
import numpy as np

from ..resources import list_tracks, tracks_dir

TRACKS_DIR = tracks_dir()
MIN_POINTS = 4


class TrackError(ValueError):
    """A track file is missing or malformed; the message names the file."""


def resolve_track_path(track: str | Path) -> Path:
    """Turn a bundled track name or a path into an existing file path."""
    candidate = Path(track)
    if candidate.suffix == ".npy" or candidate.exists():
        if not candidate.exists():
            raise TrackError(f"track file {candidate}: no such file")
        return candidate
    bundled = TRACKS_DIR / f"{track}.npy"
    if bundled.exists():
        return bundled
    raise TrackError(
        f"track {track!r}: not a bundled track name nor a file; "
        f"bundled tracks: {', '.join(list_tracks())}"
    )


def load_track(track: str | Path, reverse: bool = False) -> "Track":
    """Load a bundled track by name, or any DeepRacer `.npy` file by path."""
    path = resolve_track_path(track)
    try:
        rows = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises several types for bad files
        raise TrackError(f"track file {path}: cannot be read as a .npy array ({exc})") from exc
    return Track(rows, name=path.stem, source=str(path), reverse=reverse)


def _segments_cross(a0, a1, b0, b1) -> bool:
    """Proper intersection of segments a0-a1 and b0-b1 (touching ends excluded)."""

    def orient(p, q, r):
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

    d1, d2 = orient(b0, b1, a0), orient(b0, b1, a1)
    d3, d4 = orient(a0, a1, b0), orient(a0, a1, b1)
    return d1 * d2 < 0 and d3 * d4 < 0


def find_self_intersection(loop: np.ndarray) -> tuple[int, int] | None:
    """First pair of non-adjacent crossing segments of a closed polyline, or None."""
    pts = loop if np.allclose(loop[0], loop[-1]) else np.vstack([loop, loop[:1]])
    n = len(pts) - 1
    a0, a1 = pts[:-1], pts[1:]
    lo, hi = np.minimum(a0, a1), np.maximum(a0, a1)
    for i in range(n):
        # bounding-box prefilter, then the exact test on the few candidates
        overlap = np.all((lo <= hi[i]) & (hi >= lo[i]), axis=1)
        for j in np.nonzero(overlap)[0]:
            if j <= i + 1 or (i == 0 and j == n - 1):
                continue
            if _segments_cross(a0[i], a1[i], a0[j], a1[j]):
                return i, int(j)
    return None


COLLAPSED = 0.01  # m: a border point this close to its centre point is a degenerate row


def repair_collapsed_borders(rows: np.ndarray) -> np.ndarray:
    """Rows whose border points coincide with the centre (zero width, as DeepRacer's simulator tolerates)
    get border points interpolated from the nearest sound rows on either side."""
    rows = rows.copy()
    n = len(rows) - 1  # the closed loop's rows (the last repeats the first)
    for cols in (slice(2, 4), slice(4, 6)):
        bad = np.linalg.norm(rows[:n, cols] - rows[:n, 0:2], axis=1) < COLLAPSED
        if bad.all():
            continue  # nothing to interpolate from: the width check names the track
        good = np.nonzero(~bad)[0]
        for k in np.nonzero(bad)[0]:
            before = good[good < k][-1] if np.any(good < k) else good[-1] - n
            after = good[good > k][0] if np.any(good > k) else good[0] + n
            t = (k - before) / (after - before)
            rows[k, cols] = (1 - t) * rows[before % n, cols] + t * rows[after % n, cols]
        rows[n, cols] = rows[0, cols]
    return rows


BORDER_WINDOW = 15  # border segments searched on each side of a waypoint's own row


def border_distances(center: np.ndarray, border: np.ndarray) -> np.ndarray:
    """Distance from each centre waypoint to the nearest segment of a closed border line, among the
    border segments within `BORDER_WINDOW` rows of its own (so the far side of a hairpin never counts)."""
    n = len(center) - 1  # rows of the closed loop (the last repeats the first)
    a = border[:-1]
    b = np.roll(a, -1, axis=0)
    rows = (np.arange(n)[:, None] + np.arange(-BORDER_WINDOW, BORDER_WINDOW + 1)[None, :]) % n
    a, ab = a[rows], (b - a)[rows]  # (n, window, 2)
    p = center[:n, None, :]
    t = np.clip(np.einsum("nwk,nwk->nw", p - a, ab) / np.maximum(np.einsum("nwk,nwk->nw", ab, ab), 1e-12), 0, 1)
    nearest = np.linalg.norm(p - (a + t[..., None] * ab), axis=2).min(axis=1)
    return np.append(nearest, nearest[0])


@dataclasses.dataclass
class Projection:
    """Where a point lies relative to the track's centre line."""

    s: float  # arc length of the foot point from waypoint 0, metres
    lateral: float  # signed offset, + left of the driving direction, metres
    segment: int  # index i of the centre-line segment (waypoints i, i+1)
    heading: float  # track direction at the foot point, radians
    left_width: float  # road extent to the left of the centre line, metres
    right_width: float  # road extent to the right of the centre line, metres

    @property
    def width(self) -> float:
        return self.left_width + self.right_width


class Track:
    """A closed DeepRacer track with its geometry precomputed."""

    def __init__(self, rows: np.ndarray, name: str = "track", source: str = "<array>", reverse: bool = False):
        self.name = name
        self.source = source
        self.reverse = bool(reverse)
        rows = self._validate(np.asarray(rows), source)
        if self.reverse:
            rows = rows[::-1].copy()
        self.rows = rows
        self.center = rows[:, 0:2].copy()
        self.inner = rows[:, 2:4].copy()
        self.outer = rows[:, 4:6].copy()
        # DeepRacer's `waypoints` param: the centre line as listed in the file.
        self.waypoints = [(float(x), float(y)) for x, y in self.center]

        seg = np.diff(self.center, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        self.seg_start = self.center[:-1]
        self.seg_vec = seg
        self.seg_len = seg_len
        self.seg_len2 = np.maximum(seg_len**2, 1e-12)
        self.cum_s = np.concatenate([[0.0], np.cumsum(seg_len)])
        self.length = float(self.cum_s[-1])
        # unit direction per segment; zero-length segments borrow the next one
        direction = seg / np.maximum(seg_len, 1e-9)[:, None]
        for i in np.nonzero(seg_len < 1e-9)[0][::-1]:
            direction[i] = direction[(i + 1) % len(direction)]
        self.seg_dir = direction
        self.seg_heading = np.arctan2(direction[:, 1], direction[:, 0])
        normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)  # left normal

        # Which physical side is "inner": +1 if inner is to the left (a CCW loop), from the
        # paired border points' side of the centre line (averaged normal at each waypoint).
        wp_normal = np.empty_like(self.center)
        wp_normal[:-1] = normal
        wp_normal[-1] = normal[0]
        wp_normal[1:-1] = normal[:-1] + normal[1:]
        wp_normal[0] = wp_normal[-1] = normal[0] + normal[-1]
        wp_normal /= np.maximum(np.linalg.norm(wp_normal, axis=1), 1e-9)[:, None]
        inner_off = np.einsum("ij,ij->i", self.inner - self.center, wp_normal)
        self.inner_side = 1.0 if np.median(inner_off) > 0 else -1.0
        # The road's extent to each side at every waypoint: the distance from the centre point to the
        # nearest part of that side's border line (paired border rows can be skewed or coincide with the
        # centre in hairpins, as in DeepRacer's own Tokyo_Training_track; the border lines are still right).
        to_inner, to_outer = border_distances(self.center, self.inner), border_distances(self.center, self.outer)
        self.left_width = to_inner if self.inner_side > 0 else to_outer
        self.right_width = to_outer if self.inner_side > 0 else to_inner
        self.width = self.left_width + self.right_width
        self._segments = np.column_stack([  # one row per segment, columns as _project_point reads them
            self.seg_start, self.seg_vec, self.seg_len2, self.seg_dir, self.cum_s[:-1], self.seg_len,
            self.seg_heading, self.left_width[:-1], self.left_width[1:], self.right_width[:-1], self.right_width[1:]])
        if np.any(self.left_width + self.right_width < 0.05):
            bad = int(np.argmin(self.left_width + self.right_width))
            raise TrackError(f"track file {source}: zero width at waypoint {bad}")
        self.median_width = float(np.median(self.width))
        xy = np.vstack([self.inner, self.outer])
        self.bounds = (xy.min(axis=0), xy.max(axis=0))

    # ------------------------------------------------------------------ load
    @staticmethod
    def _validate(rows: np.ndarray, source: str) -> np.ndarray:
        if rows.ndim != 2 or rows.shape[1] != 6:
            raise TrackError(
                f"track file {source}: wrong shape {rows.shape}, expected (N, 6) rows of "
                "[center_x, center_y, inner_x, inner_y, outer_x, outer_y]"
            )
        if not np.issubdtype(rows.dtype, np.number):
            raise TrackError(f"track file {source}: dtype {rows.dtype} is not numeric")
        rows = rows.astype(np.float64)
        if not np.all(np.isfinite(rows)):
            bad = int(np.argwhere(~np.isfinite(rows))[0][0])
            raise TrackError(f"track file {source}: NaN or infinite value in row {bad}")
        if not np.allclose(rows[0], rows[-1]):
            gap = float(np.linalg.norm(rows[0, :2] - rows[-1, :2]))
            step = float(np.median(np.linalg.norm(np.diff(rows[:, :2], axis=0), axis=1)))
            if gap > max(5 * step, 0.5):
                raise TrackError(f"track file {source}: not a closed loop (the last waypoint is {gap:.2f} m from "
                                 "the first); multirace races closed tracks only")
            rows = np.vstack([rows, rows[:1]])
        distinct = len(np.unique(rows[:-1, 0:2].round(6), axis=0))
        if distinct < MIN_POINTS:
            raise TrackError(f"track file {source}: {distinct} distinct points, need at least {MIN_POINTS}")
        rows = repair_collapsed_borders(rows)
        for label, cols in (("inner", slice(2, 4)), ("outer", slice(4, 6))):
            crossing = find_self_intersection(rows[:, cols])
            if crossing is not None:
                raise TrackError(
                    f"track file {source}: self-intersecting {label} border "
                    f"(segments {crossing[0]} and {crossing[1]} cross)"
                )
        return rows

    # ------------------------------------------------------------ geometry
    def point_at(self, s: float, lateral: float = 0.0) -> tuple[float, float, float]:
        """World (x, y, heading) at arc length `s` and lateral offset (+ left)."""
        s = s % self.length
        i = int(np.searchsorted(self.cum_s, s, side="right") - 1)
        i = min(max(i, 0), len(self.seg_len) - 1)
        t = (s - self.cum_s[i]) / max(self.seg_len[i], 1e-9)
        x, y = self.seg_start[i] + t * self.seg_vec[i]
        heading = float(self.seg_heading[i])
        x -= lateral * math.sin(heading)
        y += lateral * math.cos(heading)
        return float(x), float(y), heading

    def project(self, x: float, y: float, hint: int | None = None) -> Projection:
        """Project a world point on the centre line.

        With `hint` (the segment found last time) only a few segments around it
        are searched, which is what makes per-step projection cheap; the whole
        track is searched when the local answer is at the edge of that window or
        far away.
        """
        return Projection(*_project_point(x, y, -1 if hint is None else hint, self._segments))

    def locate_cars(self, poses: np.ndarray, hints: np.ndarray, offset: float, wheels: np.ndarray) -> list[tuple]:
        """Where cars are on the track: per car (x, y) of its reported point, its Projection and wheels on track.

        poses (n, 3) of (x, y, yaw) at the body centre; the reported point is
        `offset` metres ahead of it; hints (n,) segment hints (-1 for none);
        wheels (4, 2) the (forward, left) wheel contact points from the centre.
        """
        rows = _locate_cars(poses, hints, offset, wheels, self._segments).tolist()
        return [(px, py, Projection(s, lateral, int(segment), heading, left, right), int(wheels_on))
                for px, py, s, lateral, segment, heading, left, right, wheels_on in rows]

    def closest_waypoints(self, proj: Projection) -> tuple[int, int]:
        """DeepRacer's `closest_waypoints`: indices of the waypoints behind and ahead."""
        return proj.segment, proj.segment + 1

    def closest_waypoint(self, proj: Projection) -> int:
        """The nearer of the two waypoints around the foot point (sim-trace column)."""
        i = proj.segment
        t = (proj.s - self.cum_s[i]) / max(self.seg_len[i], 1e-9)
        return i if t < 0.5 else i + 1

    def on_track(self, proj: Projection, margin: float = 0.0) -> bool:
        """Is a point with this projection on the road (borders included)?"""
        return -proj.right_width - margin <= proj.lateral <= proj.left_width + margin

    def lane_offset(self, lane: int, s: float = 0.0) -> float:
        """Lateral offset of a lane centre: lane 0 is the inner half, lane 1 the outer."""
        proj = self.project(*self.point_at(s)[:2])
        left, right = proj.left_width, proj.right_width
        inner_is_left = self.inner_side > 0
        want_left = (lane == 0) == inner_is_left
        return left / 2 if want_left else -right / 2

    def start_grid(self, num_cars: int, spacing: float = 0.75, lanes: bool = True) -> list[tuple[float, float]]:
        """(s, lateral) start slots: car k is `k * spacing` behind the line, lanes alternating.

        With one car (or `lanes=False`) cars start on the centre line.
        """
        slots = []
        for k in range(num_cars):
            s = (-k * spacing) % self.length
            lateral = self.lane_offset(k % 2, s) if (lanes and num_cars > 1) else 0.0
            slots.append((s, lateral))
        return slots

    def wrap_ds(self, ds: float) -> float:
        """Wrap an arc-length difference into [-L/2, L/2)."""
        half = self.length / 2
        return (ds + half) % self.length - half

    def __repr__(self) -> str:
        rev = ", reverse" if self.reverse else ""
        return f"Track({self.name!r}{rev}, length={self.length:.2f} m, {len(self.center)} waypoints)"


@numba.njit(cache=True)
def _project_point(x, y, hint, segments):
    """(s, lateral, segment, heading, left width, right width) of a point; `hint` < 0 searches the whole track.

    `segments` rows: start x, y, vector x, y, squared length, unit direction
    x, y, arc length at the start, length, heading, left width at both ends,
    right width at both ends.
    """
    n = segments.shape[0]
    best, best_t, best_d2, best_k = -1, 0.0, math.inf, 0
    if hint >= 0:  # a few segments around the hint
        for k in range(hint - 3, hint + 6):
            t, d2 = _foot(x, y, segments[k % n])
            if d2 < best_d2:
                best, best_t, best_d2, best_k = k % n, t, d2, k
    if hint < 0 or not (hint - 3 < best_k < hint + 5 and best_d2 < 4.0):  # the answer may lie outside the window
        best, best_t, best_d2 = -1, 0.0, math.inf
        for i in range(n):
            t, d2 = _foot(x, y, segments[i])
            if d2 < best_d2:
                best, best_t, best_d2 = i, t, d2
    seg = segments[best]
    fx, fy = seg[0] + best_t * seg[2], seg[1] + best_t * seg[3]
    lateral = math.copysign(math.hypot(x - fx, y - fy), (x - fx) * -seg[6] + (y - fy) * seg[5])
    return (seg[7] + best_t * seg[8], lateral, best, seg[9],
            seg[10] + best_t * (seg[11] - seg[10]), seg[12] + best_t * (seg[13] - seg[12]))


@numba.njit(cache=True)
def _foot(x, y, seg):
    """Position t (0..1) of the foot point on a segment, and the squared distance to it."""
    dx, dy = x - seg[0], y - seg[1]
    t = min(max((dx * seg[2] + dy * seg[3]) / seg[4], 0.0), 1.0)
    ex, ey = dx - t * seg[2], dy - t * seg[3]
    return t, ex * ex + ey * ey


@numba.njit(cache=True)
def _locate_cars(poses, hints, offset, wheels, segments):
    out = np.empty((poses.shape[0], 9))
    for c in range(poses.shape[0]):
        x, y, yaw = poses[c, 0], poses[c, 1], poses[c, 2]
        cos_y, sin_y = math.cos(yaw), math.sin(yaw)
        px, py = x + offset * cos_y, y + offset * sin_y
        s, lateral, segment, heading, left, right = _project_point(px, py, hints[c], segments)
        # wheels: lateral offsets in the local track frame of the projection
        nx, ny = -math.sin(heading), math.cos(heading)
        wheels_on = 0
        for w in range(wheels.shape[0]):
            fx, side = wheels[w, 0] - offset, wheels[w, 1]
            wx, wy = fx * cos_y - side * sin_y, fx * sin_y + side * cos_y
            if -right <= lateral + wx * nx + wy * ny <= left:
                wheels_on += 1
        out[c, 0], out[c, 1], out[c, 2], out[c, 3], out[c, 4] = px, py, s, lateral, segment
        out[c, 5], out[c, 6], out[c, 7], out[c, 8] = heading, left, right, wheels_on
    return out
