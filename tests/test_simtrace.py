"""DeepRacer sim-trace CSV from a real race, and `multirace plot` on it."""
from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest

from multirace.cli import main
from multirace.racing.entrant import BotController
from multirace.racing.runner import RaceConfig, run_race
from multirace.recording.simtrace import SimTraceRecorder, SimTraceWriter, read_simtrace
from helpers import Wild

COLUMNS = ["episode", "steps", "X", "Y", "yaw", "steer", "throttle", "action", "reward", "done",
           "all_wheels_on_track", "progress", "closest_waypoint", "track_len", "tstamp", "episode_status",
           "pause_duration"]


class Capture:
    def start(self, env):
        self.rows = {}  # (car, step) -> (info, reward), while the car races and on the step it ends
        self.ended = [False] * len(env.races)

    def step(self, env, observations, rewards, infos):
        for i, agent in enumerate(env.possible_agents):
            if not self.ended[i]:
                self.rows[(i, env.steps)] = (infos[agent], rewards[agent])
                self.ended[i] = not env.races[i].racing

    def finish(self, env, result):
        self.result = result


@pytest.fixture(scope="module")
def trace(tmp_path_factory):
    path = tmp_path_factory.mktemp("simtrace") / "race.csv"
    capture = Capture()
    result = run_race([Wild("bot:follow@1.5"), BotController("bot:follow@1.0")],
                      RaceConfig(laps=1, race="time_trial", seed=3), recorders=[SimTraceRecorder(path), capture])
    return path, capture, result


def test_exact_columns(trace):
    path, _, _ = trace
    with open(path, newline="") as f:
        header = next(csv.reader(f))
    assert header == COLUMNS
    rows = read_simtrace(path)
    assert all(len(r) == len(COLUMNS) for r in rows)


def test_values_match_the_race(trace):
    path, capture, result = trace
    rows = read_simtrace(path)
    for car in (0, 1):
        mine = [r for r in rows if r["episode"] == car]
        steps = [int(r["steps"]) for r in mine]
        assert steps == list(range(1, len(mine) + 1)), "one row per step while the car races"
        truth = [capture.rows[(car, s)] for s in steps]
        np.testing.assert_allclose([r["X"] for r in mine], [t[0]["x"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["Y"] for r in mine], [t[0]["y"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["yaw"] for r in mine], [t[0]["heading"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["throttle"] for r in mine], [t[0]["speed"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["reward"] for r in mine], [t[1] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["tstamp"] for r in mine], np.array(steps) / 15, atol=1e-5)
        # progress rises to 100 at the lap's end, which is the last row (done)
        assert mine[-1]["episode_status"] == "lap_complete" and mine[-1]["progress"] == 100.0
        assert mine[-1]["done"] and not any(r["done"] for r in mine[:-1])
        assert mine[0]["episode_status"] == "prepare"
        on_track = [r["progress"] for r in mine[:-1] if r["episode_status"] == "in_progress"]
        assert on_track[-1] > 95 and on_track[0] < 5
        assert sum(b < a - 1 for a, b in zip(on_track, on_track[1:])) <= 1  # no falling except a reset
        assert all(r["track_len"] == pytest.approx(17.709, abs=0.01) for r in mine)


def test_off_track_is_marked_with_its_penalty(trace):
    path, capture, result = trace
    rows = read_simtrace(path)
    wild = [r for r in rows if r["episode"] == 0]
    off = [r for r in wild if r["episode_status"] == "off_track"]
    expected = [s for (car, s), (info, _) in capture.rows.items() if car == 0 and "off_track" in info["events"]]
    assert off and [int(r["steps"]) for r in off] == sorted(expected)
    assert all(r["pause_duration"] == 2.0 and not r["all_wheels_on_track"] for r in off)
    assert sum(r["pause_duration"] for r in wild) == pytest.approx(2.0 * len(off))
    by_name = {car["name"]: car for car in result["cars"]}
    assert by_name["bot:follow@1.5"]["resets"] == len(off)
    assert all(r["episode_status"] != "off_track" for r in rows if r["episode"] == 1)


def test_writer_for_training_loops(tmp_path, trace):
    _, capture, _ = trace
    path = tmp_path / "0-iteration.csv"
    with SimTraceWriter(path) as log:
        for (car, step), (info, reward) in sorted(capture.rows.items()):
            if car == 0:
                log.write_step(info, reward=reward, episode=7, action=3)
    rows = read_simtrace(path)
    assert rows and {r["episode"] for r in rows} == {7} and {r["action"] for r in rows} == {"3"}


def test_plot_writes_a_png_of_the_track_and_path(trace, tmp_path, capsys):
    path, _, _ = trace
    out = tmp_path / "trace.png"
    assert main(["plot", str(path), "--out", str(out)]) == 0
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    non_white = (image < 240).any(axis=2).mean()
    assert non_white > 0.02  # lines and points drawn, not a blank canvas
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    assert (hsv[..., 1] > 100).sum() > 500  # coloured path points (speed / reward colour maps)
