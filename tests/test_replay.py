"""Replays: record a real 2-car race (collision + off-track) to .rrd and read it back with rerun's reader."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from multirace.cli import main
from multirace.racing.entrant import BotController
from multirace.racing.runner import RaceConfig, run_race
from helpers import Frames, Wild, recorded_images
from multirace.recording.replay import ReplayRecorder
from multirace.recording.replay_process import WriterProcess
from multirace.recording.replay_reader import read_chunks, replay_summary

DT = 1.0 / 15


class Blind(BotController):
    """A bot that ignores the traffic ahead (so that it runs into the slower car)."""

    def act(self, observation, info):
        env, i = self.env, self.car
        return self.bot.command(env.track, env.car_spec, env.world.poses[i], env.sim_time,
                                env.race_state.cars[i].segment)


class Capture:
    """A recorder that keeps the race's own trajectory and events, to compare the replay with."""

    def start(self, env):
        self.poses = {i: {0: tuple(env.world.poses[i])} for i in range(len(env.races))}
        self.ended = [False] * len(env.races)
        self.events = []  # (step, car index, kind)
        self.collisions = [0] * len(env.races)
        self.image_steps = {i: [] for i in range(len(env.races))}

    def step(self, env, observations, rewards, infos):
        for i, race in enumerate(env.races):
            if self.ended[i]:
                continue
            self.poses[i][env.steps] = tuple(env.world.poses[i])
            if env.steps % 2 == 0:
                self.image_steps[i].append(env.steps)
            info = infos[env.possible_agents[i]]
            for event in info["events"]:
                self.events.append((env.steps, i, event))
            if len(race.collisions) > self.collisions[i]:
                for c in race.collisions[self.collisions[i]:]:
                    self.events.append((env.steps, i, "collision:" + c["with"]))
                self.collisions[i] = len(race.collisions)
            if not race.racing:
                self.events.append((env.steps, i, race.status))
                self.ended[i] = True
        self.final_step, self.final_time = env.steps, env.sim_time

    def finish(self, env, result):
        self.result = result


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "race.rrd"
    capture, frames = Capture(), Frames(every=2)
    controllers = [Wild("bot:follow@0.6", (200, 225), steer=-30.0), Blind("bot:follow@2.0")]  # 4 off-tracks, then on
    result = run_race(controllers, RaceConfig(laps=1, race="head_to_head", seed=1),
                      recorders=[ReplayRecorder(path, image_every=2), capture, frames])
    capture.jpegs = frames.jpegs  # the JPEG of each camera frame, encoded as the writer encodes it
    return path, capture, result


def test_race_has_collision_and_off_track(recorded):
    _, capture, result = recorded
    assert sum(car["collisions"] for car in result["cars"]) > 0
    assert sum(car["resets"] for car in result["cars"]) > 0
    kinds = {kind for _, _, kind in capture.events}
    assert "off_track" in kinds and "lap_complete" in kinds
    assert any(kind.startswith("collision:") for kind in kinds)


