"""The top-down race view and MP4 writing, on the real env."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from multirace.environment.race_env import RaceEnv
from multirace.racing.runner import RaceConfig, make_controller, run_race
from multirace.sensors.topdown import layout_for, panel_order, render_topdown, view_state
from multirace.recording.replay import ReplayRecorder
from multirace.recording.replay_video import ReplayScene
from multirace.recording.video import VideoRecorder, write_video
from multirace.sim.world import CAR_COLOURS


def _colour_near(frame, col, row, colour, radius=3, tol=30) -> bool:
    r0, c0 = int(round(row)), int(round(col))
    patch = frame[max(r0 - radius, 0):r0 + radius + 1, max(c0 - radius, 0):c0 + radius + 1].astype(int)
    return bool((np.abs(patch - np.array(colour)).max(axis=-1) <= tol).any())


def _colour_pixels(frame, colour, right_edge, tol=30) -> int:
    area = frame[:, :right_edge].astype(int)
    return int((np.abs(area - np.array(colour)).max(axis=-1) <= tol).sum())


def _step(env, count):
    for _ in range(count):
        if not env.agents:
            break
        env.step({a: 5 for a in env.agents})


@pytest.mark.parametrize("num_cars, bots", [(1, ()), (4, ("follow@1.5",)), (3, ("follow@1.0", "lanes@1.5", "follow@2.0",
                                                                                 "lanes@1.0", "follow@1.2"))])
def test_shape_and_car_colours_at_car_positions(num_cars, bots):
    env = RaceEnv(num_cars=num_cars, bots=bots, race="object_avoidance", laps=2, render_mode="rgb_array")
    try:
        env.reset(seed=2)
        _step(env, 25)
        for size in ((540, 960), (240, 320)):
            frame = render_topdown(env, size)
            assert frame.shape == size + (3,) and frame.dtype == np.uint8
        frame = env.render()
        assert frame.shape == (540, 960, 3)
        layout = layout_for(env, (540, 960))
        total = env.total_cars
        for i in range(total):
            x, y, yaw = env.world.poses[i]
            # a point a quarter length behind the centre: body colour, not the heading mark
            back = 0.25 * env.car_spec.length
            col, row = layout.to_frame(np.array([x - back * math.cos(yaw), y - back * math.sin(yaw)]))
            assert _colour_near(frame, col, row, CAR_COLOURS[i]), f"car {i} colour not at its position"
        for x, y, _ in env.world.obstacle_poses:
            col, row = layout.to_frame(np.array([x, y]))
            assert _colour_near(frame, col, row, (250, 250, 250), radius=1, tol=10)
    finally:
        env.close()


def test_parked_cars_not_drawn_and_trails():
    env = RaceEnv(num_cars=2, laps=1, render_mode="rgb_array")
    try:
        before_reset = env.render()
        assert before_reset.shape == (540, 960, 3)
        env.reset(seed=0)
        for k in range(20):
            env.step({a: 5 for a in env.agents})
            frame = env.render()
            if k == 8:
                earlier = env.world.poses[0][:2].copy()
        layout = layout_for(env, (540, 960))
        assert np.hypot(*(env.world.poses[0][:2] - earlier)) > env.car_spec.length  # it moved on
        # the trail: car 0's colour (dimmed) where it was 11 steps ago
        dimmed = tuple(int(c * 0.8) for c in CAR_COLOURS[0])
        col, row = layout.to_frame(earlier)
        assert _colour_near(frame, col, row, dimmed, radius=2, tol=12)
        env.forfeit(0, "test")
        env.step({a: 5 for a in env.agents})
        frame = env.render()
        assert _colour_pixels(frame, CAR_COLOURS[0], layout.panel_x, tol=60) == 0
        assert _colour_pixels(frame, CAR_COLOURS[1], layout.panel_x) > 0
        # a new episode clears the trails
        env.reset(seed=1)
        env.render()
        assert all(len(t) == 1 for t in view_state(env).trails)
    finally:
        env.close()


def test_video_recorder_writes_readable_mp4(tmp_path):
    path = tmp_path / "race.mp4"
    recorder = VideoRecorder(path, size=(240, 320))
    controllers = [make_controller("bot:follow@1.5"), make_controller("bot:lanes@2.0")]
    run_race(controllers, RaceConfig(laps=1, max_steps=20), recorders=[recorder])
    assert recorder.frames == 21  # the start plus one per step
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    assert len(frames) == 21
    assert frames[0].shape == (240, 320, 3)


def test_write_video_from_iterator(tmp_path):
    path = tmp_path / "sub" / "gradient.mp4"
    frames = (np.full((64, 96, 3), 10 * k, np.uint8) for k in range(12))
    assert write_video(frames, path, fps=15) == 12
    capture = cv2.VideoCapture(str(path))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    ok, first = capture.read()
    assert ok and first.shape == (64, 96, 3)
    capture.release()
    with pytest.raises(ValueError):
        write_video([], tmp_path / "empty.mp4")
    with pytest.raises(ValueError):
        write_video([np.zeros((64, 96, 3), np.uint8), np.zeros((32, 32, 3), np.uint8)], tmp_path / "bad.mp4")


def test_videos_are_h264_in_mp4_as_browsers_play_them(tmp_path):
    # read back with OpenCV's own FFmpeg, not the PyAV that wrote it
    path = tmp_path / "odd.mp4"
    frames = [np.full((61, 97, 3), 20 * k, np.uint8) for k in range(10)]  # odd sizes are padded for yuv420p
    assert write_video(frames, path) == 10
    assert path.read_bytes()[4:8] == b"ftyp"  # an MP4 (ISO base media) file
    capture = cv2.VideoCapture(str(path))
    fourcc = int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode().lower()
    assert fourcc in ("avc1", "h264")
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(15.0)
    decoded = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        decoded.append(frame)
    capture.release()
    assert len(decoded) == 10 and decoded[0].shape[:2] == (62, 98)
    assert [int(round(f[:61, :97].mean())) for f in decoded] == pytest.approx([20 * k for k in range(10)], abs=3)


def _top_level_boxes(data: bytes) -> list[str]:
    """The types of an MP4's top-level boxes (atoms), in file order."""
    boxes, at = [], 0
    while at + 8 <= len(data):
        size, kind = int.from_bytes(data[at:at + 4], "big"), data[at + 4:at + 8].decode("latin-1")
        if size == 1:  # a 64-bit size follows the type
            size = int.from_bytes(data[at + 8:at + 16], "big")
        boxes.append(kind)
        at += size if size else len(data)
    return boxes


