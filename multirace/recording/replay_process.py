"""The replay writer's process and the link to it: a race hands its recorded data over and goes on.

`WriterProcess.begin(file_fd, target)` gives a process running `replay_writer.serve` that writes one
replay into the open file `file_fd` (the temporary file of `target`). Each recording begins with one byte
that carries the file's descriptor (SCM_RIGHTS); then messages go as frames on a socket (`frame`: the
pickle, and the bytes of the numpy arrays in it beside it, out of band, so that they are copied only
once, by the kernel):

- the camera images the writer does not draw itself (`scene_cameras`) go through shared memory
  (`arena.ImageArena`, made with the writer and mapped by it):
  `carry(images)` copies a step's images there and gives the small record of where they lie, which the
  message carries instead of them (images the arena has no room for yet go in the message themselves);
- `send(message)` does not wait for the writer: what the socket cannot take yet waits in memory and goes
  out with the next message (the race waits only when more than BACKLOG_BYTES wait), so the race keeps its
  core while the writer encodes images and builds columns on another;
- `finish(message)` sends the last message and waits for the writer's answer: ``("done", cpu seconds it
  spent on the file)`` once the file is complete, or ``("error", reason)``, raised as an `OutputError`
  naming the target; a writer that ended without answering (killed, crashed) is the same error, with its
  exit status;
- `stop()` ends the writer at once (a race that failed or was interrupted).

A writer that completed a file waits for this process's next recording: starting an interpreter and
importing rerun and the renderer costs a second or two of CPU, paid once per process (`prepare` starts one
ahead, while a race is set up). A writer that failed or was stopped is not used again. Idle writers end
with this process: at exit, and by themselves when their socket closes (this process ended any other way).

The writer is a fresh interpreter (`subprocess`, as multiprocessing's 'spawn'), not a fork: the race's
process has threads (numba, torch, PyBullet, rerun's own) and a fork of a threaded process may hang on a
lock another thread held. It is not multiprocessing's 'spawn' either, which imports the caller's main
script again in the child (a script without an ``if __name__ == "__main__"`` guard would run its race
twice). The child gets the parent's `sys.path`, so it imports the same multirace (a wheel or a source tree,
whatever the working folder holds), and ignores SIGINT: Ctrl-C reaches the race, which stops the writer.

The writer yields its core: it runs under Linux's SCHED_BATCH policy (its threads too), so a message that
wakes it does not take the race's core from the race; the scheduler runs it on another core, or when the
race's time slice ends. Under the default policy, each block sent woke the writer onto the race's core for
its JPEG encoding: on a machine busy with other work the send took 2-3 ms instead of 0.1 ms (README,
performance). (Elsewhere, where the policy does not exist, the writer runs as any process.)
"""
from __future__ import annotations

import itertools
import json
import os
import pickle
import select
import socket
import struct
import subprocess
import sys
import weakref
from collections import deque

import numpy as np

from ..atomic import OutputError, output_error
from .arena import ImageArena

HEADER = struct.Struct("!QQ")  # the length of the pickle that follows, and how many buffers follow it
LENGTH = struct.Struct("!Q")  # the length of each buffer (all of them before the pickle)
BACKLOG_BYTES = 64 << 20  # bytes waiting for the writer beyond which the race waits for it
SOCKET_BYTES = 4 << 20  # the socket's send buffer asked for (the system may give less): fewer, larger writes
ARENA_BYTES = 8 << 20  # shared memory for the images on their way to the writer (about 400 grey frames)
ANSWER_TIMEOUT = 300.0  # seconds the writer may go without reading or answering before it is taken for hung
EXIT_WAIT = 5.0  # seconds a failed writer has to answer or end before it is ended
BOOT = ("import json, os, signal, sys\n"
        "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "try:\n"  # see "The writer yields its core"
        "    os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))\n"
        "except (AttributeError, OSError):\n"
        "    pass\n"
        "sys.path[:] = json.loads(sys.argv[1])\n"
        "from multirace.recording.replay_writer import serve\n"
        "serve(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]))\n")
_idle: list = []  # this process's writers that wait for a recording