def test_replay_poses_match_the_race_trajectory(recorded):
    path, capture, _ = recorded
    summary = replay_summary(path)
    assert [c["id"] for c in summary["cars"]] == ["car_0", "car_1"]
    assert [c["name"] for c in summary["cars"]] == ["bot:follow@0.6", "bot:follow@2.0"]
    assert summary["steps"] == capture.final_step
    assert summary["duration"] == pytest.approx(capture.final_time, abs=1e-6)
    for i in range(2):
        recorded_poses = summary["poses"][f"car_{i}"]
        expected = capture.poses[i]
        assert [int(s) for s in recorded_poses[:, 0]] == sorted(expected), f"car_{i}: steps differ"
        truth = np.array([expected[s] for s in sorted(expected)])
        # positions are stored as float32: about 1e-6 m at these coordinates
        np.testing.assert_allclose(recorded_poses[:, 1:3], truth[:, :2], atol=1e-5)
        dyaw = (recorded_poses[:, 3] - truth[:, 2] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(dyaw).max() < 1e-5


def test_replay_images_are_jpeg_camera_frames(recorded):
    path, capture, _ = recorded
    summary = replay_summary(path, poses=False)
    for car in summary["cars"]:
        i = int(car["id"][-1])
        assert car["images"] == len(capture.image_steps[i]) > 0
    chunks = read_chunks(path)
    batch = chunks["cameras/car_1"][0]
    blob = batch.column(batch.schema.get_field_index("EncodedImage:blob")).to_pylist()[0][0]
    image = cv2.imdecode(np.frombuffer(bytes(blob), np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape[:2] == (120, 160)
    assert image.std() > 5  # a real camera view, not a blank frame


def test_replay_frames_are_the_cameras_the_agents_saw(recorded):
    """The writer draws the frames again from the recorded poses (`scene_cameras`): through a collision, resets
    and a finished car parked off the scene, every frame is the agent's own observation, JPEG-encoded."""
    path, capture, result = recorded
    assert any(car["status"] == "finished" for car in result["cars"])
    assert recorded_images(path) == capture.jpegs


@pytest.mark.parametrize("config", [dict(randomize="strong", grayscale=False), dict(grayscale=False)],
                         ids=["randomised, carried", "colour, drawn"])
def test_replay_frames_carried_or_drawn_match_the_observations(tmp_path, monkeypatch, config):
    """Randomised images (not a function of the poses) are carried to the writer as they are; colour cameras
    are drawn by it: either way each frame is the observation."""
    carried, carry = [], WriterProcess.carry

    def counted(writer, images):
        carried.append(len(images))
        return carry(writer, images)

    monkeypatch.setattr(WriterProcess, "carry", counted)
    path, frames = tmp_path / "race.rrd", Frames(every=2)
    run_race([BotController("bot:follow@1.5"), BotController("bot:follow@1.0")],
             RaceConfig(laps=1, seed=2, max_steps=40, **config), recorders=[ReplayRecorder(path, image_every=2), frames])
    assert frames.shapes == {(120, 160, 3)}  # colour observations
    assert len(frames.jpegs) == 2 * 20 and recorded_images(path) == frames.jpegs
    assert carried == ([2] * 20 if config.get("randomize") else [])  # a step's frames carried, or none


def test_scene_of_draws_only_pure_renders():
    """The writer draws the cameras only where an observation is the fast renderer's image of the poses."""
    from multirace.environment.race_env import RaceEnv
    from multirace.recording.scene_cameras import scene_of

    def scene(**config):
        env = RaceEnv(num_cars=2, **config)
        env.reset(seed=0)
        try:
            return scene_of(env)
        finally:
            env.close()

    assert scene() is not None and scene(lidar=True) is not None
    assert scene(sensor=["FRONT_FACING_CAMERA_TWO_FRAMES"]) is not None
    for config in (dict(randomize="strong"), dict(renderer="pybullet"), dict(sensor=["STEREO_CAMERAS"]),
                   dict(observation="state")):
        assert scene(**config) is None, config


def test_replay_events_have_the_right_race_times(recorded):
    path, capture, result = recorded
    summary = replay_summary(path, poses=False)
    events = summary["events"]
    for step, i, kind in capture.events:
        want = {"lap_complete": "lap", "off_track": "off_track"}.get(kind, kind)
        if kind.startswith("collision:"):
            want = "collision"
        matches = [e for e in events if e["step"] == step and e["car"] == f"car_{i}" and e["kind"] == want]
        assert matches, f"no {want} event for car_{i} at step {step}"
        assert matches[0]["race_time"] == pytest.approx(step * DT, abs=1e-6)
        if kind.startswith("collision:"):
            assert kind.split(":", 1)[1] in " ".join(e["text"] for e in matches)
    # every off-track of the time trial rules also resets the car and costs a penalty
    off_steps = {(s, i) for s, i, k in capture.events if k == "off_track"}
    resets = {(e["step"], int(e["car"][-1])) for e in events if e["kind"] == "reset"}
    assert off_steps <= resets
    assert any(e["kind"] == "penalty" for e in events)
    # laps and lap times as in the result
    by_name = {car["name"]: car for car in result["cars"]}
    for car in summary["cars"]:
        assert car["laps"] == by_name[car["name"]]["laps"]
        np.testing.assert_allclose(car["lap_times"], by_name[car["name"]]["lap_times"], atol=1e-3)
        assert car["status"] == "finished"
    assert summary["result"]["cars"][0]["name"] == result["cars"][0]["name"]


def test_cli_race_replay_and_summary(tmp_path, capsys):
    rrd, out_json = tmp_path / "cli.rrd", tmp_path / "summary.json"
    assert main(["race", "bot:follow@2.0", "bot:lanes@1.5", "--laps", "1", "--replay", str(rrd)]) == 0
    assert rrd.stat().st_size > 0
    assert f"wrote {rrd}" in capsys.readouterr().out  # as every command says what it wrote
    assert main(["replay", str(rrd), "--summary", "--json", str(out_json)]) == 0
    text = capsys.readouterr().out
    assert "bot:follow@2" in text and "lap 1 in" in text
    assert "s of sim time" in text and "race clock" in text  # which clock each time is on
    summary = json.loads(out_json.read_text())
    assert [c["laps"] for c in summary["cars"]] == [1, 1]
    assert summary["format"] == "head_to_head" and summary["steps"] > 0
