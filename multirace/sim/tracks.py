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
import os
import stat
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np

from ..resources import list_tracks, tracks_dir

TRACKS_DIR = tracks_dir()
MIN_POINTS = 4
MAX_ROWS = 100_000  # waypoints in one file (DeepRacer's tracks have a few hundred)
MAX_TRACK_BYTES = 16 * 2**20  # a .npy file larger than this is refused unread
MAX_EXTENT = 100.0  # metres across; DeepRacer's tracks span under 30 m (a file in cm or mm is far larger)
MIN_ROAD_WIDTH = 0.2  # metres: median width of the road between its border lines (a car is 0.2 m wide)
MAX_ROAD_WIDTH = 10.0  # metres: median distance between paired border points


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
        info = os.stat(path)
    except OSError as exc:
        raise TrackError(f"track file {path}: cannot be read ({exc.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        raise TrackError(f"track file {path}: not a regular file (a folder, device or FIFO)")
    if info.st_size > MAX_TRACK_BYTES:
        raise TrackError(f"track file {path}: {info.st_size / 2**20:.0f} MB, over the "
                         f"{MAX_TRACK_BYTES // 2**20} MB limit of a track file ({MAX_ROWS:,} waypoints at most)")
    try:
        rows = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises several types for bad files
        raise TrackError(f"track file {path}: cannot be read as a .npy array ({exc})") from exc
    return Track(rows, name=path.stem, source=str(path), reverse=reverse)


MAX_CHECK_PAIRS = 5_000_000  # candidate segment pairs the crossing check may test (real tracks: thousands)
LONG_SEGMENT_CELLS = 64  # a segment over more grid cells than this is tested against all others instead
MAX_LONG_SEGMENTS = 64
CROWDED = 32  # pairs in a cell of more segments are enumerated at once


def find_self_intersection(loop: np.ndarray, source: str = "<array>") -> tuple[int, int] | None:
    """First pair (i, j), i < j, of non-adjacent properly crossing segments of a closed polyline, or None.

    Segments are binned in a uniform grid about as fine as the median segment, and only segments sharing a
    cell are tested, so a loop of n points costs about O(n log n), not O(n^2).
    """
    pts = np.asarray(loop, np.float64)
    pts = pts if np.allclose(pts[0], pts[-1]) else np.vstack([pts, pts[:1]])
    n = len(pts) - 1
    a0, a1 = pts[:-1], pts[1:]
    lo, hi = np.minimum(a0, a1), np.maximum(a0, a1)
    extent = float(np.max(hi.max(axis=0) - lo.min(axis=0))) or 1.0
    cell = max(2.0 * float(np.median(np.linalg.norm(a1 - a0, axis=1))), extent * 1e-6)
    while True:  # coarser cells until the short segments cover a bounded number of cells in all
        first = np.floor((lo - lo.min(axis=0)) / cell).astype(np.int64)
        span = np.floor((hi - lo.min(axis=0)) / cell).astype(np.int64) - first + 1
        covered = span[:, 0] * span[:, 1]
        long = covered > LONG_SEGMENT_CELLS  # the few long segments are tested against every segment
        if long.sum() <= MAX_LONG_SEGMENTS and covered[~long].sum() <= 16 * n + 64:
            break
        cell *= 2.0
    covered[long] = 0
    seg = np.repeat(np.arange(n), covered)  # one entry per (segment, cell it covers)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(covered) - covered, covered)
    cx = first[seg, 0] + k % span[seg, 0]
    cy = first[seg, 1] + k // span[seg, 0]
    order = np.lexsort((seg, cy, cx))
    key = (cx * (int(cy.max(initial=0)) + 1) + cy)[order]
    seg = seg[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    if int((sizes * (sizes - 1) // 2).sum()) > MAX_CHECK_PAIRS:
        raise TrackError(f"track file {source}: border points too densely packed to check "
                         f"({int(sizes.max())} segments within {cell:.3g} m)")
    pairs = [np.column_stack([np.full(n, s), np.arange(n)]) for s in np.flatnonzero(long)]
    for offset in range(1, min(int(sizes.max(initial=0)), CROWDED)):  # entries `offset` apart in one cell
        same = key[offset:] == key[:-offset]
        pairs.append(np.column_stack([seg[:-offset][same], seg[offset:][same]]))
    for start, size in zip(starts[sizes > CROWDED], sizes[sizes > CROWDED]):  # the rest of a crowded cell's pairs
        a, b = np.triu_indices(size, CROWDED)
        pairs.append(np.column_stack([seg[start + a], seg[start + b]]))
    if not pairs:
        return None
    i, j = np.concatenate(pairs).T
    i, j = np.minimum(i, j), np.maximum(i, j)
    keep = (j > i + 1) & ~((i == 0) & (j == n - 1))
    i, j = i[keep], j[keep]  # a pair sharing several cells is tested several times: the answer is the same
    # bounding boxes overlap, then proper crossing (touching ends excluded)
    boxes = np.all((lo[i] <= hi[j]) & (hi[i] >= lo[j]), axis=1)
    i, j = i[boxes], j[boxes]

    def orient(p, q, r):
        return (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])

    crosses = ((orient(a0[j], a1[j], a0[i]) * orient(a0[j], a1[j], a1[i]) < 0)
               & (orient(a0[i], a1[i], a0[j]) * orient(a0[i], a1[i], a1[j]) < 0))
    if not crosses.any():
        return None
    first = int(np.min(i[crosses] * n + j[crosses]))
    return first // n, first % n


COLLAPSED = 0.01  # m: a border point this close to its centre point is a degenerate row


def repair_collapsed_borders(rows: np.ndarray) -> np.ndarray:
    """Rows whose border points coincide with the centre (zero width, as DeepRacer's simulator tolerates)
    get border points interpolated from the nearest sound rows on either side."""
    rows = rows.copy()
    n = len(rows) - 1  # the closed loop's rows (the last repeats the first)
    index = np.arange(n)
    for cols in (slice(2, 4), slice(4, 6)):
        bad = np.linalg.norm(rows[:n, cols] - rows[:n, 0:2], axis=1) < COLLAPSED
        if bad.all() or not bad.any():
            continue  # nothing to repair, or nothing to interpolate from (the width check names the track)
        good = index[~bad]
        around = np.concatenate([good - n, good, good + n])  # the loop's sound rows, periodically
        for c in range(cols.start, cols.stop):
            rows[index[bad], c] = np.interp(index[bad], around, np.tile(rows[good, c], 3))
        rows[n, cols] = rows[0, cols]
    return rows


BORDER_WINDOW = 15  # border segments searched on each side of a waypoint's own row


def nearest_border_points(center: np.ndarray, border: np.ndarray) -> np.ndarray:
    """For each centre waypoint, the nearest point of a closed border line, among the border segments within
    `BORDER_WINDOW` rows of its own (so the far side of a hairpin never counts)."""
    n = len(center) - 1  # rows of the closed loop (the last repeats the first)
    a = border[:-1]
    b = np.roll(a, -1, axis=0)
    rows = (np.arange(n)[:, None] + np.arange(-BORDER_WINDOW, BORDER_WINDOW + 1)[None, :]) % n
    a, ab = a[rows], (b - a)[rows]  # (n, window, 2)
    p = center[:n, None, :]
    t = np.clip(np.einsum("nwk,nwk->nw", p - a, ab) / np.maximum(np.einsum("nwk,nwk->nw", ab, ab), 1e-12), 0, 1)
    foot = a + t[..., None] * ab
    nearest = foot[np.arange(n), np.linalg.norm(p - foot, axis=2).argmin(axis=1)]
    return np.vstack([nearest, nearest[:1]])


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


class CarLocation(NamedTuple):
    """Where a car is on the track (`Track.locate_cars`): its reported point, its heading, the point's projection
    on the centre line (the fields of a `Projection`) and its wheels on the road."""

    x: float  # DeepRacer's reported point (ahead of the body centre)
    y: float
    yaw: float  # the car's heading, radians
    s: float  # arc length of the point's foot on the centre line
    lateral: float  # signed offset of the point, + left
    segment: int  # centre-line segment it projects on
    heading: float  # track direction at the foot point
    left_width: float  # road extent left and right of the centre line there
    right_width: float
    width: float  # left_width + right_width
    wheels_on: int  # wheels on the road, 0-4


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
        near_inner = nearest_border_points(self.center, self.inner)
        near_outer = nearest_border_points(self.center, self.outer)
        side_inner = np.einsum("ij,ij->i", near_inner - self.center, wp_normal)
        side_outer = np.einsum("ij,ij->i", near_outer - self.center, wp_normal)
        outside = (side_inner * side_outer > 0) & (np.minimum(abs(side_inner), abs(side_outer)) > COLLAPSED)
        if outside.any():
            raise TrackError(f"track file {source}: the centre line lies outside the road (both border lines on "
                             f"the same side of it) at {int(outside.sum())} of {len(outside)} waypoints, first at "
                             f"waypoint {int(np.argmax(outside))}")
        to_inner = np.linalg.norm(near_inner - self.center, axis=1)
        to_outer = np.linalg.norm(near_outer - self.center, axis=1)
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
        if self.median_width < MIN_ROAD_WIDTH:
            raise TrackError(f"track file {source}: the road is {self.median_width:.3f} m wide (median), under the "
                             f"{MIN_ROAD_WIDTH} m a car needs (DeepRacer's roads are 0.6-1.1 m)")
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
        if not (np.issubdtype(rows.dtype, np.floating) or np.issubdtype(rows.dtype, np.integer)):
            raise TrackError(f"track file {source}: dtype {rows.dtype} is not real numbers")
        if not 1 <= len(rows) <= MAX_ROWS:
            raise TrackError(f"track file {source}: {len(rows)} waypoints; a track has {MIN_POINTS} to {MAX_ROWS:,}")
        rows = rows.astype(np.float64)
        if not np.all(np.isfinite(rows)):
            bad = int(np.argwhere(~np.isfinite(rows))[0][0])
            raise TrackError(f"track file {source}: NaN or infinite value in row {bad}")
        extent = float(np.max(rows.reshape(-1, 2).max(axis=0) - rows.reshape(-1, 2).min(axis=0)))
        paired = float(np.median(np.linalg.norm(rows[:, 2:4] - rows[:, 4:6], axis=1)))
        if extent > MAX_EXTENT or paired > MAX_ROAD_WIDTH:
            raise TrackError(f"track file {source}: implausible scale: it spans {extent:.4g} with a road "
                             f"{paired:.4g} wide; tracks are in metres, at most {MAX_EXTENT:g} m across with roads "
                             f"under {MAX_ROAD_WIDTH:g} m (is this file in centimetres or millimetres?)")
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
            crossing = find_self_intersection(rows[:, cols], source)
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

    def locate_cars(self, poses: np.ndarray, hints: np.ndarray, offset: float, wheels: np.ndarray,
                    points: np.ndarray) -> list[CarLocation]:
        """Where cars are on the track: a `CarLocation` per car.

        poses (n, 3) of (x, y, yaw) at the body centre; the reported point is
        `offset` metres ahead of it; hints (n,) segment hints (-1 for none);
        wheels (4, 2) the (forward, left) wheel contact points from the centre. Each hint is set to the
        segment its car is found on (the next step's hint), and each row of points (n, 5) to its car's
        reported point, arc length, lateral offset and yaw (x, y, s, lateral, yaw), the location's fields in an
        array.
        """
        rows = _locate_cars(poses, hints, offset, wheels, self._segments, points)
        return [tuple.__new__(CarLocation, row) for row in rows]  # named tuples of full rows: no Python __new__ call

    def closest_waypoints(self, proj: Projection | CarLocation) -> tuple[int, int]:
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

    def lane_of(self, lateral: float) -> int:
        """The lane (`lane_offset`'s numbering) of the half of the road at `lateral` metres left of the centre
        line (the centre line itself counts to the right half)."""
        return 0 if (lateral > 0) == (self.inner_side > 0) else 1

    def start_grid(self, num_cars: int, spacing: float = 0.75, lanes: bool = True) -> list[tuple[float, float]]:
        """(s, lateral) start slots: car k is `k * spacing` behind the line, lanes alternating.

        With one car (or `lanes=False`) cars start on the centre line. TrackError if the loop is too short
        for the grid (the last car would reach the first).
        """
        if num_cars > 1 and num_cars * spacing > self.length:
            raise TrackError(f"track file {self.source}: {num_cars} cars need a start grid of "
                             f"{num_cars * spacing:.2f} m but the loop is only {self.length:.2f} m long")
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
def _locate_cars(poses, hints, offset, wheels, segments, points):
    """`Track.locate_cars`: a list of `CarLocation` rows (plain tuples, boxed by numba far cheaper than an array
    turned into one); sets each hint to its car's segment and each row of points to its (x, y, s, lateral, yaw)."""
    out = []
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
        hints[c] = segment
        points[c, 0], points[c, 1], points[c, 2], points[c, 3], points[c, 4] = px, py, s, lateral, yaw
        out.append((px, py, yaw, s, lateral, segment, heading, left, right, left + right, wheels_on))
    return out
