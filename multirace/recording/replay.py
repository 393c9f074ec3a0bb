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

The race's process only gathers what each step shows into blocks of `SHIP_EVERY` rows (steps, times,
poses, scalars, camera images, event texts, LIDAR echoes) and hands each block to the replay writer
(`replay_writer`), a process of its own (`replay_process`). The camera images are copied into memory the
writer shares, or, where they are the fast renderer's pure images of the recorded poses, drawn again by
the writer (`scene_cameras`: the race sends only which cars are parked). There the images are
JPEG-encoded, the per-step data are sent in columns (`send_columns`) every `flush_every` steps and rerun's
binary stream is written to a file beside the target, which becomes the target only when the race ends
well and the writer has written it completely (`multirace.atomic`); a writer that fails is an
`OutputError` naming the target.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ..atomic import AtomicOutput
from ..sim.world import CAR_COLOURS, OBSTACLE_SIZE
from .replay_process import WriterProcess, prepare
from .scene_cameras import scene_of

APPLICATION_ID = "multirace"
SHIP_EVERY = 90  # steps whose data go to the writer in one message (fewer, larger messages wake it less)
DEFAULT_IMAGE_EVERY = 5  # 3 Hz camera frames
SCALARS = ("speed", "progress", "reward", "rank", "standing")
RACE_MARKS = ("laps", "resets", "penalties", "penalty_time", "collisions", "status")  # `_race_state`'s order
END_TEXT = {
    "finished": "finished",
    "forfeit": "forfeit",
    "out_of_resets": "out of resets",
    "timed_out": "time up",
    "not_finished": "did not finish",
}


def block_columns(table: np.ndarray, n: int) -> dict:
    """The columns of a block of `n` cars' rows (`ReplayRecorder._record_step`'s layout, one row per step):
    "steps", "times", "active" (which cars are recorded), "pose" (rows, n, 3: x, y, yaw) and "scalars" (rows,
    SCALARS, n; NaN where a car has none)."""
    rows = len(table)
    cars = table[:, 2 + n:2 + 5 * n].reshape(rows, n, 4)
    agents = table[:, 2 + 5 * n:2 + 8 * n].reshape(rows, n, 3)
    return {"steps": table[:, 0].astype(np.int64), "times": table[:, 1], "active": table[:, 2:2 + n] != 0,
            "pose": cars[..., :3],
            "scalars": np.stack([cars[..., 3], agents[..., 0], agents[..., 1], agents[..., 2], table[:, 2 + 8 * n:]],
                                axis=1)}  # SCALARS' order


def car_id(i: int) -> str:
    """Entity name of car slot i (car names like `bot:follow@1.5` are not path-safe)."""
    return f"car_{i}"


