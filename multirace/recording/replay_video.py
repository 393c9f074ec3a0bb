"""Race videos from replays: the top-down race view drawn from a `.rrd`'s recorded poses.

``replay_video(rrd, out_mp4, fps=None, size=(540, 960)) -> dict`` reads a
replay back (`replay.replay_summary`, rerun's own reader) and writes one
`topdown.render_topdown` frame per recorded step (step 0, the grid, included),
without re-running the race: the drawing code sees a light stand-in for the
env (`ReplayScene`) whose world holds the recorded poses. What the stand-in
holds per step:

- car poses: the recorded `world/cars/car_<i>` transforms (the last one held
  while a car has no new pose, e.g. between flushes);
- parked: a car whose run ended (finish / forfeit / out of resets / time up /
  did not finish event) is no longer drawn from the step after its last pose;
- laps and status per car from the event log (lap events, end events);
- ranks from the recorded ``plots/rank`` scalars and standings (the panel's
  order, penalties counted) from ``plots/standing`` (a replay without them:
  the ranks; falling back to laps, then car order); penalty seconds,
  resets and at-fault collisions from the penalty, reset and collision events;
- boxes from ``world/obstacles``; the track and its texture from the track
  name and direction in ``race/info``.

`fps` defaults to the race's control rate (1 / dt from ``race/info``), so the
video plays in real time.
"""
from __future__ import annotations

import json
import math
import re
import types
from pathlib import Path

import numpy as np

from ..sim.car import CarSpec
from .replay import END_TEXT
from .replay_reader import first_items, index_values, read_chunks, record_column, replay_summary, static_text
from ..sim.texture import TrackTexture
from ..sensors.topdown import DEFAULT_SIZE, render_topdown
from ..sim.tracks import load_track
from .video import write_video

AT_FAULT_TEXT = ", ran into "  # the replay's collision event text of the car at fault (`replay.ReplayRecorder`)
PENALTY_TEXT = re.compile(r"penalty \+([0-9.]+) s")  # the replay's penalty event text (`replay.ReplayRecorder`)


class _World:
    """What `render_topdown` reads of a `world.World`."""

    def __init__(self, num_cars: int, obstacle_poses: np.ndarray, spec: CarSpec):
        self.num_cars = num_cars
        self.poses = np.zeros((num_cars, 3))
        self.parked = np.zeros(num_cars, dtype=bool)
        self.obstacle_poses = obstacle_poses
        self.spec = spec


class _Rules:
    def __init__(self, name: str, laps: int):
        self.name, self.laps = name, laps


