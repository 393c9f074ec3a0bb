"""What recording a replay costs a race: the same 4-car race with and without a `ReplayRecorder`, run in turns.

The two races run side by side, each in a thread of its own, taking turns of `TURN_STEPS` steps (one runs
while the other waits; which one starts alternates from pair to pair), and each turn's wall time is charged
to the race that ran it. Both threads are bound to one core (where the system can bind threads), so that
neither races on a core the other does not get. A slow patch of the machine (another process, a busy host)
then hits both races alike, as `bench`'s interleaved windows do for its env figures: timing the two races
one after the other, the same code measured anywhere from -1 % to -23 % on one noisy machine within
minutes, and two plain races in turns on cores of their own differed by up to 15 % (by up to 9 %, most
within 3 %, on one core). The replay writer's process is stopped (SIGSTOP) while the plain race takes its
turn and goes on (SIGCONT) with the recorded race's: it works, as in any recorded race, only while that
race runs, so that its work slows that race (where the two share a core, or its caches), not the plain one.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import statistics
import tempfile
import threading
import time
from pathlib import Path

from ..racing.runner import RaceConfig, make_controller, run_race
from ..recording.replay import DEFAULT_IMAGE_EVERY, ReplayRecorder

TURN_STEPS = 90  # steps a race runs before the other takes its turn (about 20 ms)
BOTS = ("bot:follow@1.5", "bot:lanes@1.0", "bot:follow@1.0", "bot:lanes@1.5")


def replay_cost(seconds: float = 240.0, image_every: int | None = DEFAULT_IMAGE_EVERY, path=None,
                track: str = "reinvent_base", repeats: int = 2, turn_steps: int = TURN_STEPS) -> dict:
    """Measure a 4-car reset_rule race of `seconds` race time with and without a replay, `repeats` times, the
    two races in turns (`turn_steps` steps each) every time.

    Returns {"replay_mb", "race_wall_s", "race_with_replay_wall_s", "overhead_percent" (wall clock),
    "speed_loss_percent" (race steps/s lost), "race_cpu_s", "race_with_replay_cpu_s", "overhead_cpu_percent"
    (CPU time of the race's thread, plus what the replay writer's process spent on the replay),
    "recorder_s" / "recorder_percent" (wall time inside the recorder's calls, against the plain race),
    "steps", "image_every", "turn_steps", "pairs" (each pair's speed loss, %)}: each race's time runs from
    the recorder's start (the env built and reset) to the end of its finish (the replay complete on disk);
    the figures are the medians over the pairs. A short race is recorded first: the replay writer's
    process starts once per process (an interpreter importing rerun), not once per race.
    """
    config = RaceConfig(track=track, race="reset_rule", laps=1000, seed=0, max_steps=int(round(seconds * 15)))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(path) if path is not None else Path(tmp) / "cost.rrd"
        run_race([make_controller(b) for b in BOTS], dataclasses.replace(config, max_steps=15),
                 recorders=[ReplayRecorder(out, image_every)])  # the one-off costs: the writer's start, imports
        pairs = [_race_pair(config, out, image_every, turn_steps, first=k % 2) for k in range(max(1, repeats))]
        size = out.stat().st_size
    plain, recorded = (statistics.median(pair[k].seconds for pair in pairs) for k in (0, 1))
    plain_cpu, recorded_cpu = (statistics.median(pair[k].cpu_seconds for pair in pairs) for k in (0, 1))
    losses = [100.0 * (1.0 - plain_turns.seconds / recorded_turns.seconds) for plain_turns, recorded_turns in pairs]
    in_recorder = statistics.median(pair[1].inner.seconds for pair in pairs)
    return {"replay_mb": round(size / 1e6, 2), "race_wall_s": round(plain, 3),
            "race_with_replay_wall_s": round(recorded, 3),
            "overhead_percent": round(100.0 * (recorded - plain) / plain, 1),
            "speed_loss_percent": round(statistics.median(losses), 1),  # race steps/s lost to recording
            "race_cpu_s": round(plain_cpu, 3), "race_with_replay_cpu_s": round(recorded_cpu, 3),
            "overhead_cpu_percent": round(100.0 * (recorded_cpu - plain_cpu) / plain_cpu, 1),
            "recorder_s": round(in_recorder, 3), "recorder_percent": round(100.0 * in_recorder / plain, 1),
            "steps": config.max_steps, "image_every": image_every, "turn_steps": turn_steps,
            "pairs": [round(loss, 1) for loss in losses]}


def _race_pair(config: RaceConfig, out: Path, image_every: int | None, turn_steps: int, first: int) -> tuple:
    """The race without and with a replay of `out`, run in turns (`first`: 0 the plain race's turn comes
    first, 1 the recorded one's), both on one core; their `_Turns` (time, CPU time, results)."""
    baton = _Baton()
    core = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    plain = _Turns(baton, first, turn_steps)
    recorded = _Turns(baton, 1 - first, turn_steps, _TimedRecorder(out, image_every))
    threads = [threading.Thread(target=turns.run, args=(config, core), name=f"race {turns.me}")
               for turns in (plain, recorded)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for turns in (plain, recorded):
        if turns.error is not None:
            raise turns.error
    return plain, recorded


class _Baton:
    """Whose turn it is, of two races; a race that has ended hands the baton over for good."""

    def __init__(self):
        self._condition = threading.Condition()
        self._owner = 0
        self._ended = [False, False]
        self._set_up = threading.Barrier(2)  # both races' envs built before the first turn

    def first_take(self, me: int) -> None:
        """`take`, once both races are set up (or the other has ended before it was): no turn is timed while
        the other race's thread builds its env."""
        try:
            self._set_up.wait()
        except threading.BrokenBarrierError:  # the other race failed before its start
            pass
        self.take(me)

    def take(self, me: int) -> None:
        """Wait until it is race `me`'s turn (or the other race has ended)."""
        with self._condition:
            self._condition.wait_for(lambda: self._owner == me or self._ended[1 - me])

    def give(self, me: int, ended: bool = False) -> None:
        """Race `me` hands the turn to the other (`ended`: and takes no more turns)."""
        if ended:
            self._set_up.abort()  # (a race that never reached its start releases the other)
        with self._condition:
            self._owner = 1 - me
            self._ended[me] = self._ended[me] or ended
            self._condition.notify_all()


class _Turns:
    """A race's side of the turns, as a recorder of it (wrapping `inner`, the recorder measured, if any): it
    runs `turn_steps` steps per turn and adds up the wall and CPU time of its turns."""

    def __init__(self, baton: _Baton, me: int, turn_steps: int, inner=None):
        self.baton, self.me, self.turn_steps, self.inner = baton, me, turn_steps, inner
        self.seconds = self.cpu_seconds = 0.0
        self.result, self.error = None, None
        self._steps = 0

    def run(self, config: RaceConfig, core: int | None) -> None:
        """The race, in turns, on `core` (None: any) (its thread's target); an error is kept for the caller and
        ends its turns."""
        try:
            if core is not None:
                os.sched_setaffinity(0, {core})  # (this thread only)
            self.result = run_race([make_controller(b) for b in BOTS], config, recorders=[self])
        except BaseException as exc:  # noqa: BLE001 - raised again by the caller, in its thread
            self.error = exc
        finally:
            self.baton.give(self.me, ended=True)

    def start(self, env) -> None:
        self.baton.first_take(self.me)
        self._begin_turn()
        if self.inner is not None:
            self.inner.start(env)

    def step(self, env, observations, rewards, infos) -> None:
        if self.inner is not None:
            self.inner.step(env, observations, rewards, infos)
        self._steps += 1
        if self._steps % self.turn_steps == 0:
            self._end_turn()
            self.baton.give(self.me)
            self.baton.take(self.me)
            self._begin_turn()

    def finish(self, env, result) -> None:
        if self.inner is not None:
            self.inner.finish(env, result)  # (the writer, done with this replay, is no longer stopped)
        self._end_turn()
        if self.inner is not None:
            self.cpu_seconds += self.inner.writer_cpu_s

    def discard(self) -> None:
        if self.inner is not None:
            self.inner.discard()  # (ends the writer, stopped or not)

    def _begin_turn(self) -> None:
        if self.inner is not None:
            self.inner.writer_signal(signal.SIGCONT)
        self._wall, self._cpu = time.perf_counter(), time.thread_time()

    def _end_turn(self) -> None:
        self.seconds += time.perf_counter() - self._wall
        self.cpu_seconds += time.thread_time() - self._cpu
        if self.inner is not None:
            self.inner.writer_signal(signal.SIGSTOP)


class _TimedRecorder(ReplayRecorder):
    """A ReplayRecorder that adds up the wall time spent in its own calls, and whose writer process can be
    stopped and continued while it records."""

    seconds = 0.0

    def writer_signal(self, signum: int) -> None:
        """Send `signum` to the writer's process while it records this replay (nothing before or after)."""
        if self._writer is not None:
            os.kill(self._writer.process.pid, signum)

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
