"""Track loading, validation and geometry on the real DeepRacer tracks."""
import math
from pathlib import Path

import numpy as np
import pytest

from multirace.sim.tracks import Track, TrackError, list_tracks, load_track

ALL_TRACKS = list_tracks()


def test_all_41_bundled_tracks_load_with_known_lengths():
    assert len(ALL_TRACKS) == 41
    lengths = {name: load_track(name).length for name in ALL_TRACKS}
    # centre-line lengths from the tracks' README
    assert lengths["reinvent_base"] == pytest.approx(17.71, abs=0.01)
    assert lengths["reInvent2019_track"] == pytest.approx(23.12, abs=0.01)
    assert lengths["penbay_pro"] == pytest.approx(89.24, abs=0.01)
    assert lengths["Monaco"] == pytest.approx(60.27, abs=0.01)


@pytest.mark.parametrize("name", ALL_TRACKS)
def test_centre_points_project_onto_themselves(name):
    track = load_track(name)
    for s in np.linspace(0, track.length, 23, endpoint=False):
        x, y, heading = track.point_at(s)
        proj = track.project(x, y)
        assert proj.s == pytest.approx(s, abs=1e-6) or abs(proj.s - s) == pytest.approx(track.length, abs=1e-6)
        assert abs(proj.lateral) < 1e-6
        assert track.on_track(proj)
        assert proj.width > 0.5


def test_lateral_offset_sign_and_off_track():
    track = load_track("reinvent_base")
    x, y, heading = track.point_at(2.0, lateral=0.2)
    proj = track.project(x, y)
    assert proj.lateral == pytest.approx(0.2, abs=1e-6)  # + is left of the driving direction
    assert track.on_track(proj)
    x, y, _ = track.point_at(2.0, lateral=-0.6)  # the road is 0.76 m wide
    assert not track.on_track(track.project(x, y))


def test_reverse_runs_the_other_way_and_flips_left():
    fwd, rev = load_track("reinvent_base"), load_track("reinvent_base", reverse=True)
    assert rev.length == pytest.approx(fwd.length)
    x, y, heading = fwd.point_at(5.0, lateral=0.2)
    proj = rev.project(x, y)
    assert proj.lateral == pytest.approx(-0.2, abs=1e-3)
    assert abs(math.remainder(rev.project(x, y).heading - heading - math.pi, 2 * math.pi)) < 0.2


def test_monaco_runs_clockwise_and_inner_lane_is_on_the_right():
    track = load_track("Monaco")
    assert track.inner_side < 0  # CW loop: the geometric inside is to the right
    assert track.lane_offset(0, 5.0) < 0 < track.lane_offset(1, 5.0)


@pytest.mark.parametrize("name,reverse", [("Monaco", False), ("reinvent_base", False), ("reinvent_base", True)])
def test_lane_of_a_lateral_offset_is_the_lane_whose_centre_lies_there(name, reverse):
    track = load_track(name, reverse=reverse)
    for s in (0.0, 0.3 * track.length, 0.7 * track.length):
        assert [track.lane_of(track.lane_offset(lane, s)) for lane in (0, 1)] == [0, 1]


def test_hint_search_agrees_with_full_search():
    track = load_track("reInvent2019_track")
    rng = np.random.default_rng(0)
    for _ in range(200):
        s = rng.uniform(0, track.length)
        x, y, _ = track.point_at(s, rng.uniform(-0.4, 0.4))
        full = track.project(x, y)
        hinted = track.project(x, y, hint=full.segment + int(rng.integers(-3, 4)))
        assert hinted.s == pytest.approx(full.s, abs=1e-9)


def test_start_grid_is_staggered_in_alternating_lanes():
    track = load_track("reinvent_base")
    grid = track.start_grid(4)
    assert [round((-s) % track.length, 6) for s, _ in grid] == [0.0, 0.75, 1.5, 2.25]
    laterals = [lat for _, lat in grid]
    assert laterals[0] * laterals[1] < 0 and laterals[0] * laterals[2] > 0
    assert track.start_grid(1) == [(0.0, 0.0)]


def _save(tmp_path, name, array):
    path = tmp_path / name
    np.save(path, array)
    return path


def test_bad_track_files_fail_with_the_file_and_the_problem(tmp_path):
    good = np.load(load_track("reinvent_base").source)
    cases = {
        "shape.npy": (good[:, :4], "wrong shape"),
        "nan.npy": (np.where(np.arange(good.size).reshape(good.shape) == 40, np.nan, good), "NaN"),
        "few.npy": (good[:3], "distinct points"),
        "zero_width.npy": (np.column_stack([good[:, :2], good[:, :2], good[:, :2]]), "zero width"),
    }
    crossed = good.copy()
    crossed[[10, 30], 2:4] = crossed[[30, 10], 2:4]  # swap inner border points: a figure-eight border
    cases["cross.npy"] = (crossed, "self-intersecting")
    for name, (array, message) in cases.items():
        path = _save(tmp_path, name, array)
        with pytest.raises(TrackError) as err:
            load_track(path)
        assert str(path) in str(err.value) and message in str(err.value), str(err.value)