class ReplayScene:
    """A stand-in for `env.RaceEnv` with the attributes the top-down view reads, set from a replay.

    Call `at(step)` to move it to a recorded step (steps must not go backwards
    within one video; going back starts new trails, as for a new episode).
    """

    def __init__(self, path, summary: dict | None = None, chunks: dict | None = None):
        self.path = Path(path)
        chunks = chunks if chunks is not None else read_chunks(self.path)
        summary = summary if summary is not None else replay_summary(self.path, poses=True)
        info = json.loads(static_text(chunks, "race/info"))
        self.summary = summary
        self.track = load_track(info["track"], reverse=bool(info.get("reverse", False)))
        self.texture = TrackTexture(self.track)
        self.car_spec = CarSpec()
        self.dt = float(info.get("dt") or 1.0 / 15)
        self.rules = _Rules(info.get("format", ""), int(info.get("laps") or 0))
        self.ids = [c["id"] for c in info["cars"]]
        self.car_names = [c["name"] for c in info["cars"]]
        n = len(self.ids)
        self.world = _World(n, _obstacles(chunks), self.car_spec)
        self.total_cars = n
        self.possible_agents = list(self.ids)
        self._poses = [summary["poses"].get(cid, np.zeros((0, 4))) for cid in self.ids]
        self._ranks = [_scalar_series(chunks, f"plots/rank/{cid}") for cid in self.ids]
        self._standings = [_scalar_series(chunks, f"plots/standing/{cid}") for cid in self.ids]
        self._marks = [[(e["step"], e["kind"], e["text"]) for e in summary["events"]
                        if e["car"] == cid and e["kind"] in ("penalty", "reset", "collision")] for cid in self.ids]
        # per car: sorted lap-event steps and the (step, status) of its end
        self._lap_steps = [sorted(e["step"] for e in summary["events"] if e["car"] == cid and e["kind"] == "lap")
                           for cid in self.ids]
        self._end = []
        for cid in self.ids:
            ends = [(e["step"], e["kind"]) for e in summary["events"] if e["car"] == cid and e["kind"] in END_TEXT]
            self._end.append(ends[-1] if ends else None)
        self.last_step = int(max([summary["steps"]] + [int(p[-1, 0]) for p in self._poses if len(p)]))
        self.races = [types.SimpleNamespace(racing=True, laps=0, status="racing", penalty_time=0.0, resets=0,
                                            at_fault=0) for _ in range(n)]
        self.steps = 0
        self.sim_time = 0.0
        self.at(0)

    def at(self, step: int) -> "ReplayScene":
        """Set every car's pose, lap count, status and rank to those recorded at `step`."""
        step = int(step)
        self.steps = step
        self.sim_time = step * self.dt
        for i in range(self.total_cars):
            poses = self._poses[i]
            if len(poses):
                k = int(np.searchsorted(poses[:, 0], step, side="right")) - 1
                self.world.poses[i] = poses[max(k, 0), 1:4]
                last_pose_step = poses[-1, 0]
            else:
                last_pose_step = -1
            race = self.races[i]
            race.laps = int(np.searchsorted(self._lap_steps[i], step, side="right"))
            end = self._end[i]
            ended = end is not None and step >= end[0]
            race.racing = not ended
            race.status = end[1] if ended else "racing"
            marks = [(kind, text) for at, kind, text in self._marks[i] if at <= step]
            race.resets = sum(kind == "reset" for kind, _ in marks)
            race.at_fault = sum(kind == "collision" and AT_FAULT_TEXT in text for kind, text in marks)
            race.penalty_time = sum(float(m.group(1)) for kind, text in marks if kind == "penalty"
                                    for m in [PENALTY_TEXT.search(text)] if m)
            # a car is drawn on the step its run ends (its last pose), parked after
            self.world.parked[i] = ended and step > max(end[0], last_pose_step)
        return self

    def ranks(self) -> list[int]:
        """Positions at the current step: recorded ranks where there are any, else by laps then car order."""
        return self._positions(self._ranks)

    def standings(self) -> list[int]:
        """The race video panel's positions at the current step (penalties counted): the recorded standings,
        or the ranks in a replay recorded before standings were."""
        return self._positions(self._standings if any(len(s) for s in self._standings) else self._ranks)

    def _positions(self, recorded: list) -> list[int]:
        step = self.steps
        keys = []
        for i in range(self.total_cars):
            series = recorded[i]
            rank = math.inf
            if len(series):
                k = int(np.searchsorted(series[:, 0], step, side="right")) - 1
                if k >= 0:
                    rank = float(series[k, 1])
            keys.append((rank, -self.races[i].laps, i))
        order = sorted(range(self.total_cars), key=lambda i: keys[i])
        positions = [0] * self.total_cars
        for place, i in enumerate(order):
            positions[i] = place + 1
        return positions


def _scalar_series(chunks: dict, entity: str) -> np.ndarray:
    """(k, 2) array of (step, value) of a `Scalars` entity, sorted by step."""
    rows = []
    for batch in chunks.get(entity, []):
        steps = index_values(batch, "step")
        col = record_column(batch, "Scalars:scalars")
        if steps is None or col is None:
            continue
        for s, v in zip(steps, first_items(col.to_pylist())):
            if v is not None:
                rows.append((float(s), float(v)))
    rows.sort()
    return np.array(rows, dtype=np.float64).reshape(-1, 2)


def _obstacles(chunks: dict) -> np.ndarray:
    """(M, 3) x, y, yaw of the recorded boxes (static `world/obstacles`)."""
    for batch in chunks.get("world/obstacles", []):
        centres = record_column(batch, "Boxes3D:centers")
        quats = record_column(batch, "Boxes3D:quaternions")
        if centres is None:
            continue
        rows = [c for c in centres.to_pylist() if c]
        if not rows:
            continue
        cs = rows[-1]
        qs = ([q for q in quats.to_pylist() if q] or [None])[-1] if quats is not None else None
        out = []
        for k, c in enumerate(cs):
            yaw = 0.0
            if qs is not None and k < len(qs):
                qx, qy, qz, qw = qs[k]
                yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            out.append((float(c[0]), float(c[1]), yaw))
        return np.array(out, dtype=np.float64).reshape(-1, 3)
    return np.zeros((0, 3))


def replay_frames(path, size=DEFAULT_SIZE, scene: ReplayScene | None = None):
    """Yield the top-down frame (uint8 RGB) of every step 0..last recorded step of a replay."""
    scene = scene if scene is not None else ReplayScene(path)
    for step in range(scene.last_step + 1):
        yield render_topdown(scene.at(step), size)


def replay_video(path, out, fps: float | None = None, size=DEFAULT_SIZE) -> dict:
    """Write the top-down race view of a replay as an MP4; returns {"file", "frames", "steps", "fps"}."""
    scene = ReplayScene(path)
    fps = float(fps) if fps else 1.0 / scene.dt
    frames = write_video(replay_frames(path, size, scene), out, fps=fps)
    return {"file": str(out), "frames": frames, "steps": scene.last_step, "fps": fps}