def prepare() -> None:
    """Start a writer ahead of the next recording, unless one is waiting already."""
    if not any(writer.usable() for writer in _idle):
        _idle.append(WriterProcess())


def _end(process: subprocess.Popen, sock: socket.socket, arena: ImageArena, pid: int) -> None:
    """Close the socket and the image arena and end the writer (it holds nothing a race still needs); a fork
    of the process that started it only closes its copies of them."""
    sock.close()
    arena.close()
    if os.getpid() == pid:
        if process.poll() is None:
            process.kill()
        process.wait()


class WriterProcess:
    """A replay writer's process; one recording at a time (`begin`), its errors naming that recording's
    target."""

    def __init__(self):
        ours, theirs = socket.socketpair()
        try:
            self.arena = ImageArena.create(ARENA_BYTES)
        except BaseException:
            ours.close()
            theirs.close()
            raise
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-c", BOOT, json.dumps(sys.path), str(theirs.fileno()), str(self.arena.fd),
                 str(self.arena.size)], pass_fds=(theirs.fileno(), self.arena.fd), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            self.arena.close()
            raise
        finally:
            theirs.close()
        ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BYTES)
        self.target, self._pid, self._sock = None, os.getpid(), ours
        self.cpu_seconds = 0.0  # CPU time the writer spent on its last complete recording
        self._backlog: deque = deque()  # memoryviews not yet written, in order
        self._waiting = 0  # their bytes
        self._stop = weakref.finalize(self, _end, self.process, ours, self.arena, self._pid)

    @classmethod
    def begin(cls, file_fd: int, target) -> WriterProcess:
        """A writer (one that waits, or a new one) recording into `file_fd`; an OutputError naming `target`
        where none can be started."""
        while _idle:
            writer = _idle.pop()
            if writer.usable():
                try:
                    writer._begin(file_fd, target)
                    return writer
                except OSError:  # it ended while it waited
                    writer.stop()
        try:
            writer = cls()
            writer._begin(file_fd, target)
        except OSError as exc:
            raise output_error(target, exc) from None
        return writer

    def usable(self) -> bool:
        """Whether this writer belongs to this process and runs (a fork's copy does not)."""
        return self._pid == os.getpid() and self._stop.alive and self.process.poll() is None

    def carry(self, images: list[np.ndarray]) -> tuple | np.ndarray:
        """`images` (of one shape and dtype) as a message takes them to the writer: where they lie in the shared
        arena, after a copy there (an `ArenaImage` as a plain tuple: a block's dozens of them pickle several
        times faster so), or (no room there now) a copy of their own, sent through the socket."""
        images = [np.ascontiguousarray(image) for image in images]
        where = self.arena.put(images)
        return tuple(where) if where is not None else np.stack(images)

    def send(self, message) -> None:
        """Hand `message` to the writer (its arrays must not change afterwards: they are sent as they are,
        maybe later); raises the writer's error if it has failed."""
        parts = [part for part in frame(message) if len(part)]  # (an empty array has no bytes to send)
        self._backlog.extend(parts)
        self._waiting += sum(len(part) for part in parts)
        self._write(wait=self._waiting > BACKLOG_BYTES)
        try:
            self._sock.recv(1, socket.MSG_PEEK)
        except BlockingIOError:  # no answer (nor end): the writer is at work
            return
        raise self._failure()  # it answers early only when it failed

    def finish(self, message) -> None:
        """Send the last message and wait until the writer has written the file completely; the writer
        then waits for this process's next recording."""
        self.send(message)
        self._write(wait=True)
        self._wait(select.POLLIN, "did not answer")
        answer = self._answer(ANSWER_TIMEOUT)
        if not (isinstance(answer, tuple) and len(answer) == 2 and answer[0] == "done"):
            raise self._failure(answer)
        self.cpu_seconds = answer[1]
        _idle.append(self)

    def stop(self) -> None:
        """End the writer now (nothing more is written)."""
        self._stop()

    def _begin(self, file_fd: int, target) -> None:
        self.target = target
        self._sock.setblocking(True)
        socket.send_fds(self._sock, [b"F"], [file_fd])
        self._sock.setblocking(False)

    def _write(self, wait: bool) -> None:
        """Write what waits to the socket, as far as it takes it without waiting (all of it, with `wait`)."""
        while self._backlog:
            try:
                sent = self._sock.sendmsg(itertools.islice(self._backlog, 256))
            except BlockingIOError:
                if not wait:
                    return
                self._wait(select.POLLOUT, "took no data")
                continue
            except OSError:  # the writer has gone (a broken pipe, a reset): its answer says why
                raise self._failure() from None
            self._waiting -= sent
            while sent:
                head = self._backlog[0]
                if len(head) > sent:
                    self._backlog[0] = head[sent:]
                    break
                sent -= len(head)
                self._backlog.popleft()

    def _wait(self, event: int, what: str) -> None:
        """Wait until the socket is ready for `event` (or the writer has gone); a writer that leaves it
        unready for ANSWER_TIMEOUT is taken for hung: it is ended and this is an OutputError."""
        poll = select.poll()
        poll.register(self._sock, event)
        if not poll.poll(ANSWER_TIMEOUT * 1000):
            self.stop()
            raise output_error(self.target, RuntimeError(f"the replay writer {what} for {ANSWER_TIMEOUT:g} s"))

    def _answer(self, seconds: float):
        """The writer's answer (a message), or None where it ended without one within `seconds`."""
        self._sock.settimeout(seconds)
        try:
            return receive(self._sock)
        except (OSError, EOFError, pickle.UnpicklingError):
            return None
        finally:
            self._sock.setblocking(False)

    def _failure(self, answer=None) -> OutputError:
        """The OutputError naming the target for a writer that failed (its answer is read unless given)."""
        if answer is None:
            answer = self._answer(EXIT_WAIT)
        if isinstance(answer, tuple) and len(answer) == 2 and answer[0] == "error":
            reason = str(answer[1])
        else:
            try:
                code = self.process.wait(EXIT_WAIT)
            except subprocess.TimeoutExpired:
                code = None
            reason = ("the replay writer process stopped answering" if code is None else
                      f"the replay writer process was killed by signal {-code}" if code < 0 else
                      f"the replay writer process ended (exit status {code})")
        self.stop()
        return output_error(self.target, RuntimeError(reason))


