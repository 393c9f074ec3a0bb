"""The replay writer: lays a race's recorded data out as a rerun recording and writes the `.rrd` file.

It runs in a process of its own (`replay_process`), fed by `replay.ReplayRecorder` (which describes the
layout) with, for each replay: the file to write (its descriptor), ``("start", description)``,
``("rows", batch)`` as the race goes and ``("finish", result text or None)``. It JPEG-encodes the camera
images as they come (read from the shared `arena.ImageArena`, whose space it then gives back, or drawn
here from the recorded poses, `scene_cameras`), logs events and LIDAR echoes at their step, builds the
per-step columns of every `flush_every` rows (`send_columns`, `columns`) and writes the recording to the
file it was given; it answers ``("done", cpu seconds spent on it)`` once the file is complete, or
``("error", reason)``.

rerun's file sink (`save`) encodes and writes the recording as it comes (flushed after each block of
columns), with one manifest at the end, into a pipe whose bytes a thread here writes to the file and syncs
to disk every `SYNC_BYTES` (`_FileCopy`): a write that fails (a full disk) is this process's error, not a
log line of rerun's writer thread, and rerun never waits on a failed file; the race's end waits only for
the last block's columns, the manifest and the last bytes' sync.
(Not rerun's binary stream: each read of it is a complete RRD with its own manifest, and a file of two
is refused by rerun's reader, "CRC check failed"; read once at the end, it costs the race's end time in
proportion to the whole recording.)
"""
from __future__ import annotations

import math
import os
import select
import socket
import sys
import threading
import time
import traceback

import cv2
import numpy as np
import rerun as rr

from . import blueprints
from .arena import ArenaImage, ImageArena
from .columns import image_columns, scalar_columns, time_index, transform_columns
from .replay import block_columns
from .replay_process import answer, next_file, receive
from .scene_cameras import SceneCameras

SYNC_BYTES = 1 << 20  # bytes written to the file between two syncs to disk
TRACK_LINES = (("center", (235, 190, 40), 0.01), ("inner", (240, 240, 240), 0.025),
               ("outer", (240, 240, 240), 0.025))  # name, colour, radius


def serve(sock_fd: int, arena_fd: int, arena_bytes: int) -> None:
    """Write the replays the race's process sends on the socket `sock_fd`, one after another, answering each;
    their camera images come through the image arena in the open file `arena_fd` (`arena_bytes` long).
    After a failed replay, or when the race's process closes its end in the middle of one, this process ends
    at once (`os._exit`: rerun's exit hooks would wait to flush a recording nobody reads)."""
    sock = socket.socket(fileno=sock_fd)
    arena = ImageArena(arena_fd, arena_bytes)
    while (file_fd := next_file(sock)) is not None:
        cpu = time.process_time()
        outcome = _record(sock, file_fd, arena)
        if outcome != "done":
            if outcome is not None:  # (None: the race's end closed before `finish`, the race failed or ended)
                answer(sock, outcome)
            sys.stderr.flush()
            os._exit(1 if outcome is not None else 0)
        answer(sock, ("done", time.process_time() - cpu))


def _record(sock: socket.socket, file_fd: int, arena: ImageArena) -> str | tuple | None:
    """Write one replay into the open file `file_fd`: "done", ("error", reason), or None where the race's
    end closed before ``finish``."""
    try:
        with open(file_fd, "wb") as file:
            writer = None
            while (message := receive(sock)) is not None:
                kind, content = message
                if kind == "start":
                    writer = ReplayWriter(file, arena, **content)
                elif kind == "rows":
                    writer.add(content, more_waiting=bool(select.select([sock], [], [], 0)[0]))
                else:
                    writer.finish(content)
                    return "done"
    except OSError as exc:  # the file could not be written (a full disk): the race names it
        return ("error", exc.strerror or str(exc))
    except Exception as exc:  # noqa: BLE001 - any failure is the race's error, with its trace here
        traceback.print_exc()
        return ("error", f"the replay writer failed ({type(exc).__name__}: {exc})")
    return None


