"""MP4 videos of races: `write_video` for frames, `VideoRecorder` for `run_race`.

``write_video(frames, path, fps=15) -> int`` writes RGB uint8 frames (a list
or any iterator; all the size of the first) with OpenCV's ``mp4v`` codec and
returns how many it wrote. ``VideoRecorder(path, fps=15, size=(540, 960))``
follows `race.run_race`'s recorder interface (``start(env)``, ``step(env,
observations, rewards, infos)``, ``finish(env, result)``) and writes one
top-down frame (`topdown.render_topdown`) at the start and after every step.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..sensors.topdown import DEFAULT_SIZE, render_topdown


class _Writer:
    """A cv2.VideoWriter opened on the first frame, fed RGB frames."""

    def __init__(self, path, fps: float):
        self.path = Path(path)
        self.fps = float(fps)
        self.writer = None
        self.size = None
        self.count = 0

    def write(self, frame: np.ndarray) -> None:
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim not in (2, 3):
            raise ValueError(f"video frames must be uint8 (H, W) or (H, W, 3), got {frame.dtype} {frame.shape}")
        if frame.ndim == 2 or frame.shape[2] == 1:
            frame = cv2.cvtColor(frame.reshape(frame.shape[:2]), cv2.COLOR_GRAY2BGR)
        else:
            frame = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)
        h, w = frame.shape[:2]
        if self.writer is None:
            if self.path.parent and not self.path.parent.exists():
                self.path.parent.mkdir(parents=True, exist_ok=True)
            self.size = (w, h)
            self.writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, self.size)
            if not self.writer.isOpened():
                raise OSError(f"cannot open {self.path} for writing an MP4 video")
        elif (w, h) != self.size:
            raise ValueError(f"video frame size {w}x{h} differs from the first frame's {self.size[0]}x{self.size[1]}")
        self.writer.write(frame)
        self.count += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()
            self.writer = None


def write_video(frames, path, fps: float = 15) -> int:
    """Write RGB uint8 frames (a sequence or an iterator) to an MP4 at `path`; returns the frame count."""
    writer = _Writer(path, fps)
    try:
        for frame in frames:
            writer.write(frame)
    finally:
        writer.close()
    if writer.count == 0:
        raise ValueError("write_video: no frames to write")
    return writer.count


class VideoRecorder:
    """A `run_race` recorder that writes the top-down race view to an MP4."""

    def __init__(self, path, fps: float = 15, size=DEFAULT_SIZE):
        self.path = Path(path)
        self.fps = fps
        self.size = tuple(size)
        self._writer: _Writer | None = None

    @property
    def frames(self) -> int:
        return self._writer.count if self._writer is not None else 0

    def start(self, env) -> None:
        self._writer = _Writer(self.path, self.fps)
        self._writer.write(render_topdown(env, self.size))

    def step(self, env, observations=None, rewards=None, infos=None) -> None:
        if self._writer is None:
            self.start(env)
            return
        self._writer.write(render_topdown(env, self.size))

    def finish(self, env, result=None) -> None:
        if self._writer is not None:
            self._writer.close()

    def __del__(self):
        if getattr(self, "_writer", None) is not None:
            self._writer.close()
