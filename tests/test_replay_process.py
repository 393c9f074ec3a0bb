"""Replays written by the writer process: every step and every image reaches the file, a writer's failure is an
error naming the file, and no writer outlives the race's process or a failed race (real races, real processes)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from multirace.atomic import OutputError
from multirace.racing.entrant import BotController
from multirace.racing.runner import RaceConfig, make_controller, run_race
from multirace.recording import replay_process
from multirace.recording.replay import ReplayRecorder
from helpers import Frames, recorded_images
from multirace.recording.replay_reader import replay_summary, view_origins

BOTS = ("bot:follow@1.5", "bot:lanes@1.0", "bot:follow@1.0", "bot:lanes@1.5")
class Act(BotController):
    """A bot that does `what(self)` once, at step `at`."""

    def __init__(self, spec, at, what):
        super().__init__(spec)
        self.at, self.what = at, what

    def act(self, observation, info):
        if self.env.steps == self.at:
            self.what(self)
        return super().act(observation, info)


def leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def ended(process) -> bool:
    """Whether the writer's process has ended (a zombie whose parent died counts as ended)."""
    try:
        with open(f"/proc/{process}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def test_a_long_replay_holds_every_step_and_every_camera_frame(tmp_path):
    # 700 steps in blocks of 100 rows (not a multiple of the 90-step messages), a frame every 7th step: the
    # file must hold each car's pose at every step and the very frame of every 7th step, and rerun's reader must
    # read it (two blocks or more once made a file with two manifests, which it refused)
    path, frames = tmp_path / "long.rrd", Frames(every=7)
    run_race([make_controller(b) for b in BOTS], RaceConfig(race="reset_rule", laps=1000, max_steps=700),
             recorders=[frames, ReplayRecorder(path, image_every=7, flush_every=100)])
    summary = replay_summary(path)
    assert summary["steps"] == 700
    for i in range(len(BOTS)):
        poses = summary["poses"][f"car_{i}"]
        assert [int(s) for s in poses[:, 0]] == list(range(701)), f"car_{i}: a step is missing"
        truth = np.array([frames.poses[(i, s)] for s in range(1, 701)])
        np.testing.assert_allclose(poses[1:, 1:3], truth, atol=1e-5)
    images = recorded_images(path)
    assert len(frames.jpegs) == 4 * 100 and images == frames.jpegs  # the right frame at the right step


class StoppedWriter:
    """A recorder that stops the replay writer's process (SIGSTOP) from step `stop` to step `go`, so that the
    race's messages queue up for it."""

    def __init__(self, replay: ReplayRecorder, stop: int, go: int):
        self.replay, self.stop, self.go = replay, stop, go

    def start(self, env):
        pass

    def step(self, env, observations, rewards, infos):
        step = env.race_state.step
        if step in (self.stop, self.go):
            os.kill(self.replay._writer.process.pid, signal.SIGSTOP if step == self.stop else signal.SIGCONT)

    def finish(self, env, result):
        pass


def test_a_writer_behind_the_race_holds_blocks_back_and_still_writes_every_step(tmp_path):
    # the writer stopped for 500 steps finds six messages waiting: it holds full blocks of 100 rows back until
    # the queue is empty (or a block would pass 200 rows), and every pose and frame still reaches the file
    path, frames = tmp_path / "behind.rrd", Frames(every=7)
    replay = ReplayRecorder(path, image_every=7, flush_every=100)
    run_race([make_controller(b) for b in BOTS], RaceConfig(race="reset_rule", laps=1000, max_steps=700),
             recorders=[frames, replay, StoppedWriter(replay, stop=50, go=550)])
    summary = replay_summary(path)
    for i in range(len(BOTS)):
        poses = summary["poses"][f"car_{i}"]
        assert [int(s) for s in poses[:, 0]] == list(range(701)), f"car_{i}: a step is missing"
    assert recorded_images(path) == frames.jpegs


def test_frames_the_shared_arena_has_no_room_for_reach_the_file_through_the_socket(tmp_path, monkeypatch):
    # an arena of six grey frames (a fresh writer: the waiting one has the full-size arena): in a 4-car race
    # most steps' four frames find it full and go in the messages themselves; every frame still reaches the
    # file, at its step (a randomised race: its frames are carried, not drawn by the writer)
    monkeypatch.setattr(replay_process, "ARENA_BYTES", 6 * 120 * 160)
    monkeypatch.setattr(replay_process, "_idle", [])
    carried = []
    carry = replay_process.WriterProcess.carry

    def counted(self, images):
        carried.append(carry(self, images))
        return carried[-1]

    monkeypatch.setattr(replay_process.WriterProcess, "carry", counted)
    path, frames = tmp_path / "small.rrd", Frames(every=3)
    run_race([make_controller(b) for b in BOTS], RaceConfig(race="reset_rule", laps=1000, max_steps=240,
                                                                  randomize="mild"),
             recorders=[frames, ReplayRecorder(path, image_every=3)])
    in_arena = sum(isinstance(where, tuple) for where in carried)  # an `ArenaImage`'s fields
    assert 0 < in_arena < len(carried) == 80  # one carry a step, of the four cars' frames
    assert recorded_images(path) == frames.jpegs


def test_a_replay_does_not_change_the_race(tmp_path):
    config = RaceConfig(race="head_to_head", laps=1, seed=3, max_steps=300)
    plain = run_race([make_controller(b) for b in BOTS[:2]], config)
    recorded = run_race([make_controller(b) for b in BOTS[:2]], config, recorders=[ReplayRecorder(tmp_path / "r.rrd")])
    assert recorded == plain


def test_a_race_with_a_replay_opens_on_its_cameras_without_importing_rerun_in_its_process(tmp_path):
    # the replay writer's process builds the screen the replay opens on; the race's process never loads rerun
    path = tmp_path / "r.rrd"
    script = ("import sys; from multirace.cli import main; "
              f"code = main(['race', 'bot:follow@2.0', 'bot:lanes@1.5', '--laps', '1', '--replay', {str(path)!r}]); "
              "print('rerun loaded' if any(m.split('.')[0] == 'rerun' for m in sys.modules) else 'no rerun'); "
              "sys.exit(code)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == "no rerun"
    assert view_origins(path) == ["cameras/car_0", "cameras/car_1", "events", "plots/progress", "plots/rank",
                                  "plots/reward", "plots/speed", "plots/standing", "world"]


def test_replays_in_a_row_share_one_writer_process(tmp_path):
    recorders = [ReplayRecorder(tmp_path / f"{k}.rrd") for k in range(2)]
    writers = []
    for recorder in recorders:
        watch = Act("bot:follow@1.5", 5, lambda car: writers.append(recorder._writer.process.pid))
        run_race([watch], RaceConfig(laps=1, max_steps=40), recorders=[recorder])
    assert writers[0] == writers[1]
    assert [replay_summary(tmp_path / f"{k}.rrd")["steps"] for k in range(2)] == [40, 40]


@pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="Linux's scheduling policies")
def test_the_writer_and_its_threads_yield_the_core_to_the_race(tmp_path):
    """The writer (and every thread it started: rerun's own) runs under SCHED_BATCH, so the blocks a race sends
    it do not take the race's core (replay_process, "The writer yields its core"); the race runs as it did."""
    recorder = ReplayRecorder(tmp_path / "race.rrd")
    policies = []

    def look(car):
        tasks = f"/proc/{recorder._writer.process.pid}/task"
        policies.extend(os.sched_getscheduler(int(tid)) for tid in os.listdir(tasks))

    run_race([Act("bot:follow@1.5", 100, look)], RaceConfig(laps=3, max_steps=240), recorders=[recorder])
    assert len(policies) > 1 and set(policies) == {os.SCHED_BATCH}, policies
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert replay_summary(tmp_path / "race.rrd")["steps"] == 240


def test_a_writer_that_fails_is_an_error_naming_the_file_and_the_old_file_stays(tmp_path):
    path = tmp_path / "race.rrd"
    path.write_bytes(b"the previous replay")
    recorder = ReplayRecorder(path)
    bad = np.zeros((8, 8, 7), np.uint8)  # seven channels: no JPEG, the writer's cv2 raises
    car = Act("bot:follow@1.5", 20, lambda car: recorder.log_image("explain/car_0", 20, 1.0, bad))
    with pytest.raises(OutputError, match="race.rrd: not written .*the replay writer failed"):
        run_race([car], RaceConfig(laps=1, max_steps=200), recorders=[recorder])
    assert path.read_bytes() == b"the previous replay" and leftovers(tmp_path) == []


def test_a_killed_writer_is_an_error_naming_the_file_and_the_next_replay_gets_a_new_one(tmp_path):
    path = tmp_path / "race.rrd"
    recorder = ReplayRecorder(path)
    killed = []

    def kill(car):
        killed.append(recorder._writer.process.pid)
        os.kill(killed[0], signal.SIGKILL)

    with pytest.raises(OutputError, match="race.rrd: not written .*killed by signal 9"):
        run_race([Act("bot:follow@1.5", 20, kill)], RaceConfig(laps=1, max_steps=200), recorders=[recorder])
    assert not path.exists() and leftovers(tmp_path) == [] and ended(killed[0])
    run_race([make_controller("bot:follow@1.5")], RaceConfig(laps=1, max_steps=30), recorders=[ReplayRecorder(path)])
    assert replay_summary(path)["steps"] == 30


@pytest.mark.parametrize("error", [KeyboardInterrupt, RuntimeError])
def test_a_race_that_fails_stops_its_writer_and_leaves_no_file(tmp_path, error):
    path, recorder, writer = tmp_path / "race.rrd", None, []

    def fail(car):
        writer.append(recorder._writer.process.pid)
        raise error("stop")

    recorder = ReplayRecorder(path)
    with pytest.raises(error):
        run_race([Act("bot:follow@1.5", 40, fail)], RaceConfig(laps=1, max_steps=200), recorders=[recorder])
    assert ended(writer[0]) and not path.exists() and leftovers(tmp_path) == []


def test_a_writer_ends_when_the_race_process_is_killed(tmp_path):
    code = ("import os, signal, sys\n"
            "from multirace.racing.runner import RaceConfig, make_controller, run_race\n"
            "from multirace.recording.replay import ReplayRecorder\n"
            f"recorder = ReplayRecorder({str(tmp_path / 'race.rrd')!r})\n"
            "class Die:\n"
            "    def start(self, env): pass\n"
            "    def step(self, env, *args):\n"
            "        if env.steps == 30:\n"
            "            print(recorder._writer.process.pid, flush=True)\n"
            "            os.kill(os.getpid(), signal.SIGKILL)\n"
            "run_race([make_controller('bot:follow@1.5')], RaceConfig(laps=1, max_steps=200),\n"
            "         recorders=[recorder, Die()])\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == -signal.SIGKILL, done.stderr[-2000:]
    writer = int(done.stdout.split()[0])
    deadline = time.monotonic() + 20
    while not ended(writer) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert ended(writer)
