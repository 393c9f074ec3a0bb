"""`multirace replay race.rrd --video out.mp4`: the top-down view rendered from a replay's recorded poses."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from multirace.racing.runner import RaceConfig, make_controller, run_race
from multirace.recording.replay import ReplayRecorder
from multirace.recording.replay_reader import replay_summary
from multirace.recording.replay_video import ReplayScene, replay_video
from multirace.sensors.topdown import layout_for
from multirace.sim.world import CAR_COLOURS

SIZE = (270, 480)


def _read_frames(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    return frames


def _colour_near(frame, col, row, colour, radius=4, tol=45) -> bool:
    r0, c0 = int(round(row)), int(round(col))
    patch = frame[max(r0 - radius, 0):r0 + radius + 1, max(c0 - radius, 0):c0 + radius + 1].astype(int)
    return bool((np.abs(patch - np.array(colour)).max(axis=-1) <= tol).any())


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay_video") / "race.rrd"
    config = RaceConfig(track="reinvent_base", race="head_to_head", laps=1, seed=0, max_steps=75)
    run_race([make_controller("bot:follow@1.5"), make_controller("bot:lanes@1.0")], config,
             recorders=[ReplayRecorder(path)])
    return path


def test_video_from_recorded_poses(recorded, tmp_path):
    out = tmp_path / "race.mp4"
    info = replay_video(recorded, out, size=SIZE)
    summary = replay_summary(recorded, poses=True)
    steps = summary["steps"]
    assert info["frames"] in (steps, steps + 1)
    frames = _read_frames(out)
    assert len(frames) in (steps, steps + 1)
    assert frames[0].shape == SIZE + (3,)
    for frame in frames[:: max(1, len(frames) // 5)]:
        assert frame.std() > 10, "blank frame"
    # a car's colour near its recorded position (frame k shows step k)
    scene = ReplayScene(recorded)
    layout = layout_for(scene, SIZE)
    length = scene.car_spec.length
    for i, cid in enumerate(["car_0", "car_1"]):
        poses = summary["poses"][cid]
        hits = 0
        for s, x, y, yaw in poses[10::10]:
            k = int(s)
            back = 0.25 * length
            col, row = layout.to_frame(np.array([x - back * math.cos(yaw), y - back * math.sin(yaw)]))
            hits += _colour_near(frames[k], col, row, CAR_COLOURS[i])
        assert hits >= 0.8 * len(poses[10::10]), f"{cid}: colour found near its recorded pose in only {hits} frames"
    # the cars move: the frames are not all the same
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 0.1


def test_scene_follows_recorded_poses(recorded):
    scene = ReplayScene(recorded)
    summary = scene.summary
    for cid, poses in summary["poses"].items():
        i = scene.ids.index(cid)
        s, x, y, yaw = poses[len(poses) // 2]
        scene.at(int(s))
        assert np.allclose(scene.world.poses[i], (x, y, yaw))
    assert sorted(scene.ranks()) == [1, 2]


def test_cli_replay_video(recorded, tmp_path):
    from multirace.cli import main

    out = tmp_path / "cli.mp4"
    assert main(["replay", str(recorded), "--video", str(out)]) == 0
    assert len(_read_frames(out)) >= 75
