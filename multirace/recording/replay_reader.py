"""Reading a race replay back with rerun's own reader (`rerun.chunk.RrdReader`).

`replay_summary(path)` returns what a file holds: cars, steps, duration, laps,
events, image counts and each car's pose per step; `open_viewer` opens the
rerun viewer on it where one can run.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..text import TEXT_LENGTH, display_name, laps_text
from .files import regular_file
from .replay import END_TEXT


def record_column(batch, name):
    idx = batch.schema.get_field_index(name)
    return None if idx < 0 else batch.column(idx)


def first_items(values):
    """The first item of each row's component batch (rows are lists)."""
    return [None if v is None or len(v) == 0 else v[0] for v in values]


def read_chunks(path) -> dict:
    """Every chunk's record batch in an .rrd, grouped by entity path (leading '/' removed)."""
    from rerun.chunk import RrdReader

    by_entity: dict[str, list] = {}
    try:
        for chunk in RrdReader(str(path)).stream():
            by_entity.setdefault(chunk.entity_path.lstrip("/"), []).append(chunk.to_record_batch())
    except (RuntimeError, OSError) as exc:  # rerun's reader raises RuntimeError on a file it cannot decode
        if not Path(path).exists():
            raise FileNotFoundError(f"replay {path}: no such file") from None
        raise ValueError(f"{path}: not a rerun replay (.rrd) multirace can read ({str(exc).splitlines()[0]})") from None
    return by_entity


def view_origins(path) -> list[str]:
    """The origins of the views on the screen a replay opens on (its blueprint), e.g. ``world`` or
    ``cameras/car_0``, sorted."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    origins = set()
    for store in reader.blueprints():
        for chunk in reader.stream(store=store):
            column = record_column(chunk.to_record_batch(), "ViewBlueprint:space_origin")
            if column is not None:
                origins.update(first_items(column.to_pylist()))
    return sorted(origin for origin in origins if origin is not None)


def index_values(batch, name):
    import pyarrow as pa

    col = record_column(batch, name)
    if col is None:
        return None
    if pa.types.is_duration(col.type):
        return np.asarray(col.cast(pa.int64()).to_numpy(zero_copy_only=False), dtype=np.float64) * 1e-9
    return np.asarray(col.to_numpy(zero_copy_only=False))


def replay_summary(path, poses: bool = True) -> dict:
    """What a replay holds, read back with rerun's own reader.

    Returns {"track", "format", "laps", "cars": [{"id", "name", "laps", "lap_times", "images",
    "pose_steps", "lidar_scans", "lidar_echoes", "status"}], "steps", "duration", "events": [{"step",
    "race_time", "car", "name", "kind", "clock", "text"}], "result"} and, with `poses`, "poses":
    {car id: array (k, 4) of step, x, y, yaw} sorted by step.
    """
    path = regular_file(path, "replay")
    chunks = read_chunks(path)
    info = static_text(chunks, "race/info")
    if info is None:
        raise ValueError(f"replay {path}: not a multirace replay (no race/info)")
    info = race_info(info, path)
    result_text = static_text(chunks, "race/result")
    result = _json(result_text, path, "race/result") if result_text else None
    contents = _Contents(info)
    for entity, batches in chunks.items():
        for batch in batches:
            contents.add(entity.split("/"), batch)
    events = sorted(contents.events, key=lambda e: (e["step"], e["car"]))
    pose_rows, lidar_echoes = contents.pose_rows, contents.lidar_echoes
    cars = []
    for c in info["cars"]:
        laps = [e for e in events if e["car"] == c["id"] and e["kind"] == "lap"]
        ends = [e["kind"] for e in events if e["car"] == c["id"] and e["kind"] in END_TEXT]
        lap_times = [t for t in (lap_time(e["text"]) for e in laps) if t is not None]
        cars.append({"id": c["id"], "name": c["name"], "laps": len(laps), "lap_times": lap_times,
                     "images": contents.image_counts.get(c["id"], 0), "pose_steps": len(pose_rows[c["id"]]),
                     "lidar_scans": len(lidar_echoes[c["id"]]), "lidar_echoes": sum(lidar_echoes[c["id"]]),
                     "status": ends[-1] if ends else "racing"})
    summary = {
        "file": str(path), "size_mb": round(path.stat().st_size / 1e6, 3),
        "track": info["track"], "reverse": info["reverse"], "format": info["format"], "laps": info["laps"],
        "cars": cars, "steps": max(contents.all_steps, default=0), "duration": round(contents.max_time, 6),
        "events": events, "result": result,
    }
    if poses:
        summary["poses"] = {cid: np.array([(s, *p) for s, p in sorted(rows.items())], dtype=np.float64).reshape(-1, 4)
                            for cid, rows in pose_rows.items()}
    return summary


class _Contents:
    """What the chunks of a replay hold, gathered batch by batch: poses, LIDAR echoes, images, events."""

    def __init__(self, info: dict):
        self.names = {c["id"]: c["name"] for c in info["cars"]}
        self.all_steps: set[int] = set()
        self.max_time = 0.0
        self.pose_rows: dict[str, dict[int, tuple]] = {c["id"]: {} for c in info["cars"]}
        self.image_counts = {c["id"]: 0 for c in info["cars"]}
        self.lidar_echoes: dict[str, list] = {c["id"]: [] for c in info["cars"]}  # echo count per recorded scan
        self.events: list[dict] = []

    def add(self, parts: list[str], batch) -> None:
        """Take one record batch of the entity path `parts`."""
        steps = index_values(batch, "step")
        times = index_values(batch, "race_time")
        if steps is None:
            return
        self.all_steps.update(int(s) for s in steps)
        if times is not None and len(times):
            self.max_time = max(self.max_time, float(times.max()))
        if len(parts) == 3 and parts[2] not in self.pose_rows:  # a car the race description does not name
            return
        if parts[:2] == ["world", "cars"] and len(parts) == 3:
            self._poses(parts[2], steps, batch)
        elif parts[:2] == ["world", "lidar"] and len(parts) == 3:
            positions = record_column(batch, "Points3D:positions")
            if positions is not None:
                self.lidar_echoes[parts[2]].extend(len(p or ()) for p in positions.to_pylist())
        elif parts[0] == "cameras" and len(parts) == 2:
            blob = record_column(batch, "EncodedImage:blob")
            if blob is not None:
                self.image_counts[parts[1]] = self.image_counts.get(parts[1], 0) + sum(
                    1 for b in blob.to_pylist() if b)
        elif parts[0] == "events" and len(parts) == 2 and times is not None:
            self._events(parts[1], steps, times, batch)

    def _poses(self, car: str, steps, batch) -> None:
        trans = record_column(batch, "Transform3D:translation")
        quat = record_column(batch, "Transform3D:quaternion")
        if trans is None or quat is None:
            return
        for s, t, q in zip(steps, first_items(trans.to_pylist()), first_items(quat.to_pylist())):
            if t is None or q is None:
                continue
            qx, qy, qz, qw = q
            yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            self.pose_rows[car][int(s)] = (float(t[0]), float(t[1]), float(yaw))

    def _events(self, car: str, steps, times, batch) -> None:
        text_column = record_column(batch, "TextLog:text")
        if text_column is None:
            return
        texts = first_items(text_column.to_pylist())

        def column(name):
            values = record_column(batch, name)
            return first_items(values.to_pylist()) if values is not None else [None] * len(texts)

        for s, t, text, kind, clock in zip(steps, times, texts, column("kind"), column("clock")):
            self.events.append({"step": int(s), "race_time": round(float(t), 6), "car": car,
                                "name": self.names.get(car, car), "kind": kind, "clock": clock, "text": text})


def _json(text: str, path, entity: str):
    try:
        return json.loads(text)
    except (ValueError, RecursionError):  # RecursionError: nesting deeper than the parser's stack
        raise ValueError(f"replay {path}: {entity} is not JSON multirace can read") from None


def race_info(text: str, path) -> dict:
    """The race description of a replay (its race/info JSON), checked: a one-line error naming the file
    where it is not an object with track, reverse, format (text, a boolean, text), laps (a whole number) and
    cars (each with a text id and name)."""
    info = _json(text, path, "race/info")
    cars = info.get("cars") if isinstance(info, dict) else None
    types = {"track": str, "reverse": bool, "format": str, "laps": int}
    if (not isinstance(cars, list) or not all(isinstance(info.get(k), t) for k, t in types.items())
            or not all(isinstance(c, dict) and isinstance(c.get("id"), str) and isinstance(c.get("name"), str)
                       for c in cars)):
        raise ValueError(f"replay {path}: race/info is not a multirace race description "
                         "(track, reverse, format, laps and cars with an id and a name)")
    return info


def lap_time(text) -> float | None:
    """The seconds of a lap event's text ("... in 12.345 s"), or None where it holds none."""
    try:
        return float(str(text).rsplit(" in ", 1)[1].split()[0])
    except (IndexError, ValueError):
        return None


