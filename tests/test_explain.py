"""`multirace explain`: Grad-CAM of a shipped agent lies on the track borders and the road ahead."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import load_agent, make_metadata, save_agent
from multirace.environment.race_env import RaceEnv
from multirace.tools.explain import (BORDER, CENTRE, FLOOR, ROAD, SKY, TRACK_LABELS, GradCam, cell_geometry, explain,
                               heat_shares, last_conv_activation, scene_labels)
from multirace.sensors.fast_renderer import _gray
from multirace.racing.nets import build_net
from multirace.recording.replay_reader import read_chunks, replay_summary, view_origins

AGENT = Path(__file__).resolve().parents[1] / "agents" / "dagger_small.pt"
pytestmark = pytest.mark.skipif(not AGENT.exists(), reason="shipped agent agents/dagger_small.pt missing")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("explain")
    result = explain(AGENT, track="reinvent_base", steps=120, out=tmp / "strip.png", replay=tmp / "explain.rrd",
                     keep_frames=True)
    return result, tmp


def test_heat_lies_on_track_borders_and_road(run):
    result, _ = run
    heats, labels = result["heats"], result["labels"]
    assert result["frames"] == len(heats) == 120
    on_track, area = [], []
    for heat, label in zip(heats, labels):
        shares = heat_shares(heat, label)
        on_track.append(shares["heat_on_track"])
        area.append(shares["track_fraction"])
    on_track, area = float(np.mean(on_track)), float(np.mean(area))
    # most of the heat is on the road, its borders and centre line ...
    assert on_track > 0.6, on_track
    # ... clearly more than the track's share of the image (what a uniform map would give) ...
    assert on_track > area + 0.04, (on_track, area)
    # ... and the painted lines (borders, centre dashes) draw heat well above their area share
    assert result["lines_lift"] > 1.25, result["lines_lift"]
    # a uniform heat map scores exactly the area share, so it fails the test above
    uniform = np.ones_like(heats[0])
    assert heat_shares(uniform, labels[0])["heat_on_track"] == pytest.approx(heat_shares(uniform, labels[0])[
        "track_fraction"])
    # the maps follow the image: the same heat against another frame's scene scores lower
    n = len(heats)
    shuffled = np.mean([heat_shares(heats[k], labels[(k + n // 2) % n])["heat_on_track"] for k in range(n)])
    assert on_track > shuffled, (on_track, shuffled)


def test_scene_labels_match_the_camera_image():
    env = RaceEnv(track="reinvent_base", num_cars=1, race="time_trial", laps=1, max_steps=30)
    try:
        obs, _ = env.reset(seed=1)
        for _ in range(10):
            obs, *_ = env.step({"car_0": env.actions.nearest(0.0, 1.0)})
        labels = scene_labels(env)
        p = env.texture.palette
        grey = np.array([_gray(p.floor), _gray(p.road), _gray(p.border), _gray(p.centre), _gray(p.sky)])
        image = obs["car_0"].astype(int)
        agree = np.abs(grey[labels] - image) <= 12
        assert agree.mean() > 0.97, agree.mean()
        assert set(np.unique(labels)) <= {FLOOR, ROAD, BORDER, CENTRE, SKY}
        assert (labels == ROAD).mean() > 0.2 and (labels == SKY)[0].all()
    finally:
        env.close()


def test_cells_sit_at_their_receptive_field_centres():
    agent = load_agent(AGENT, step_budget=None)
    layer = last_conv_activation(agent.net)
    (row0, col0), (row_step, col_step) = cell_geometry(agent.net, layer)
    assert (row0, col0, row_step, col_step) == (32.5, 32.5, 16.0, 16.0)  # small CNN on 120x160
    cam = GradCam(agent.net, discrete=True)
    try:
        impulse = np.zeros((4, 6), np.float32)
        impulse[1, 2] = 1.0
        up = cam.upsample(impulse, 120, 160)
        r, c = np.unravel_index(np.argmax(up), up.shape)
        assert abs(r - (row0 + row_step)) <= 1 and abs(c - (col0 + 2 * col_step)) <= 1
    finally:
        cam.close()


def test_outputs_strip_and_replay(run):
    result, tmp = run
    strip = cv2.imread(str(tmp / "strip.png"))
    assert strip is not None and strip.shape[0] > 2 * 120 and strip.shape[1] > 4 * 160
    summary = replay_summary(tmp / "explain.rrd", poses=True)
    assert summary["steps"] == 120 and len(summary["poses"]["car_0"]) >= 100
    chunks = read_chunks(tmp / "explain.rrd")
    blobs = [b for batch in chunks.get("explain/car_0", []) for b in batch.column(
        batch.schema.get_field_index("EncodedImage:blob")).to_pylist() if b]
    assert len(blobs) == 120
    first = cv2.imdecode(np.frombuffer(bytes(blobs[0][0]) if isinstance(blobs[0][0], (list, bytes)) else
                                       np.asarray(blobs[0], np.uint8).tobytes(), np.uint8), cv2.IMREAD_COLOR)
    assert first is not None and first.shape[:2] == (120, 160)
    assert {"explain", "cameras", "world"} <= set(view_origins(tmp / "explain.rrd"))  # it opens on the overlay


def test_continuous_agent_mp4_and_cli(tmp_path):
    from multirace.cli import main

    space = load_action_space({"action_space": {"steering_angle": {"low": -30, "high": 30},
                                                "speed": {"low": 0.5, "high": 1.5}},
                               "action_space_type": "continuous"})
    net = build_net(image_shape=(120, 160, 1), action_space=space)
    path = save_agent(tmp_path / "cont.pt", net, make_metadata(space, net.network, "cont"))
    out = tmp_path / "heat.mp4"
    assert main(["explain", str(path), "--track", "Oval_track", "--steps", "8", "--out", str(out)]) == 0
    cap = cv2.VideoCapture(str(out))
    count = 0
    while cap.read()[0]:
        count += 1
    assert count == 8
    assert cap.get(cv2.CAP_PROP_FRAME_WIDTH) == 480
    assert TRACK_LABELS == (ROAD, BORDER, CENTRE)


def test_explain_says_when_the_one_lap_ends_the_run_before_its_steps(tmp_path, capsys):
    from multirace.cli import main

    assert main(["explain", "racer", "--track", "Mexico_track", "--steps", "200", "--out",
                 str(tmp_path / "strip.png")]) == 0  # racer laps Mexico_track in about 6.4 s: 96 steps
    printed = " ".join(capsys.readouterr().out.split())
    assert "ended (finished) after" in printed and "of --steps 200" in printed and "one lap at most" in printed