class ReplayWriter:
    """One recording: the static entities at once, then rows, images and log entries as they come."""

    def __init__(self, file, arena: ImageArena, application_id: str, jpeg_quality: int, flush_every: int,
                 scalars: tuple, info: str, cars: list, half_size: tuple, track: dict, obstacles,
                 obstacle_size: tuple, layout: str, cameras: bool, scene: dict | None = None):
        self.jpeg_quality, self.flush_every, self.scalars = jpeg_quality, flush_every, scalars
        self.ids, self.colours = [c["id"] for c in cars], [tuple(c["colour"]) for c in cars]
        self.z = half_size[2]
        self.arena = arena
        self.cameras = SceneCameras(**scene) if scene is not None else None  # draws the "drawn" images
        self.rec = rec = rr.RecordingStream(application_id, make_default=False, make_thread_default=False)
        self._copy = _FileCopy(file)
        rec.save(self._copy.path)
        rec.set_log_time_enabled(False)  # wall-clock time says nothing about a simulated race
        rec.log("race/info", rr.TextDocument(info), static=True)
        for name, colour, radius in TRACK_LINES:
            xy = track[name]
            pts = np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)
            rec.log(f"world/track/{name}", rr.LineStrips3D([pts], colors=[colour], radii=[radius]), static=True)
        if len(obstacles):
            lx, ly, lz = obstacle_size
            rec.log("world/obstacles", rr.Boxes3D(
                centers=[[x, y, lz / 2] for x, y, _ in obstacles],
                half_sizes=[[lx / 2, ly / 2, lz / 2]] * len(obstacles),
                quaternions=[rr.Quaternion(xyzw=[0, 0, math.sin(yaw / 2), math.cos(yaw / 2)])
                             for *_, yaw in obstacles],
                colors=[(250, 250, 250)] * len(obstacles), fill_mode="solid"), static=True)
        for cid, colour, car in zip(self.ids, self.colours, cars):
            rec.log(f"world/cars/{cid}", rr.Boxes3D(half_sizes=[list(half_size)], colors=[colour],
                                                    labels=[car["name"]], fill_mode="solid"), static=True)
        rec.send_blueprint(blueprints.build(layout, self.ids, scalars, cameras), make_active=True, make_default=True)
        self._first = 0  # the race's row index of the block's first row
        self._frames = [[] for _ in self.ids]  # per car: (row in the race, JPEG) not yet sent
        self._block_reset()

    def add(self, batch: dict, more_waiting: bool = False) -> None:
        """Take the rows of consecutive steps (and their images and log entries) from the race; columns go out
        once the block holds `flush_every` rows, unless `more_waiting` (the race has sent more already: at
        its end, the last rows and the result follow at once), so that the block's columns and the last
        rows' go out together rather than one after the other, up to twice `flush_every` rows."""
        received, released = self._first + self._rows, None
        columns = block_columns(batch["table"], len(self.ids))
        for row, cars, images in batch["images"]:  # a step's images of `cars`
            if isinstance(images, tuple):  # where they lie in the arena (`WriterProcess.carry`)
                where = ArenaImage._make(images)
                images, released = self.arena.image(where), where.end
            self._keep_frames(received + row, cars, images)
        if released is not None:
            self.arena.release(released)
        for row, cars, parked in batch["drawn"]:  # a step's images of `cars`, drawn here (`scene_cameras`)
            self._keep_frames(received + row, cars, self.cameras.draw(cars, columns["pose"][row], parked))
        for step, race_time, entity, image in batch["pictures"]:
            jpeg = self._encode(image)
            if jpeg is not None:
                self._log(step, race_time, entity, rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))
        for step, race_time, car, points in batch["echoes"]:
            self._log(step, race_time, f"world/lidar/{self.ids[car]}",
                      rr.Points3D(points, colors=[self.colours[car]], radii=[0.015]))
        for step, race_time, car, entries in batch["events"]:
            for kind, level, text, clock in entries:
                self._log(step, race_time, f"events/{self.ids[car]}", rr.TextLog(text, level=level),
                          rr.AnyValues(kind=kind, car=self.ids[car], clock=float(clock)))
        rows = len(columns["steps"])
        if self._rows + rows > len(self._steps):  # (a block held back, below, that these rows would overflow)
            self._flush()
        if rows > len(self._steps):
            self._block_reset(rows)
        block = slice(self._rows, self._rows + rows)
        self._steps[block], self._times[block] = columns["steps"], columns["times"]
        self._active[block], self._pose[block], self._scalars[block] = (columns["active"], columns["pose"],
                                                                         columns["scalars"])
        self._rows += rows
        if self._rows >= self.flush_every and not more_waiting:
            self._flush()
            self.rec.flush()  # encoded and in the file now, while the race goes on: less for its end to wait for

    def finish(self, result: str | None) -> None:
        """Send the last rows and the result, end the recording and write it to the file in one piece."""
        self._flush()
        if result is not None:
            self.rec.log("race/result", rr.TextDocument(result), static=True)
        self.rec.disconnect()  # ends the stream: rerun writes its footer (the manifest of every chunk)
        self._copy.close()

    # --------------------------------------------------------------- helpers

    def _log(self, step: int, time: float, entity: str, *archetypes) -> None:
        self.rec.set_time("step", sequence=step)
        self.rec.set_time("race_time", duration=time)
        self.rec.log(entity, *archetypes)

    def _keep_frames(self, row: int, cars, images) -> None:
        """The cars' camera images of the race's row `row`, JPEG-encoded until their block's columns go out."""
        for car, image in zip(cars, images):
            jpeg = self._encode(image)
            if jpeg is not None:
                self._frames[car].append((row, jpeg))

    def _encode(self, image: np.ndarray) -> bytes | None:
        """A camera image (grey, or RGB) as JPEG bytes (None where it cannot be encoded)."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        return jpeg.tobytes() if ok else None

    def _block_reset(self, least: int = 0) -> None:
        """A block of up to twice `flush_every` rows (at least `least`), one per step: its step and time, which
        cars are recorded, their poses and scalars (NaN: none)."""
        rows, n = max(2 * self.flush_every, least), len(self.ids)
        self._rows = 0
        self._steps, self._times = np.empty(rows, np.int64), np.empty(rows, np.float64)
        self._active, self._pose = np.empty((rows, n), bool), np.empty((rows, n, 3), np.float64)
        self._scalars = np.empty((rows, len(self.scalars), n), np.float64)  # the scalars' order

    def _flush(self) -> None:
        """Send the block's rows as columns: each car's poses, scalars and camera images."""
        rows = self._rows
        if not rows:
            return
        rec = self.rec
        steps, times = self._steps[:rows], self._times[:rows]

        def index(rows):
            return time_index(steps[rows], times[rows])

        active, poses = self._active[:rows], self._pose[:rows]
        scalars = {name: self._scalars[:rows, k] for k, name in enumerate(self.scalars)}
        end = self._first + rows
        for i, cid in enumerate(self.ids):
            rows = np.flatnonzero(active[:, i])
            car_index = index(rows)  # (the scalars' too, where they have a value at every row: the usual case)
            if len(rows):
                x, y, yaw = poses[rows, i].T
                half = yaw / 2
                zero = np.zeros_like(half)
                rec.send_columns(f"world/cars/{cid}", indexes=car_index, columns=transform_columns(
                    np.column_stack([x, y, np.full(len(rows), self.z)]),
                    np.column_stack([zero, zero, np.sin(half), np.cos(half)])))
            for name, values in scalars.items():
                with_value = rows[~np.isnan(values[rows, i])]
                if len(with_value):
                    rec.send_columns(f"plots/{name}/{cid}",
                                     indexes=car_index if len(with_value) == len(rows) else index(with_value),
                                     columns=scalar_columns(values[with_value, i]))
            images = [(row - self._first, jpeg) for row, jpeg in self._frames[i] if row < end]
            self._frames[i] = [(row, jpeg) for row, jpeg in self._frames[i] if row >= end]
            if images:
                rec.send_columns(f"cameras/{cid}", indexes=index(np.array([r for r, _ in images], np.int64)),
                                 columns=image_columns([b for _, b in images], "image/jpeg"))
        self._first = end
        self._block_reset()


class _FileCopy:
    """A pipe (`path`, for rerun to open) whose bytes a thread writes to `file`. The first write error is kept,
    and the rest of the pipe drained, so that rerun never waits on it; `close` raises it."""

    def __init__(self, file):
        self.file, self.error, self.size = file, None, 0
        self._read, self._write = os.pipe()
        self.path = f"/dev/fd/{self._write}"
        self._thread = threading.Thread(target=self._copy, name="replay file", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Wait until everything written to the pipe is in the file (once rerun has closed its end)."""
        os.close(self._write)
        self._thread.join()
        os.close(self._read)
        if self.error is not None:
            raise self.error
        if not self.size:
            raise OSError(f"rerun wrote nothing to {self.path}")

    def _copy(self) -> None:
        unsynced = 0
        while chunk := os.read(self._read, 1 << 20):
            if self.error is None:
                try:
                    self.file.write(chunk)
                    self.size += len(chunk)
                    unsynced += len(chunk)
                    if unsynced >= SYNC_BYTES:  # on disk as it comes: the race's commit (fsync) waits only for the rest
                        self.file.flush()
                        os.fdatasync(self.file.fileno())
                        unsynced = 0
                except (OSError, ValueError) as exc:  # ValueError: the file was closed (a replay given up)
                    self.error = exc