def test_videos_are_faststart_and_only_mp4(tmp_path):
    path = tmp_path / "fast.mp4"
    write_video([np.full((64, 96, 3), 9 * k, np.uint8) for k in range(20)], path)
    boxes = _top_level_boxes(path.read_bytes())
    assert "moov" in boxes and "mdat" in boxes
    assert boxes.index("moov") < boxes.index("mdat")  # a browser can start playing before the whole file arrives
    for name in ("race.avi", "race.gif", "race"):
        with pytest.raises(ValueError, match="MP4"):
            VideoRecorder(tmp_path / name)
        with pytest.raises(ValueError, match="MP4"):
            write_video([np.zeros((8, 8, 3), np.uint8)], tmp_path / name)
    assert not list(tmp_path.glob("race*"))


class _PanelWatch:
    """A race recorder that notes, after every step, the panel's order and the road order (rules' ranking)."""

    def __init__(self):
        self.steps = []

    def start(self, env):
        pass

    def step(self, env, *_):
        road = env.ranks()
        self.steps.append((panel_order(env), sorted(range(len(road)), key=lambda k: road[k]),
                           [race.penalty_time for race in env.races]))

    def finish(self, env, result):
        self.final = panel_order(env)


def test_the_video_panel_follows_the_results_order_with_penalties(tmp_path):
    # dagger_fast causes collisions: as the striker it collects 5 s penalties while it leads on the road
    watch = _PanelWatch()
    replay = tmp_path / "race.rrd"
    result = run_race([make_controller(s) for s in ("dagger_fast", "bot:follow@1.0", "bot:follow@1.5")],
                      RaceConfig(race="head_to_head", laps=2, seed=0),
                      recorders=[watch, ReplayRecorder(replay, image_every=0)])
    assert any(car["penalties"] for car in result["cars"]), "the race should have a penalised car"
    assert watch.final == [int(c["car"][4:]) for c in result["cars"]]  # the last frame lists the results' order
    scene = ReplayScene(replay)  # the replay's video (`multirace replay --video`) lists the same order
    assert all(panel_order(scene.at(k + 1)) == panel for k, (panel, _, _) in enumerate(watch.steps))
    scene.at(scene.last_step)  # and counts each car's at-fault collisions as the results do
    slots = sorted(result["cars"], key=lambda c: int(c["car"][4:]))
    assert [race.at_fault for race in scene.races] == [c["collisions_caused"] for c in slots]
    assert any(race.at_fault for race in scene.races)


class _Penalise(_PanelWatch):
    """A `_PanelWatch` that gives the road leader a 10 s penalty after 3 s of racing."""

    def step(self, env, *_):
        if env.steps == 45:
            env.races[int(np.argmin(env.ranks()))].penalty_time += 10.0
        super().step(env)


def test_a_road_leader_with_penalties_stands_where_it_will_finish():
    # follow bots never overtake: bot:follow@1.5 leads bot:follow@1.2 on the road all race, 12 s to 15 s a lap
    watch = _Penalise()
    result = run_race([make_controller("bot:follow@1.5"), make_controller("bot:follow@1.2")],
                      RaceConfig(race="head_to_head", laps=1, seed=0), recorders=[watch])
    assert [c["name"] for c in result["cars"]] == ["bot:follow@1.2", "bot:follow@1.5"]  # 15 s against 12 + 10 s
    assert watch.final == [1, 0]
    before, after = watch.steps[:44], watch.steps[45:]
    assert all(road == panel == [0, 1] for panel, road, _ in before)
    assert all(panel == [1, 0] for panel, _, _ in after)  # the panel counts the penalty at once...
    assert [road[0] for _, road, _ in after[:-1]] == [0] * (len(after) - 1)  # ...while it leads on the road


def test_penalties_and_resets_are_marked_on_the_car_and_in_the_panel():
    env = RaceEnv(num_cars=2, race="head_to_head", laps=1)
    env.reset(seed=0)
    plain = render_topdown(env)
    env.races[1].penalty_time, env.races[1].penalties, env.races[1].resets = 5.0, 1, 1
    env.core.sim_time += 0.1  # a moment later (the core keeps the clock)
    marked = render_topdown(env)
    layout = layout_for(env)
    col, row = (int(v) for v in layout.to_frame(env.world.poses[1][None, :2])[0])
    near = (slice(max(row - 40, 0), row + 40), slice(max(col - 40, 0), col + 40))
    assert (marked[near] != plain[near]).any(axis=2).sum() > 30  # a ring around car_1 and "+5s"
    assert (marked[:, layout.panel_x:] != plain[:, layout.panel_x:]).any()  # "+5s 1 reset" in its panel line
    env.races[1].collisions.append({"time": 0.1, "with": "car_0", "caused": True, "kind": "rear_end"})
    faulted = render_topdown(env)
    assert (faulted[:, layout.panel_x:] != marked[:, layout.panel_x:]).any()  # "+5s 1 reset 1 at fault"
    env.close()
