"""Race videos for the match pages: the top-down view rendered from a match's replay, H.264 with faststart.

A video is made on first request (`recording.replay_video`), remuxed so that its index (the `moov` atom)
comes first and a browser starts playing before the whole file arrived, and kept in the league's videos/
folder under the match id; it is written to a temporary file and renamed into place when complete.
"""
from __future__ import annotations

import os
import threading
from pathlib import Path

VIDEOS = "videos"
VIDEO_SIZE = (360, 640)  # (height, width): small enough for a phone, sharp enough at 1280 px
_locks: dict = {}
_locks_guard = threading.Lock()


def faststart_copy(src, dst) -> None:
    """Copy an MP4's video stream into `dst` with the index first (ffmpeg's movflags=faststart)."""
    import av

    with av.open(str(src)) as source, av.open(str(dst), "w", format="mp4",
                                              options={"movflags": "faststart"}) as target:
        stream_in = source.streams.video[0]
        stream_out = target.add_stream_from_template(stream_in)
        for packet in source.demux(stream_in):
            if packet.dts is None:  # the demuxer's final empty packet
                continue
            packet.stream = stream_out
            target.mux(packet)


def match_video(folder: Path, match_id: str, replay: Path) -> Path:
    """The match's video (made from its replay on first call; concurrent calls wait for the one render)."""
    from ...recording.replay_video import replay_video

    final = folder / VIDEOS / f"{match_id}.mp4"
    with _locks_guard:
        lock = _locks.setdefault(match_id, threading.Lock())
    with lock:
        if final.is_file():
            return final
        final.parent.mkdir(exist_ok=True)
        raw = final.with_name(f".{match_id}.{os.getpid()}.raw.mp4")
        tmp = final.with_name(f".{match_id}.{os.getpid()}.tmp.mp4")
        try:
            replay_video(replay, raw, size=VIDEO_SIZE)
            faststart_copy(raw, tmp)
            os.replace(tmp, final)
        finally:
            raw.unlink(missing_ok=True)
            tmp.unlink(missing_ok=True)
    return final