def test_unreadable_and_unknown_tracks(tmp_path):
    junk = tmp_path / "junk.npy"
    junk.write_bytes(b"not numpy at all")
    with pytest.raises(TrackError, match="junk.npy"):
        load_track(junk)
    with pytest.raises(TrackError, match="not a bundled track"):
        load_track("no_such_track")
    with pytest.raises(TrackError, match="no such file"):
        load_track(tmp_path / "missing.npy")


def test_tokyo_hairpin_with_skewed_border_rows_loads_at_its_drawn_width():
    # DeepRacer's Tokyo_Training_track pairs border points far along the track from their centre point
    # (1.16 m apart for a road whose border lines are 0.66 m apart); widths come from the border lines
    track = load_track("Tokyo_Training_track")
    assert track.width.min() > 0.6 and track.median_width == pytest.approx(0.66, abs=0.01)
    x, y, _ = track.point_at(track.cum_s[116], lateral=0.25)
    assert track.on_track(track.project(x, y))


def test_collapsed_border_rows_are_repaired_from_their_neighbours():
    rows = np.load(f"{Path(load_track('reinvent_base').source)}").copy()
    rows[40, 2:4] = rows[40, 0:2]  # inner point on the centre
    rows[41, 2:6] = np.concatenate([rows[41, 0:2], rows[41, 0:2]])  # both border points on the centre
    track = Track(rows, name="collapsed")
    assert track.width.min() == pytest.approx(load_track("reinvent_base").width.min(), abs=0.02)


def test_an_open_route_is_refused_as_not_a_closed_loop():
    s = np.linspace(0.0, 10.0, 50)
    straight = np.column_stack([s, np.zeros(50), s, np.full(50, 0.4), s, np.full(50, -0.4)])
    with pytest.raises(TrackError, match="not a closed loop"):
        Track(straight, source="Straight_track.npy")


def _ring(points=200, radius=3.0, half_width=0.4):
    theta = np.linspace(0, 2 * np.pi, points)
    unit = np.column_stack([np.cos(theta), np.sin(theta)])
    return np.column_stack([radius * unit, (radius - half_width) * unit, (radius + half_width) * unit])


@pytest.mark.parametrize("case, words", [
    ("empty", "0 waypoints"),
    ("centimetres", "implausible scale"),
    ("millimetres", "implausible scale"),
    ("six_cm_road", "0.060 m wide"),
    ("centre_outside", "centre line lies outside the road"),
    ("complex", "not real numbers"),
])
def test_implausible_tracks_are_refused_naming_the_file(tmp_path, case, words):
    ring = _ring()
    array = {"empty": np.zeros((0, 6)), "centimetres": ring * 100, "millimetres": ring * 1000,
             "six_cm_road": _ring(half_width=0.03),
             "centre_outside": np.column_stack([ring[:, 0:2] * 1.2, ring[:, 2:6]]),
             "complex": ring.astype(np.complex128)}[case]
    path = _save(tmp_path, f"{case}.npy", array)
    with pytest.raises(TrackError) as err:
        load_track(path)
    assert str(path) in str(err.value) and words in str(err.value), str(err.value)


def test_a_folder_or_fifo_named_like_a_track_is_refused_unread(tmp_path):
    import os

    (tmp_path / "folder.npy").mkdir()
    os.mkfifo(tmp_path / "fifo.npy")
    for name in ("folder.npy", "fifo.npy"):
        with pytest.raises(TrackError, match="not a regular file"):
            load_track(tmp_path / name)


def test_a_loop_too_short_for_the_grid_is_refused_before_the_race():
    import multirace

    small = Track(_ring(radius=0.38, half_width=0.3), source="small_loop.npy")  # a 2.4 m loop
    with pytest.raises(TrackError, match="small_loop.npy: 8 cars need a start grid of 6.00 m"):
        multirace.parallel_env(track=small, num_cars=8)
    multirace.parallel_env(track=small, num_cars=3).reset(seed=0)  # 2.25 m of grid fits


def test_self_intersection_check_agrees_with_brute_force_and_scales():
    from multirace.sim.tracks import find_self_intersection

    def brute(pts):
        pts = np.vstack([pts, pts[:1]])
        n = len(pts) - 1

        def orient(p, q, r):
            return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

        for i in range(n):
            for j in range(i + 2, n - (i == 0)):
                a0, a1, b0, b1 = pts[i], pts[i + 1], pts[j], pts[j + 1]
                if orient(b0, b1, a0) * orient(b0, b1, a1) < 0 and orient(a0, a1, b0) * orient(a0, a1, b1) < 0:
                    return i, j
        return None

    rng = np.random.default_rng(1)
    for trial in range(200):
        m = int(rng.integers(4, 50))
        theta = np.sort(rng.uniform(0, 2 * np.pi, m))
        radius = rng.uniform(1, 3, m) if trial % 2 else np.full(m, 2.0)
        pts = rng.uniform(0, 5, (m, 2)) if trial % 3 == 0 else np.column_stack([radius * np.cos(theta),
                                                                                radius * np.sin(theta)])
        assert find_self_intersection(pts) == brute(pts)
    big = _ring(points=100_000, radius=10.0)  # 100k points: grid-binned, not quadratic
    crossed = big.copy()
    crossed[[100, 60_000], 2:4] = crossed[[60_000, 100], 2:4]
    assert find_self_intersection(big[:, 2:4]) is None
    assert find_self_intersection(crossed[:, 2:4]) == (99, 60_000)
