"""The process a reward file runs in (`python -m multirace.environment.reward_worker`, see `serve`).

A reward file is the user's own code: it may read files and open sockets, and
nothing here stops that. What this process contains is its reach into a run:
it holds no env, no learner and no signal handler of the run's, so what the
function does to its interpreter (a KeyboardInterrupt, a thread that never
ends, SIGALRM ignored, `os._exit`, `os.fork`, `math.isfinite` replaced, a walk
up the call stack) stays here. The run's side (`reward_process`) keeps the
time limit, checks every value it is sent and ends this process when it is
done with it.

Protocol: the run writes frames (a 4-byte big-endian length, then a pickle of
``{"params": [dict, ...], "constant": {key: value} or absent}``; the
constant params, such as the waypoints, are sent when they change and merged
into every call's params). This process writes one JSON line per frame,
``{"values": [float, ...]}`` with, where a call failed (the batch ends there),
``"error": what, "detail": text``; and one line after loading the file,
``{"loaded": true}`` or an error. Before each call it writes the car's index
into the shared progress word (PROGRESS_FD), so the run can name the car whose
call overran without a message per call.
"""
from __future__ import annotations

import importlib.util
import json
import mmap
import numbers
import os
import pickle
import struct
import sys

DETAIL_LIMIT = 300  # characters of an exception's text passed back
PROGRESS_BYTES = 4  # the shared word holding the index of the call in progress


def _die_with_parent() -> None:
    """Ask Linux to end this process when the run that started it ends (best effort elsewhere)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _read_exactly(fd: int, size: int) -> bytes:
    chunks, left = [], size
    while left:
        chunk = os.read(fd, left)
        if not chunk:
            raise EOFError
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _failure(exc: BaseException) -> dict:
    """A reply naming what the code did: called sys.exit, or raised (any exception, KeyboardInterrupt too)."""
    if isinstance(exc, SystemExit):
        return {"error": f"called sys.exit({exc.code!r})", "detail": ""}
    text = f"{type(exc).__name__}: {exc}"
    return {"error": "raised", "detail": ": " + text[:DETAIL_LIMIT]}


def _as_reply(value) -> dict:
    """A returned value as a reply: any real number but a bool, as a float."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return {"error": f"returned {repr(value)[:80]}",
                "detail": f"; expected a number (DeepRacer requires a float), not a {type(value).__name__}"}
    try:
        return {"value": float(value)}
    except OverflowError:
        return {"error": "returned a number too large for a float", "detail": ""}
    except Exception as exc:
        return _failure(exc)


def _load(path: str):
    """The file's reward_function, or a reply saying why there is none."""
    spec = importlib.util.spec_from_file_location("reward_function_file", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["reward_function_file"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException as exc:
        failure = _failure(exc)
        if failure["error"] == "raised":
            failure["error"] = "cannot be loaded"
        return None, failure
    function = getattr(module, "reward_function", None)
    if not callable(function):
        return None, {"error": "defines no reward_function(params)", "detail": ""}
    return function, {"loaded": True}


def _call(function, params: dict) -> dict:
    try:
        return _as_reply(function(params))
    except BaseException as exc:
        return _failure(exc)


def serve(read_fd: int, write_fd: int, progress_fd: int, path: str) -> None:
    """Load `path`, then answer each frame of params with one reply line, until the run closes the pipe. A
    copy of this process made by the function (`os.fork`) ends before it can reply."""
    pid = os.getpid()
    out = os.fdopen(write_fd, "w", buffering=1)
    progress = mmap.mmap(progress_fd, PROGRESS_BYTES)

    def reply(message: dict) -> None:
        if os.getpid() != pid:  # a fork the function made: it must not answer, nor run anything of ours
            os._exit(0)
        out.write(json.dumps(message) + "\n")

    function, loaded = _load(path)
    reply(loaded)
    if function is None:
        return
    constant: dict = {}
    while True:
        try:
            header = _read_exactly(read_fd, 4)
            message = pickle.loads(_read_exactly(read_fd, struct.unpack(">I", header)[0]))
        except EOFError:
            return
        constant.update(message.get("constant", {}))
        values = []
        result = {"values": values}
        for k, params in enumerate(message["params"]):
            params.update({key: value[:] if type(value) is list else value for key, value in constant.items()})
            struct.pack_into(">I", progress, 0, k)
            outcome = _call(function, params)
            if "error" in outcome:  # the batch ends at its first error
                result.update(outcome)
                break
            values.append(outcome["value"])
        reply(result)


if __name__ == "__main__":
    import signal

    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's to handle; it then ends this process
    try:
        serve(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    except BaseException:  # the run is gone (a broken pipe) or the function broke this process: end quietly
        pass
    finally:
        os._exit(0)  # threads the function started must not keep this process alive
