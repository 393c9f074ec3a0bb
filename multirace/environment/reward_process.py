"""Loading reward functions; a reward file runs in a process of its own (`reward_worker`), one batch of
calls per env step.

The run keeps everything that decides the outcome: a hard time limit per call
(the process is killed when a call overruns it: the function cannot disarm
the run's clock), the check that each value is a finite number in range
(with the run's own `math`), and a clear error when the process dies (exit,
`os._exit`, a crash). The function sees only its params: the env, the
learner and their call stack are in another process. A call costs one pipe
round trip per env step for all cars (a pickle down, a JSON line back; the
worker publishes which call it is in through a shared word, so an overrun
names its car); the constant params (the waypoints) are sent once per track.

`load_reward_function` gives the RewardFunction for None (the console's default), a Python callable (both
in-process, see `rewards`) or a reward file (a `RewardProcess`).
"""
from __future__ import annotations

import json
import mmap
import os
import pickle
import select
import struct
import subprocess
import sys
import time
import weakref
from pathlib import Path

from . import rewards
from .rewards import BuiltInReward, RewardFunction, RewardFunctionError, follow_centre_line

CONSTANT_KEYS = ("waypoints",)  # params that stay the same for a track: sent when they change
EXIT_WAIT = 2.0  # seconds a worker whose pipe closed has to end before it is ended
STARTUP_SLACK = 5.0  # seconds for the interpreter to start, on top of the file's load time limit
REPLY_LIMIT = 1 << 16  # bytes of one reply line; a longer one is malformed
PROGRESS_BYTES = 4  # the shared word where the worker publishes the index of the call in progress
PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])


def _stop(process: subprocess.Popen, fds: list) -> None:
    """End the worker (it holds nothing of the run's) and close the run's ends of its pipes."""
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass
    if process.poll() is None:
        process.kill()
    process.wait()


def _well_formed(reply) -> bool:
    """A reply the worker may send: loaded, or values (floats), either with an error and its detail."""
    if not isinstance(reply, dict):
        return False
    error = "error" not in reply or isinstance(reply["error"], str) and isinstance(reply.get("detail"), str)
    values = reply.get("values")
    return error and ("loaded" in reply or "error" in reply and "values" not in reply or
                      isinstance(values, list) and all(type(v) is float for v in values))