def static_text(chunks: dict, entity: str) -> str | None:
    for batch in chunks.get(entity, []):
        col = record_column(batch, "TextDocument:text")
        if col is not None:
            values = [v for v in first_items(col.to_pylist()) if v is not None]
            if values:
                return values[-1]
    return None


def format_summary(summary: dict) -> str:
    """A short human-readable text of a replay summary. Every text from the file (names, events, track,
    format, status) is shown as plain text: a replay is anyone's file, and its words must not reach the
    terminal as escapes."""
    lines = [f"{display_name(summary['file'], TEXT_LENGTH)} ({summary['size_mb']:.2f} MB): "
             f"{display_name(summary['format'])} on {display_name(summary['track'])}"
             f"{' (reverse)' if summary['reverse'] else ''}, {laps_text(summary['laps'])}, "
             f"{summary['steps']} steps, {summary['duration']:.2f} s of sim time",
             "(sim time: steps x 1/15 s since the start; lap and finish times: the race clock, which adds "
             "penalties)"]
    for c in summary["cars"]:
        laps = ", ".join(f"{t:.2f}" for t in c["lap_times"]) or "-"
        lines.append(f"  {display_name(c['id'])} {display_name(c['name'])}: {laps_text(c['laps'])} (race clock "
                     f"{laps}), {display_name(c['status'])}, {c['pose_steps']} poses, {c['images']} images")
    lines.append(f"  {len(summary['events'])} events (at sim time):")
    for e in summary["events"]:
        lines.append(f"    sim {e['race_time']:8.3f} s  step {e['step']:5d}  {display_name(e['text'], TEXT_LENGTH)}")
    return "\n".join(lines)


def open_viewer(path) -> int:
    """Open the rerun viewer on a replay, or say how when it is not available."""
    import shutil
    import subprocess

    path = regular_file(path, "replay")
    import os
    import sys

    exe = shutil.which("rerun")
    headless = sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if exe is None or headless:
        why = "no display here" if exe is not None else "the `rerun` viewer is not installed"
        print(f"Cannot open the rerun viewer ({why}). On a machine with a display, install it with "
              f"`pip install rerun-sdk==0.41.*` and run `rerun {path}`; here, print the contents with "
              f"`multirace replay {path} --summary`.")
        return 1
    return subprocess.call([exe, str(path)])
