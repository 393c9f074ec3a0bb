"""MP4 videos of races: `write_video` for frames, `VideoRecorder` for `run_race`.

``write_video(frames, path, fps=15) -> int`` writes RGB uint8 frames (a list
or any iterator; all the size of the first) as H.264 (avc1, yuv420p) in an
MP4 container with PyAV's libx264, the format every browser plays, written
faststart (the index first, so a browser starts playing while it loads), and
returns how many it wrote; a name that does not end in .mp4 is refused. ``VideoRecorder(path, fps=15, size=(540, 960))``
follows `racing.runner.run_race`'s recorder interface (``start(env)``,
``step(env, observations, rewards, infos)``, ``finish(env, result)``) and
writes one top-down frame (`sensors.topdown.render_topdown`) at the start and
after every step.
"""
from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np

from ..atomic import AtomicOutput, output_error
from ..sensors.topdown import DEFAULT_SIZE, render_topdown

CODEC = "libx264"
PIXEL_FORMAT = "yuv420p"  # 4:2:0, what browsers decode; it needs even frame sizes
QUALITY = "20"  # x264's constant rate factor: lower is better (18-23 looks clean on these scenes)
CONTAINER_OPTIONS = {"movflags": "faststart"}  # the index (moov) before the frames: a browser plays it while loading


def check_video_path(path) -> Path:
    """`path` if it names an MP4 (the one container written); a ValueError naming it otherwise, before any
    race runs (a `.avi` or `.gif` would get an MP4 under a name that says something else)."""
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"{path}: videos are written as H.264 MP4 only; give a name ending in .mp4")
    return path


class _Writer:
    """An H.264 MP4 stream opened on the first frame, fed RGB frames; written beside the target and put in
    place by `close()` (atomically: a failed video leaves any previous file of that name as it was)."""

    def __init__(self, path, fps: float):
        self.path = Path(path)
        self.fps = float(fps)
        self.output = None
        self.container = None
        self.stream = None
        self.size = None
        self.count = 0

    def _open(self, width: int, height: int) -> None:
        import av

        self.output = AtomicOutput(self.path)
        try:
            self.container = av.open(str(self.output.tmp), mode="w", format="mp4", options=CONTAINER_OPTIONS)
        except (OSError, av.FFmpegError) as exc:
            self.output.discard()
            raise output_error(self.path, exc) from None
        self.stream = self.container.add_stream(CODEC, rate=Fraction(self.fps).limit_denominator(1000),
                                                options={"crf": QUALITY})
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = PIXEL_FORMAT

    def write(self, frame: np.ndarray) -> None:
        import av

        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] not in (1, 3)):
            raise ValueError(f"video frames must be uint8 (H, W) or (H, W, 3), got {frame.dtype} {frame.shape}")
        if frame.ndim == 2 or frame.shape[2] == 1:
            frame = np.repeat(frame.reshape(frame.shape[:2])[:, :, None], 3, axis=2)
        h, w = frame.shape[:2]
        if self.container is None:
            self.size = (w, h)
            self._open(w, h)
        elif (w, h) != self.size:
            raise ValueError(f"video frame size {w}x{h} differs from the first frame's {self.size[0]}x{self.size[1]}")
        if w % 2 or h % 2:  # yuv420p: pad odd sizes by one edge pixel
            frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        try:
            for packet in self.stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame),
                                                                        format="rgb24")):
                self.container.mux(packet)
        except (OSError, av.FFmpegError) as exc:
            self.discard()
            raise output_error(self.path, exc) from None
        self.count += 1

    def close(self) -> None:
        """Finish the video and put it in place."""
        import av

        if self.container is None:
            return
        try:
            for packet in self.stream.encode():  # flush the encoder
                self.container.mux(packet)
            self.container.close()
        except (OSError, av.FFmpegError) as exc:
            self.discard()
            raise output_error(self.path, exc) from None
        self.container = None
        self.output.commit()

    def discard(self) -> None:
        """Drop the video being written (a failed or abandoned one); the target is untouched."""
        if self.container is not None:
            try:
                self.container.close()
            except Exception:  # noqa: BLE001 - the file is dropped whatever state it is in
                pass
            self.container = None
        if self.output is not None:
            self.output.discard()


def write_video(frames, path, fps: float = 15) -> int:
    """Write RGB uint8 frames (a sequence or an iterator) to an MP4 at `path`; returns the frame count."""
    writer = _Writer(check_video_path(path), fps)
    try:
        for frame in frames:
            writer.write(frame)
    except BaseException:
        writer.discard()
        raise
    writer.close()
    if writer.count == 0:
        raise ValueError("write_video: no frames to write")
    return writer.count


class VideoRecorder:
    """A `run_race` recorder that writes the top-down race view to an MP4."""

    def __init__(self, path, fps: float = 15, size=DEFAULT_SIZE):
        self.path = check_video_path(path)
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

    def discard(self) -> None:
        """Drop the video of a race that failed: the target is untouched."""
        if self._writer is not None:
            self._writer.discard()

    def __del__(self):  # a recorder never finished leaves nothing behind
        if getattr(self, "_writer", None) is not None:
            self._writer.discard()
