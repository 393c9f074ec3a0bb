"""Race replays: record a race to a rerun `.rrd` file (`replay_reader` reads one back).

`ReplayRecorder(path)` is a race recorder (`run_race(..., recorders=[...])`):
it writes, headless (no viewer needed), with rerun-sdk 0.41:

- ``race/info`` (static): track, format, laps, seed and the cars (id, name, colour)
  as a JSON `TextDocument`; ``race/result`` (static) the result record at the end;
- ``world/track/{center,inner,outer}`` (static): the track lines as `LineStrips3D`;
  ``world/obstacles`` (static): the boxes as `Boxes3D`;
- ``world/cars/car_<i>``: a `Boxes3D` in the car's `CAR_COLOURS` colour (static)
  moved by a `Transform3D` every step (body centre; yaw about z as a quaternion) while the car
  races, and once more on the step its run ends;
- ``cameras/car_<i>``: the car's camera image as JPEG (`EncodedImage`), every
  `image_every`-th step;
- ``world/lidar/car_<i>`` (races with a LIDAR): the echoes of the car's scan
  (beams that met something within range) as `Points3D` in the world, with
  the camera images;
- ``plots/{speed,progress,reward,rank,standing}/car_<i>``: `Scalars` per step
  (``rank``: the rules' order, the agents' info; ``standing``: with penalties
  counted while cars race, as the race video's panel, `RaceRules.standings`)
  (speed is the drive train's actual speed in m/s, progress the lap progress
  in % as in DeepRacer's params);
- ``events/car_<i>``: `TextLog` entries (lap with lap time, off_track, reset,
  collision with whom, penalty, crash, finish / forfeit / out of resets / time
  up) plus the machine-readable fields `kind`, `car`, `clock` as `AnyValues`.

Time lines: ``race_time`` (simulated race time, a duration in seconds) and
``step`` (the env's step number). A blueprint with the 3D view, the camera
images, the plots and the event log is sent with the recording, so
``rerun race.rrd`` opens on a useful screen.

Per-step data is buffered and sent in columns (`send_columns`) every
`flush_every` steps, which keeps the recording cost low; the encoded bytes
(rerun's binary stream) are then written by this module to a file beside the
target, which becomes the target only when the race ends well (`multirace.atomic`).
"""
from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
import math
from pathlib import Path

import cv2
import numpy as np

from ..atomic import AtomicOutput
from ..sim.world import CAR_COLOURS, OBSTACLE_SIZE

APPLICATION_ID = "multirace"
ENCODE_BATCH = 32  # camera images handed to the encoder thread at once
DEFAULT_IMAGE_EVERY = 5  # 3 Hz camera frames: keeps recording under 30 % of race speed
SCALARS = ("speed", "progress", "reward", "rank", "standing")
END_TEXT = {
    "finished": "finished",
    "forfeit": "forfeit",
    "out_of_resets": "out of resets",
    "timed_out": "time up",
    "not_finished": "did not finish",
}


def _rr():
    import rerun as rr

    return rr


def car_id(i: int) -> str:
    """Entity name of car slot i (car names like `bot:follow@1.5` are not path-safe)."""
    return f"car_{i}"