class ReplayRecorder:
    """Records a race to a rerun `.rrd` file (see the module docstring for its layout).

    `image_every`: record each car's camera every k-th step (0 or None: no images). A replay writer process
    is started ahead (`replay_process.prepare`) unless one is waiting already. `layout` names the screen the
    replay opens on (`blueprints.LAYOUTS`).
    """

    layout = "race"

    def __init__(self, path, image_every: int | None = DEFAULT_IMAGE_EVERY, jpeg_quality: int = 75,
                 flush_every: int = 600, application_id: str = APPLICATION_ID):
        self.path = Path(path)
        self.image_every = int(image_every or 0)
        self.jpeg_quality = int(jpeg_quality)
        self.flush_every = max(1, int(flush_every))
        self.application_id = application_id
        self.writer_cpu_s = 0.0  # CPU seconds the writer process spent on the replay, once it is complete
        self._writer = None
        prepare()

    # --------------------------------------------------------------- recorder
    def start(self, env) -> None:
        self._output = AtomicOutput(self.path)  # recorded beside the target, put in place by `close()`
        with self._output.guard():
            fd = os.open(self._output.tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        try:
            self._writer = WriterProcess.begin(fd, self.path)
        except BaseException:
            self._output.discard()
            raise
        finally:
            os.close(fd)
        state = env.race_state
        self.n = n = len(state.cars)
        self.ids = [car_id(i) for i in range(n)]
        self._agents = [env.possible_agents[i] if i < len(env.possible_agents) else None for i in range(n)]
        self._prev = [self._race_state(car.race) for car in state.cars]
        self._ended = [not car.racing for car in state.cars]
        self._recorded = [not ended for ended in self._ended]  # whether a car's pose goes in the next row
        self._everyone = [True] * n
        self._ranked = not state.rules.projects_standings  # the standings are the published ranks
        self._scene = scene_of(env) if self.image_every else None  # the writer draws the cameras itself, if set
        self._block_reset()
        cars = [{"id": self.ids[i], "name": car.name, "colour": list(CAR_COLOURS[i % len(CAR_COLOURS)])}
                for i, car in enumerate(state.cars)]
        info = {"track": state.track.name, "reverse": bool(state.track.reverse), "track_length": state.track.length,
                "format": state.rules.name, "laps": state.rules.laps, "dt": state.dt, "cars": cars}
        spec, track = env.car_spec, state.track
        self._writer.send(("start", {
            "application_id": self.application_id, "jpeg_quality": self.jpeg_quality,
            "flush_every": self.flush_every, "scalars": SCALARS, "info": json.dumps(info, indent=1), "cars": cars,
            "half_size": (spec.length / 2, spec.width / 2, spec.height / 2),
            "track": {"center": track.center, "inner": track.inner, "outer": track.outer},
            "obstacles": np.asarray(state.obstacles), "obstacle_size": OBSTACLE_SIZE,
            "layout": self.layout, "cameras": bool(self.image_every), "scene": self._scene}))
        # the grid at step 0
        self._record_step(env, None, {}, None)

    def step(self, env, observations, rewards, infos) -> None:
        self._record_step(env, observations, rewards, infos)
        if len(self._rows) >= SHIP_EVERY:
            self._ship()

    def finish(self, env, result) -> None:
        self._end(json.dumps(result, indent=1) if result is not None else None)

    def close(self) -> None:
        """Finish the recording and put the .rrd in place (atomically: a recording that could not be written
        completely, e.g. on a full disk, is an OutputError and leaves any previous file as it was)."""
        self._end(None)

    def discard(self) -> None:
        """Drop the recording of a race that failed; the target is untouched."""
        if self._writer is not None:
            self._writer.stop()
            self._writer = None
            self._output.discard()

    def log_image(self, entity: str, step: int, race_time: float, image: np.ndarray) -> None:
        """Record an image (uint8, grey or RGB) as a JPEG at `entity`, at `step` / `race_time`."""
        self._pictures.append((int(step), float(race_time), entity, np.array(image)))

    def _end(self, result: str | None) -> None:
        """Send the last rows and `result` (a JSON text, or None), wait for the writer to complete the file,
        then put it in place."""
        if self._writer is None:
            return
        try:
            self._ship()
            self._writer.finish(("finish", result))
        except BaseException:
            self.discard()
            raise
        self.writer_cpu_s = self._writer.cpu_seconds
        self._writer = None
        self._output.commit()

    # --------------------------------------------------------------- helpers
    @staticmethod
    def _race_state(race) -> tuple:
        """What of a car's race record makes an event when it changes (RACE_MARKS)."""
        return race.laps, race.resets, race.penalties, race.penalty_time, len(race.collisions), race.status

    def _block_reset(self) -> None:
        """A block of up to `SHIP_EVERY` rows, one per step (`_record_step` lays a row out), and the images and
        log entries of those steps."""
        self._rows: list[list[float]] = []
        self._images, self._drawn, self._pictures, self._events, self._echoes = [], [], [], [], []

    def _ship(self) -> None:
        """Hand the block to the writer (its rows as one array, `block_columns` splits it there) and start a new
        one."""
        table = np.array(self._rows, np.float64).reshape(len(self._rows), 2 + 9 * self.n)  # (an empty block too)
        self._writer.send(("rows", {
            "table": table, "images": self._images, "drawn": self._drawn, "pictures": self._pictures,
            "events": self._events, "echoes": self._echoes}))
        self._block_reset()

    def _record_step(self, env, observations, rewards, infos) -> None:
        """Add the step's row to the block: its step and time; whether each car is recorded (while it races,
        on the step its run ends, and on the grid at step 0); each car's x, y, yaw and speed; each agent's
        progress, reward and rank; each car's standing. A list: cheaper to grow than arrays to fill."""
        state = env.race_state
        step, cars, agents = state.step, state.cars, self._agents
        infos, rewards, nan = infos or {}, rewards or {}, math.nan
        row = [step, state.time, *(self._recorded if step else self._everyone)]
        for car in cars:
            row += car[2:6]  # x, y, yaw, speed: CarState's fields 2-5
        for agent in agents:
            info = infos.get(agent)
            row += (nan, rewards.get(agent, nan), nan) if info is None else (
                info["progress"], rewards.get(agent, nan), info["rank"])
        row += [car.rank for car in cars] if self._ranked else env.standings()[:self.n]
        self._rows.append(row)
        take_image = bool(self.image_every) and observations is not None and step % self.image_every == 0
        imaged, images = [], []  # the cars whose camera images this step records, and those images
        for i, car in enumerate(cars):
            if self._ended[i]:  # its run ended on an earlier step
                continue
            agent = agents[i]
            if take_image and agent in observations:
                imaged.append(car.index)
                image = self._camera_image(env, car, observations[agent])
                if self._scene is None:
                    images.append(image)
            race = car.race  # (its events this step are its agent's info["events"])
            if infos and (car.events or self._race_state(race) != self._prev[i]):
                self._log_events(env, car, infos)
            if not race.racing:
                self._ended[i], self._recorded[i] = True, False
        if images:  # (carried as a copy: the agents may reuse their arrays)
            self._images.append((len(self._rows) - 1, imaged, self._writer.carry(images)))
        elif imaged:  # the writer draws them from the row's poses (`scene_cameras`): which cars are off the scene
            self._drawn.append((len(self._rows) - 1, imaged, env.world.parked.tolist()))

    def _camera_image(self, env, car, observation) -> np.ndarray:
        """A car's camera image in its observation of this step (its LIDAR echoes are kept for the writer)."""
        state = env.race_state
        if isinstance(observation, dict):  # a LIDAR env: {"camera", "lidar"}
            if env.sensors.lidar == "lidar":  # (SECTOR_LIDAR's 8 sectors have no echo points)
                points = env.lidar.echoes((car.x, car.y, car.yaw), observation["lidar"])
                self._echoes.append((state.step, state.time, car.index, points))
            observation = observation["camera"]
        image = np.asarray(observation)
        if image.ndim == 3 and image.shape[2] == 2:  # a stereo pair: its left camera
            image = image[..., 0]
        return image

    def _log_events(self, env, car, infos) -> None:
        """Text log entries for what changed in a car's race record this step."""
        state = env.race_state
        i, race, name = car.index, car.race, car.name
        now = self._race_state(race)
        prev, now = dict(zip(RACE_MARKS, self._prev[i])), dict(zip(RACE_MARKS, now))
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
            clock = float(clock if clock is not None else 0.0)
            self._events.append((state.step, state.time, i, [entry + (clock,) for entry in entries]))
        self._prev[i] = tuple(now.values())