class RewardProcess(RewardFunction):
    """`RewardFunction` for a reward file: the same calls and errors, the function in its own process."""

    def __init__(self, path):
        super().__init__(None, str(path))
        self._process = None
        self._pid = None
        self._sent = {}  # constant key -> the object last sent
        self._start()

    # ------------------------------------------------------------ the process
    def _start(self) -> None:
        to_worker, from_run = os.pipe()
        from_worker, to_run = os.pipe()
        progress = os.memfd_create("multirace-reward-progress")
        os.ftruncate(progress, PROGRESS_BYTES)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [PACKAGE_ROOT, os.environ.get("PYTHONPATH")])))
        process = subprocess.Popen(
            [sys.executable, "-m", "multirace.environment.reward_worker", str(to_worker), str(to_run), str(progress),
             self.label], pass_fds=(to_worker, to_run, progress), stdin=subprocess.DEVNULL, env=env)
        os.close(to_worker)
        os.close(to_run)
        self._progress = mmap.mmap(progress, PROGRESS_BYTES)
        os.close(progress)
        self._process, self._pid, self._sent = process, os.getpid(), {}
        self._write_fd, self._read_fd, self._buffer = from_run, from_worker, b""
        self._finalizer = weakref.finalize(self, _stop, process, [from_run, from_worker])
        try:
            reply = self._reply(rewards.LOAD_TIME_LIMIT + STARTUP_SLACK)
        except TimeoutError:
            self.close()
            raise RewardFunctionError(f"reward function file {self.label}: loading it did not finish within "
                                      f"{rewards.LOAD_TIME_LIMIT:g} s") from None
        except EOFError:
            raise RewardFunctionError(f"reward function file {self.label}: {self._death()} when loaded") from None
        if "loaded" not in reply:
            self.close()
            raise RewardFunctionError(f"reward function file {self.label}: {reply['error']}"
                                      f"{' when loaded' if 'exit' in reply['error'] else ''}{reply['detail']}")

    def close(self) -> None:
        """End the worker process; the next call starts a new one."""
        if self._process is not None and self._pid == os.getpid():
            self._finalizer()
        self._process = None

    def _death(self) -> str:
        """What became of a worker whose pipe closed (one that closed it and lives on is ended)."""
        try:
            code = self._process.wait(timeout=EXIT_WAIT)
        except subprocess.TimeoutExpired:
            code = None
        self.close()
        if code is None:
            return "closed its pipe to the run (its process was ended)"
        return f"was killed by signal {-code}" if code < 0 else f"ended its process (exit status {code})"

    def _reply(self, seconds: float) -> dict:
        """The worker's next reply line; TimeoutError after `seconds`, EOFError if it died, a malformed reply
        as an error reply."""
        deadline = time.monotonic() + seconds
        while b"\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._read_fd], [], [], left)[0]:
                raise TimeoutError
            chunk = os.read(self._read_fd, REPLY_LIMIT)
            if not chunk:
                raise EOFError
            self._buffer += chunk
            if len(self._buffer) > REPLY_LIMIT:
                return {"values": [], "error": "wrote a malformed reply", "detail": " (over 64 KiB)"}
        line, self._buffer = self._buffer.split(b"\n", 1)
        try:
            reply = json.loads(line)
            if _well_formed(reply):
                return reply
        except (ValueError, RecursionError):
            pass
        return {"values": [], "error": "wrote a malformed reply", "detail": f": {line[:80]!r}"}

    def _batch_reply(self) -> dict:
        """The reply to a batch: each call may take `CALL_TIME_LIMIT` (the worker publishes which call it is
        in), TimeoutError when one overruns it."""
        limit = rewards.CALL_TIME_LIMIT
        current, deadline = 0, time.monotonic() + limit
        while True:
            try:
                return self._reply(deadline - time.monotonic())
            except TimeoutError:
                if self._call_in_progress() == current:
                    raise
                current, deadline = self._call_in_progress(), time.monotonic() + limit

    def _call_in_progress(self) -> int:
        return struct.unpack_from(">I", self._progress, 0)[0]

    def _send(self, params_list: list) -> None:
        message = {"params": []}
        constant = {}
        for params in params_list:
            for key in CONSTANT_KEYS:
                if key in params and params[key] is not self._sent.get(key):
                    constant[key] = self._sent[key] = params[key]
            message["params"].append({key: value for key, value in params.items() if key not in CONSTANT_KEYS})
        if constant:
            message["constant"] = constant
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        data = memoryview(struct.pack(">I", len(data)) + data)
        while data:
            data = data[os.write(self._write_fd, data):]

    # ------------------------------------------------------------ calls
    def rewards(self, params_list: list, step: int, cars: list) -> list:
        """The function's values for each car's params at `step` (one round trip); RewardFunctionError naming
        the file, step and car on any failure, the worker killed on a call that overruns the time limit."""
        if self._process is None or self._pid != os.getpid():  # closed, or this is a forked copy of the run
            self._start()
        struct.pack_into(">I", self._progress, 0, 0)
        try:
            self._send(params_list)
            reply = self._batch_reply()
        except TimeoutError:
            car = cars[min(self._call_in_progress(), len(cars) - 1)]
            self.close()
            raise self._error(f"did not return within {rewards.CALL_TIME_LIMIT:g} s", step, car) from None
        except (EOFError, OSError):
            car = cars[min(self._call_in_progress(), len(cars) - 1)]
            raise self._error(self._death(), step, car) from None
        values = reply["values"]
        if "error" not in reply and len(values) != len(cars):
            reply.update(error="wrote a malformed reply", detail=f" ({len(values)} values for {len(cars)} cars)")
        if "error" in reply:
            if reply["error"] == "wrote a malformed reply":
                self.close()
            raise self._error(reply["error"], step, cars[min(len(values), len(cars) - 1)], reply["detail"])
        return [self._checked(value, step, car) for value, car in zip(values, cars)]

    def __call__(self, params: dict, step: int, car: str) -> float:
        return self.rewards([params], step, [car])[0]

    def __getstate__(self):
        return {"label": self.label}

    def __setstate__(self, state):
        self.__init__(state["label"])


def load_reward_function(spec=None) -> RewardFunction:
    """A RewardFunction from None (the console default), a callable, or a path to a `.py` file."""
    if spec is None:
        return BuiltInReward(follow_centre_line, "follow_centre_line (default)")
    if isinstance(spec, RewardFunction):
        return spec
    if spec is follow_centre_line:  # `--reward centre`
        return BuiltInReward(follow_centre_line, "follow_centre_line")
    if callable(spec):
        return RewardFunction(spec, getattr(spec, "__name__", repr(spec)))
    path = Path(spec)
    if not path.is_file():
        raise RewardFunctionError(f"reward function file {path}: no such file")
    return RewardProcess(path)