class ReplayRecorder:
    """Records a race to a rerun `.rrd` file (see the module docstring for its layout).

    `image_every`: record each car's camera every k-th step (0 or None: no images).
    """

    def __init__(self, path, image_every: int | None = DEFAULT_IMAGE_EVERY, jpeg_quality: int = 75,
                 flush_every: int = 600, application_id: str = APPLICATION_ID):
        self.path = Path(path)
        self.image_every = int(image_every or 0)
        self.jpeg_quality = int(jpeg_quality)
        self.flush_every = max(1, int(flush_every))
        self.application_id = application_id
        self.rec = None

    # --------------------------------------------------------------- recorder
    def start(self, env) -> None:
        rr = _rr()
        self._output = AtomicOutput(self.path)  # recorded beside the target, put in place by `close()`
        self._encoder = ThreadPoolExecutor(max_workers=1)
        self.rec = rec = rr.RecordingStream(self.application_id, make_default=False, make_thread_default=False)
        # the .rrd bytes come to this process (rerun's binary stream) and are written here: a write that fails
        # (a full disk) is an error of this call, not a log line of rerun's writer thread
        self._stream = rec.binary_stream()
        with self._output.guard():
            self._file = open(self._output.tmp, "wb")
        rec.set_log_time_enabled(False)  # wall-clock time says nothing about a simulated race
        state = env.race_state
        self.n = n = len(state.cars)
        self.ids = [car_id(i) for i in range(n)]
        self._agents = [env.possible_agents[i] if i < len(env.possible_agents) else None for i in range(n)]
        self._prev = [self._race_state(car.race) for car in state.cars]
        self._ended = [not car.racing for car in state.cars]
        self._buffer_reset()
        info = {
            "track": state.track.name, "reverse": bool(state.track.reverse), "track_length": state.track.length,
            "format": state.rules.name, "laps": state.rules.laps, "dt": state.dt,
            "cars": [{"id": self.ids[i], "name": car.name, "colour": list(CAR_COLOURS[i % len(CAR_COLOURS)])}
                     for i, car in enumerate(state.cars)],
        }
        rec.log("race/info", rr.TextDocument(json.dumps(info, indent=1)), static=True)
        self._log_track(state)
        spec = env.car_spec
        self._z = spec.height / 2
        for i in range(n):
            rec.log(f"world/cars/{self.ids[i]}",
                    rr.Boxes3D(half_sizes=[[spec.length / 2, spec.width / 2, spec.height / 2]],
                               colors=[CAR_COLOURS[i % len(CAR_COLOURS)]], labels=[state.cars[i].name],
                               fill_mode="solid"), static=True)
        rec.send_blueprint(self._blueprint(n), make_active=True, make_default=True)
        # the grid at step 0
        self._record_step(env, None, {}, None)

    def step(self, env, observations, rewards, infos) -> None:
        self._record_step(env, observations, rewards, infos)
        if self._rows >= self.flush_every:
            self._flush()
            self._drain(flush=False)

    def finish(self, env, result) -> None:
        rr = _rr()
        self._flush()
        if result is not None:
            self.rec.log("race/result", rr.TextDocument(json.dumps(result, indent=1)), static=True)
        self.close()

    def close(self) -> None:
        """Finish the recording and put the .rrd in place (atomically: a recording that could not be written
        completely, e.g. on a full disk, is an OutputError and leaves any previous file as it was)."""
        if getattr(self, "_encoder", None) is not None:
            self._encoder.shutdown()
            self._encoder = None
        if self.rec is not None:
            self._drain(flush=True)
            self.rec.disconnect()
            self._drain(flush=False)  # the end of the stream (rerun's footer)
            self.rec = None
            with self._output.guard():
                self._file.close()
            self._output.commit()

    def discard(self) -> None:
        """Drop the recording of a race that failed; the target is untouched."""
        if getattr(self, "_encoder", None) is not None:
            self._encoder.shutdown()
            self._encoder = None
        if self.rec is not None:
            self.rec.disconnect()
            self.rec = None
            try:
                self._file.close()
            except OSError:
                pass
            self._output.discard()

    def _drain(self, flush: bool) -> None:
        """Write what the recording stream holds to the file (all of it, after a flush, with `flush`)."""
        data = self._stream.read(flush=flush)
        if data:
            with self._output.guard():
                self._file.write(data)

    # --------------------------------------------------------------- helpers
    @staticmethod
    def _race_state(race) -> dict:
        return {"laps": race.laps, "resets": race.resets, "penalties": race.penalties,
                "penalty_time": race.penalty_time, "collisions": len(race.collisions), "status": race.status}

    def _log_track(self, state) -> None:
        rr, rec, track = _rr(), self.rec, state.track
        for name, xy, colour, radius in (("center", track.center, (235, 190, 40), 0.01),
                                         ("inner", track.inner, (240, 240, 240), 0.025),
                                         ("outer", track.outer, (240, 240, 240), 0.025)):
            pts = np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)
            rec.log(f"world/track/{name}", rr.LineStrips3D([pts], colors=[colour], radii=[radius]), static=True)
        poses = state.obstacles
        if len(poses):
            lx, ly, lz = OBSTACLE_SIZE
            rec.log("world/obstacles", rr.Boxes3D(
                centers=[[x, y, lz / 2] for x, y, _ in poses],
                half_sizes=[[lx / 2, ly / 2, lz / 2]] * len(poses),
                quaternions=[rr.Quaternion(xyzw=[0, 0, math.sin(yaw / 2), math.cos(yaw / 2)]) for *_, yaw in poses],
                colors=[(250, 250, 250)] * len(poses), fill_mode="solid"), static=True)

    def _blueprint(self, n: int):
        import rerun.blueprint as rrb

        cams = [rrb.Spatial2DView(origin=f"cameras/{self.ids[i]}", name=self.ids[i]) for i in range(n)]
        plots = [rrb.TimeSeriesView(origin=f"plots/{name}", name=name) for name in SCALARS]
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(rrb.Spatial3DView(origin="world", name="race"),
                             rrb.TextLogView(origin="events", name="events"), row_shares=[3, 1]),
                rrb.Vertical(rrb.Grid(*cams, name="cameras") if self.image_every else rrb.TextDocumentView(
                    origin="race/info"), rrb.Tabs(*plots, name="plots"), row_shares=[1, 1]),
                column_shares=[3, 2]),
            rrb.TimePanel(timeline="race_time"),
            collapse_panels=True,
        )

    def _buffer_reset(self) -> None:
        """Blocks of `flush_every` rows, one per buffered step: its step and time, which cars are recorded,
        their poses and scalars (NaN: none)."""
        rows, n = self.flush_every, self.n
        self._rows = 0
        self._steps, self._times = np.empty(rows, np.int64), np.empty(rows, np.float64)
        self._active, self._pose = np.empty((rows, n), bool), np.empty((rows, n, 3), np.float64)
        self._scalars = np.empty((rows, len(SCALARS), n), np.float64)  # SCALARS' order
        self._pending = []  # (row, car, image) not yet handed to the encoder
        self._encoding = []  # jobs encoding batches of them

    def _record_step(self, env, observations, rewards, infos) -> None:
        row = self._rows
        self._rows += 1
        state = env.race_state
        step, cars, n = state.step, state.cars, self.n
        self._steps[row], self._times[row] = step, state.time
        races = [car.race for car in cars]
        # a car is recorded while it races, on the step its run ends, and on the grid at step 0
        self._active[row] = [race.racing or not ended or step == 0 for race, ended in zip(races, self._ended)]
        self._pose[row] = [(car.x, car.y, car.yaw) for car in cars]
        agents, nan = self._agents, math.nan
        infos, rewards = infos or {}, rewards or {}
        self._scalars[row] = ([car.speed for car in cars],
                              [infos[a]["progress"] if a in infos else nan for a in agents],
                              [rewards[a] if a in rewards else nan for a in agents],
                              [infos[a]["rank"] if a in infos else nan for a in agents],
                              env.standings()[:n])
        take_image = bool(self.image_every) and observations is not None and step % self.image_every == 0
        self._time_set = False
        for i, race in enumerate(races):
            if self._ended[i]:  # its run ended on an earlier step
                continue
            agent = agents[i]
            if take_image and agent in observations:
                image = observations[agent]
                if isinstance(image, dict):  # a LIDAR env: {"camera", "lidar"}
                    if env.sensors.lidar == "lidar":  # (SECTOR_LIDAR's 8 sectors have no echo points)
                        self._log_lidar_echoes(env, state.cars[i], image["lidar"])
                    image = image["camera"]
                image = np.asarray(image)
                if image.ndim == 3 and image.shape[2] == 2:  # a stereo pair: its left camera
                    image = image[..., 0]
                elif image.ndim == 3:  # colour (grey images are (H, W))
                    image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
                self._pending.append((row, i, image.copy()))  # encoded later: the agent may reuse the array
            if infos:
                prev = self._prev[i]
                if (race.laps != prev["laps"] or race.resets != prev["resets"] or race.penalties != prev["penalties"]
                        or len(race.collisions) != prev["collisions"] or race.status != prev["status"]
                        or infos.get(agent, {}).get("events")):
                    self._log_events(env, state.cars[i], infos)
            if not race.racing:
                self._ended[i] = True
        if len(self._pending) >= ENCODE_BATCH:
            self._submit_pending()

    def _submit_pending(self) -> None:
        """Hand the images waiting to be encoded to the encoder thread as one job (JPEG encoding releases the
        GIL, so it runs on another core meanwhile; one job per batch, not per step, wakes that thread rarely)."""
        if self._pending:
            self._encoding.append(self._encoder.submit(self._encode_all, self._pending))
            self._pending = []

    def _set_step_time(self, state) -> None:
        """Point the recording's time lines at this step (once per step) before a direct `log`."""
        if not self._time_set:
            self.rec.set_time("step", sequence=state.step)
            self.rec.set_time("race_time", duration=state.time)
            self._time_set = True

    def _log_lidar_echoes(self, env, car, ranges) -> None:
        """A car's LIDAR echoes as world points (beams that met nothing are left out)."""
        i = car.index
        points = env.lidar.echoes((car.x, car.y, car.yaw), ranges)
        self._set_step_time(env.race_state)
        self.rec.log(f"world/lidar/{self.ids[i]}", _rr().Points3D(points, colors=[CAR_COLOURS[i % len(CAR_COLOURS)]],
                                                                  radii=[0.015]))

    def _encode_all(self, images) -> list:
        """[(row, car, image)] -> [(row, car, JPEG bytes or None)]."""
        return [(row, car, self._encode(image)) for row, car, image in images]

    def _encode(self, image: np.ndarray) -> bytes | None:
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        return jpeg.tobytes() if ok else None

    def _log_events(self, env, car, infos) -> None:
        """Text log entries for what changed in a car's race record this step."""
        rr, rec, state = _rr(), self.rec, env.race_state
        i, race, name = car.index, car.race, car.name
        prev, now = self._prev[i], self._race_state(race)
        agent = self._agents[i]
        info = infos.get(agent) if agent else None
        step_events = list(info["events"]) if info is not None else []
        clock = race.clock(state.time) if race.racing else race.finish_time
        entries = []  # (kind, level, text)
        for k in range(prev["laps"], now["laps"]):
            lap_time = race.lap_times[k]
            entries.append(("lap", "INFO", f"{name}: lap {k + 1} in {lap_time:.3f} s"))
        if "off_track" in step_events or (now["resets"] > prev["resets"] and "crashed" not in step_events):
            entries.append(("off_track", "WARN", f"{name}: off track"))
        if "crashed" in step_events:
            entries.append(("crashed", "WARN", f"{name}: crashed into a box"))
        for c in race.collisions[prev["collisions"]:]:
            who = "ran into" if c["caused"] else "was hit by"  # "ran into": at fault under the race rules
            kind = c.get("kind", "contact").replace("_", " ")
            entries.append(("collision", "WARN", f"{name}: collision ({kind}), {who} {c['with']}"))
        if now["resets"] > prev["resets"]:
            entries.append(("reset", "INFO", f"{name}: reset ({now['resets']} so far)"))
        if now["penalties"] > prev["penalties"]:
            added = now["penalty_time"] - prev["penalty_time"]
            entries.append(("penalty", "WARN", f"{name}: penalty +{added:g} s ({now['penalties']} so far)"))
        if now["status"] != prev["status"] and now["status"] != "racing":
            text = END_TEXT.get(now["status"], now["status"])
            reason = f" ({race.reason})" if race.reason else ""
            level = "INFO" if now["status"] == "finished" else "WARN"
            entries.append((now["status"], level, f"{name}: {text} at {race.finish_time:.3f} s{reason}"))
        if entries:
            self._set_step_time(state)
        for kind, level, text in entries:
            rec.log(f"events/{self.ids[i]}", rr.TextLog(text, level=level),
                    rr.AnyValues(kind=kind, car=self.ids[i], clock=float(clock if clock is not None else 0.0)))
        self._prev[i] = now

    def _flush(self) -> None:
        rows = self._rows
        if not rows:
            return
        rr, rec = _rr(), self.rec
        steps, times = self._steps[:rows], self._times[:rows]

        def index(rows):
            rows = np.asarray(rows, dtype=np.int64)
            return [rr.TimeColumn("step", sequence=steps[rows]), rr.TimeColumn("race_time", duration=times[rows])]

        active, poses = self._active[:rows], self._pose[:rows]
        scalars = {name: self._scalars[:rows, k] for k, name in enumerate(SCALARS)}
        self._submit_pending()
        camera_frames = [[] for _ in self.ids]  # per car: (row, jpeg)
        for job in self._encoding:
            for row, car, jpeg in job.result():
                camera_frames[car].append((row, jpeg))
        for i, cid in enumerate(self.ids):
            rows = np.flatnonzero(active[:, i])
            if len(rows):
                x, y, yaw = poses[rows, i].T
                half = yaw / 2
                zero = np.zeros_like(half)
                rec.send_columns(f"world/cars/{cid}", indexes=index(rows), columns=rr.Transform3D.columns(
                    translation=np.column_stack([x, y, np.full(len(rows), self._z)]),
                    quaternion=np.column_stack([zero, zero, np.sin(half), np.cos(half)])))
            for name, values in scalars.items():
                with_value = rows[~np.isnan(values[rows, i])]
                if len(with_value):
                    rec.send_columns(f"plots/{name}/{cid}", indexes=index(with_value),
                                     columns=rr.Scalars.columns(scalars=values[with_value, i]))
            images = [(row, jpeg) for row, jpeg in camera_frames[i] if jpeg is not None]
            if images:
                rec.send_columns(f"cameras/{cid}", indexes=index([r for r, _ in images]),
                                 columns=rr.EncodedImage.columns(blob=[b for _, b in images],
                                                                 media_type=["image/jpeg"] * len(images)))
        self._buffer_reset()
