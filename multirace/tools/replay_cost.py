"""What recording a replay costs a race: the same 4-car race with and without a `ReplayRecorder`."""
from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

from ..racing.runner import RaceConfig, make_controller, run_race
from ..recording.replay import DEFAULT_IMAGE_EVERY, ReplayRecorder


def replay_cost(seconds: float = 240.0, image_every: int | None = DEFAULT_IMAGE_EVERY, path=None,
                track: str = "reinvent_base", repeats: int = 2) -> dict:
    """Measure a 4-car reset_rule race of `seconds` race time with and without a replay.

    Returns {"replay_mb", "race_wall_s", "race_with_replay_wall_s", "overhead_percent" (wall clock),
    "speed_loss_percent" (race steps/s lost), "race_cpu_s", "race_with_replay_cpu_s", "overhead_cpu_percent"
    (CPU time of the process, all threads, plus what the replay writer's process spent on the replay),
    "recorder_s" / "recorder_percent" (wall time inside the recorder's calls, against the plain race),
    "steps", "image_every"}; the best of `repeats` runs each. A short race is recorded first: the replay
    writer's process starts once per process (an interpreter importing rerun), not once per race.
    """
    bots = ("bot:follow@1.5", "bot:lanes@1.0", "bot:follow@1.0", "bot:lanes@1.5")
    config = RaceConfig(track=track, race="reset_rule", laps=1000, seed=0, max_steps=int(round(seconds * 15)))

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(path) if path is not None else Path(tmp) / "cost.rrd"
        run_race([make_controller(b) for b in bots], dataclasses.replace(config, max_steps=15),
                 recorders=[ReplayRecorder(out, image_every)])  # the one-off costs: the writer's start, imports
        plain, recorded, plain_cpu, recorded_cpu, in_recorder = [], [], [], [], []
        for _ in range(max(1, repeats)):
            start, cpu = time.perf_counter(), time.process_time()
            run_race([make_controller(b) for b in bots], config)
            plain.append(time.perf_counter() - start)
            plain_cpu.append(time.process_time() - cpu)
            start, cpu = time.perf_counter(), time.process_time()
            recorder = _TimedRecorder(out, image_every)
            run_race([make_controller(b) for b in bots], config, recorders=[recorder])
            recorded.append(time.perf_counter() - start)
            in_recorder.append(recorder.seconds)
            recorded_cpu.append(time.process_time() - cpu + recorder.writer_cpu_s)
        size = out.stat().st_size
    base, rec = min(plain), min(recorded)
    base_cpu, rec_cpu = min(plain_cpu), min(recorded_cpu)
    return {"replay_mb": round(size / 1e6, 2), "race_wall_s": round(base, 3), "race_with_replay_wall_s": round(rec, 3),
            "overhead_percent": round(100.0 * (rec - base) / base, 1),
            "speed_loss_percent": round(100.0 * (1.0 - base / rec), 1),  # race steps/s lost to recording
            "race_cpu_s": round(base_cpu, 3), "race_with_replay_cpu_s": round(rec_cpu, 3),
            "overhead_cpu_percent": round(100.0 * (rec_cpu - base_cpu) / base_cpu, 1),
            "recorder_s": round(min(in_recorder), 3),
            "recorder_percent": round(100.0 * min(in_recorder) / base, 1),
            "steps": config.max_steps, "image_every": image_every}


class _TimedRecorder(ReplayRecorder):
    """A ReplayRecorder that adds up the wall time spent in its own calls."""

    seconds = 0.0

    def _timed(self, method, *args):
        start = time.perf_counter()
        method(*args)
        self.seconds += time.perf_counter() - start

    def start(self, env):
        self._timed(super().start, env)

    def step(self, env, observations, rewards, infos):
        self._timed(super().step, env, observations, rewards, infos)

    def finish(self, env, result):
        self._timed(super().finish, env, result)