def _read_exactly(sock: socket.socket, size: int) -> bytearray:
    data = bytearray(size)
    view, got = memoryview(data), 0
    while got < size:
        n = sock.recv_into(view[got:])
        if not n:
            raise EOFError
        got += n
    return data


def frame(message) -> list[memoryview]:
    """`message` as the parts of one frame: a header (the pickle's length, how many buffers, their lengths),
    the pickle, then the buffers (the memory of the contiguous numpy arrays in `message`, not copied)."""
    buffers = []
    data = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    buffers = [buffer.raw() for buffer in buffers]
    head = HEADER.pack(len(data), len(buffers)) + b"".join(LENGTH.pack(len(b)) for b in buffers)
    return [memoryview(head), memoryview(data), *buffers]


def receive(sock: socket.socket):
    """The next message on the socket, or None where the other end is closed before it."""
    try:
        header = _read_exactly(sock, HEADER.size)
    except EOFError:
        return None
    size, count = HEADER.unpack(header)
    lengths = struct.unpack(f"!{count}Q", _read_exactly(sock, LENGTH.size * count))
    data = _read_exactly(sock, size)
    return pickle.loads(data, buffers=[_read_exactly(sock, length) for length in lengths])


def next_file(sock: socket.socket) -> int | None:
    """The writer's side: the file descriptor that begins the next recording, or None once the race's
    process has closed its end."""
    try:
        data, fds, _, _ = socket.recv_fds(sock, 1, 1)
    except OSError:
        return None
    return fds[0] if data and fds else None


def answer(sock: socket.socket, message) -> None:
    """The writer's side: send `message` back to the race (nothing if the race's end is already closed)."""
    try:
        sock.sendall(b"".join(frame(message)))
    except OSError:
        pass
