"""DeepRacer sim-trace CSV logs, so the community's log-analysis tools work on our runs.

The file has exactly DeepRacer's sim-trace columns (`SIMTRACE_COLUMNS`), with
DeepRacer's units and meanings (see ../shared/formats/README.md):

``X, Y``             the reward params `x, y` (DeepRacer's reported point), metres
``yaw``              the params `heading`, degrees
``steer, throttle``  the commanded action (deg, m/s): exactly the action space's entry for a
                     discrete action, never the noisy values the car executed
``action``           the action index for a discrete space, else ``[steer throttle]``
``progress``         params `progress`, 0-100 % of the current lap (100 on a lap_complete row)
``closest_waypoint`` the nearer of params `closest_waypoints`
``tstamp``           simulated time, seconds
``episode_status``   prepare (first step), in_progress, off_track, crashed,
                     lap_complete, time_up, park (run ended otherwise: forfeit,
                     step limit)
``pause_duration``   penalty seconds added on that step

No extra column is written (older deepracer-utils releases read these files
positionally, so an added column would shift theirs). In a race log every
car's run is one *episode*: the
``episode`` column is the car's slot (car_0 -> 0, car_1 -> 1, ...), so
deepracer-utils' per-episode analysis gives per-car analysis. One row per car
per step while the car races (and on the step its run ends, with done=True).

`SimTraceRecorder(path, controllers)` is a race recorder for
`run_race(controllers, ..., recorders=[...])`: it notes each controller's
command as it is given (and, for an agent with a discrete action space, its
index). `SimTraceWriter` writes rows from a training loop, one
`write_step(info, ..., action=, command=)` per car and step, with `info` the
env's info dict of that car (the 27 reward params plus race keys). Only cars
with infos (learning cars) are logged.
"""
from __future__ import annotations

import array
import csv
import io
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..atomic import AtomicOutput
from .files import regular_file

SIMTRACE_COLUMNS = ("episode", "steps", "X", "Y", "yaw", "steer", "throttle", "action", "reward", "done",
                    "all_wheels_on_track", "progress", "closest_waypoint", "track_len", "tstamp",
                    "episode_status", "pause_duration")
EPISODE_STATUSES = ("prepare", "in_progress", "off_track", "crashed", "reversed", "immobilized",
                    "lap_complete", "time_up", "pause", "park")


def episode_status(info: dict) -> str:
    """DeepRacer's `episode_status` of one step from the env's info dict."""
    events = info.get("events", ())
    status = info.get("status", "racing")
    if "off_track" in events:
        return "off_track"
    if "crashed" in events:
        return "crashed"
    if "lap_complete" in events or status == "finished":
        return "lap_complete"
    if status == "timed_out":
        return "time_up"
    if status == "out_of_resets":
        return "off_track"
    if status in ("forfeit", "not_finished"):
        return "park"
    if int(info.get("steps", 0)) <= 1:
        return "prepare"
    return "in_progress"


def closest_waypoint(info: dict) -> int:
    """The nearer of the two waypoints around the car (DeepRacer's sim-trace `closest_waypoint`)."""
    prev_i, next_i = (int(v) for v in info["closest_waypoints"])
    waypoints = info["waypoints"]
    x, y = info["x"], info["y"]
    d_prev = math.hypot(waypoints[prev_i][0] - x, waypoints[prev_i][1] - y)
    d_next = math.hypot(waypoints[next_i][0] - x, waypoints[next_i][1] - y)
    return prev_i if d_prev <= d_next else next_i


def simtrace_row(info: dict, *, episode: int, reward: float, action=None, done: bool = False,
                 pause_duration: float = 0.0, command=None) -> list:
    """One sim-trace row (values in `SIMTRACE_COLUMNS` order) from a car's info dict of one step.

    `action`: the discrete action index, or None for a continuous command (written `[steer speed]`).
    `command`: the commanded (steering degrees, speed m/s); without it, the info's executed values.
    """
    steer, speed = (float(v) for v in command) if command is not None else (float(info["steering_angle"]),
                                                                           float(info["speed"]))
    if isinstance(action, (int, np.integer)) and not isinstance(action, bool):
        action_text = str(int(action))
    else:
        action_text = f"[{steer} {speed}]"
    status = episode_status(info)
    # DeepRacer logs progress 100 on the step that completes the lap
    progress = 100.0 if status == "lap_complete" else float(info["progress"])
    return [int(episode), float(info["steps"]), float(info["x"]), float(info["y"]), float(info["heading"]),
            steer, speed, action_text, float(reward), bool(done), bool(info["all_wheels_on_track"]),
            progress, closest_waypoint(info), float(info["track_length"]),
            round(float(info["sim_time"]), 6), status, float(pause_duration)]


class SimTraceStep(NamedTuple):
    """One car's sim-trace row formatted where the car runs (a training worker, `CarSimTrace`): the row's CSV
    text after its episode column, and what a training log's metrics need (`TrainingLog.write_text`)."""

    text: str
    sim_time: float
    status: str  # the row's episode_status
    progress: float  # the info's progress, 0-100


class CarSimTrace:
    """Formats one car's sim-trace rows, episode after episode, as `SimTraceWriter.write_step` would write them
    (the pause of each row is the penalty added since the car's last row of the episode; a row with `done`
    ends the episode). A training worker formats its cars' rows so the learner only writes them."""

    def __init__(self):
        self._penalty = 0.0  # penalty seconds seen so far in the car's episode
        self._buffer = io.StringIO()
        self._csv = csv.writer(self._buffer)

    def step(self, info: dict, *, reward: float, done: bool, action=None, command=None) -> SimTraceStep:
        """This step's row (arguments as `simtrace_row`'s)."""
        penalty = float(info.get("penalty_time", 0.0))
        pause = max(penalty - self._penalty, 0.0)
        self._penalty = 0.0 if done else penalty
        row = simtrace_row(info, episode=0, reward=reward, action=action, done=done, pause_duration=round(pause, 6),
                           command=command)
        self._buffer.seek(0)
        self._buffer.truncate()
        self._csv.writerow(row[1:])
        return SimTraceStep(self._buffer.getvalue(), float(info["sim_time"]), row[15], float(info["progress"]))


class SimTraceWriter:
    """Writes a sim-trace CSV row by row (usable from training loops).

    ``with SimTraceWriter("0-iteration.csv") as log: log.write_step(info, reward=r, episode=e)``
    """

    def __init__(self, path):
        self.path = Path(path)
        self._output = AtomicOutput(self.path)  # the rows go beside the target; `close()` puts the file in place
        with self._output.guard():
            self._file = open(self._output.tmp, "w", newline="")
        self._csv = csv.writer(self._file)
        self._csv.writerow(SIMTRACE_COLUMNS)
        self._penalty: dict = {}  # episode -> penalty_time seen so far
        self.rows = 0

    def write_step(self, info: dict, *, reward: float, episode: int, action=None, done: bool | None = None,
                   command=None) -> None:
        """Log one step of one car. `done` defaults to "the car's run is over" (info status); `action` is the
        discrete index (None: continuous) and `command` the commanded (steer deg, speed m/s)."""
        penalty = float(info.get("penalty_time", 0.0))
        pause = max(penalty - self._penalty.get(episode, 0.0), 0.0)
        self._penalty[episode] = penalty
        if done is None:
            done = info.get("status", "racing") != "racing"
        row = simtrace_row(info, episode=episode, reward=reward, action=action, done=done,
                           pause_duration=round(pause, 6), command=command)
        with self._output.guard():
            self._csv.writerow(row)
        self.rows += 1

    def write_text(self, episode: int, text: str) -> None:
        """Log a row formatted elsewhere (`CarSimTrace`): its text after the episode column."""
        with self._output.guard():
            self._file.write(f"{int(episode)},{text}")
        self.rows += 1

    def new_episode(self, episode: int) -> None:
        """Forget penalty bookkeeping for an episode number that is reused (a new env episode)."""
        self._penalty.pop(episode, None)

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        """Finish the file and put it in place (atomically)."""
        if self._file.closed:
            return
        with self._output.guard():
            self._file.close()
        self._output.commit()

    def discard(self) -> None:
        """Drop the file being written (a failed run); the target is untouched."""
        if not self._file.closed:
            try:
                self._file.close()
            except OSError:
                pass
        self._output.discard()

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is None:
            self.close()
        else:
            self.discard()


class CommandTap:
    """Stands in for a race controller and notes each command it gives (and its discrete action index).

    The index is None for an agent with a continuous action space (the row's action is then
    ``[steer throttle]``, as DeepRacer writes it) and -1 for a controller without an action space
    (a scripted bot), deepracer-utils' value for "no action index", so that a bot's rows leave the
    agents' action breakdown intact.
    """

    def __init__(self, controller):
        self.controller = controller
        self.command = None  # the last (steer deg, speed m/s) given
        self.index = None  # its action index, for an agent with a discrete action space

    def __getattr__(self, name):
        return getattr(self.controller, name)

    def reset(self, env, car: int) -> None:
        self.command = self.index = None
        self.controller.reset(env, car)

    def act(self, observation, info):
        self.command = self.index = None
        command = self.controller.act(observation, info)
        self.command = tuple(float(v) for v in command)
        space = getattr(getattr(self.controller, "agent", None), "action_space", None)
        if space is None:
            self.index = -1
        elif space.discrete and self.command in space.actions:
            self.index = space.actions.index(self.command)
        return command


class SimTraceRecorder:
    """Race recorder writing a DeepRacer sim-trace CSV: one row per car per step, episode = car slot.

    Given the race's `controllers` list, it puts a `CommandTap` in place of each (in that list), so the
    rows hold the commanded steer and throttle and, for agents with discrete action spaces, the action
    index, as DeepRacer's do. Without it, the rows hold the commands as the env reports them.
    """

    def __init__(self, path, controllers: list | None = None):
        self.path = Path(path)
        self.writer: SimTraceWriter | None = None
        self.taps = []
        if controllers is not None:
            controllers[:] = self.taps = [CommandTap(c) for c in controllers]

    def start(self, env) -> None:
        self.writer = SimTraceWriter(self.path)
        self._ended = [not car.racing for car in env.race_state.cars]

    def step(self, env, observations, rewards, infos) -> None:
        for i, agent in enumerate(env.possible_agents):
            if self._ended[i] or agent not in infos:
                continue
            racing = env.race_state.cars[i].racing
            tap = self.taps[i] if i < len(self.taps) else None
            self.writer.write_step(infos[agent], reward=float(rewards.get(agent, 0.0)), episode=i,
                                   done=not racing, action=tap.index if tap else None,
                                   command=tap.command if tap else None)
            if not racing:
                self._ended[i] = True

    def finish(self, env, result) -> None:
        if self.writer is not None:
            self.writer.close()

    def discard(self) -> None:
        """Drop the sim-trace of a race that failed."""
        if self.writer is not None:
            self.writer.discard()


MAX_LINE = 1 << 20  # characters in one line of a sim-trace; a longer one is not a sim-trace
REQUIRED_COLUMNS = ("episode", "steps", "X", "Y", "track_len")
MAX_COLUMN_ROWS = 10_000_000  # rows `read_simtrace_columns` reads (about 50 bytes of memory each)


def _lines(file, path):
    """The file's lines, none longer than `MAX_LINE` (a file of one endless line is refused, not read whole)."""
    number = 0
    while True:
        line = file.readline(MAX_LINE + 1)
        if not line:
            return
        number += 1
        if len(line) > MAX_LINE:
            raise ValueError(f"sim-trace {path} line {number}: longer than {MAX_LINE} characters; "
                             "not a DeepRacer sim-trace CSV")
        yield line


def simtrace_records(path, required=REQUIRED_COLUMNS):
    """Stream the raw rows (dicts of text) of a sim-trace CSV, one at a time, with the line each is on; a
    one-line ValueError naming the file (and line) for anything that is not a sim-trace with `required`."""
    path = regular_file(path, "sim-trace")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(_lines(f, path))
            missing = [c for c in required if c not in (reader.fieldnames or ())]
            if missing:
                raise ValueError(f"{path}: not a DeepRacer sim-trace CSV (no column {', '.join(missing)})")
            for raw in reader:
                yield reader.line_num, raw
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a DeepRacer sim-trace CSV (not UTF-8 text)") from None
    except csv.Error as exc:
        raise ValueError(f"sim-trace {path}: not a readable CSV ({exc})") from None


def read_simtrace(path) -> list[dict]:
    """Rows of a sim-trace CSV as dicts with numbers and booleans parsed (no pandas needed)."""
    return [_parsed(raw, path) for _, raw in simtrace_records(path)]


def read_simtrace_columns(path, numbers: tuple, required=REQUIRED_COLUMNS) -> dict:
    """Chosen columns of a sim-trace as arrays, streamed (memory: 8 bytes per value, not a dict per row):
    `numbers` as float64, each finite, plus ``episode`` (int64) and ``off`` (the step went off track or
    crashed). Any value that is not a finite number is a one-line error naming the file, line and column."""
    columns = {key: array.array("d") for key in numbers}
    episodes, off = array.array("q"), array.array("b")
    for line, raw in simtrace_records(path, required=tuple(dict.fromkeys(required + numbers))):
        if len(episodes) >= MAX_COLUMN_ROWS:
            raise ValueError(f"sim-trace {path}: over {MAX_COLUMN_ROWS:,} rows; this reads at most that many")
        for key, column in columns.items():
            try:
                value = float(raw[key])
            except (TypeError, ValueError):
                value = math.nan
            if not math.isfinite(value):
                raise ValueError(f"sim-trace {path} line {line}: column {key} is {str(raw[key])[:40]!r}, "
                                 "not a finite number")
            column.append(value)
        try:
            episodes.append(int(float(raw["episode"])))
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"sim-trace {path} line {line}: column episode is {str(raw['episode'])[:40]!r}, "
                             "not a whole number") from None
        off.append(raw.get("episode_status") in ("off_track", "crashed"))
    arrays = {key: np.frombuffer(column, dtype=np.float64) for key, column in columns.items()}
    arrays["episode"] = np.frombuffer(episodes, dtype=np.int64)
    arrays["off"] = np.frombuffer(off, dtype=np.int8).astype(bool)
    return arrays


def _parsed(raw: dict, path) -> dict:
    """One sim-trace row with its numbers and booleans parsed."""
    row = dict(raw)
    try:
        for key in ("steps", "X", "Y", "yaw", "steer", "throttle", "reward", "progress", "track_len",
                    "tstamp", "pause_duration"):
            if key in row and row[key] not in (None, ""):
                row[key] = float(row[key])
        for key in ("episode", "closest_waypoint"):
            if key in row and row[key] not in (None, ""):
                row[key] = int(float(row[key]))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: a sim-trace row has a value that is not a number ({exc})") from None
    for key in ("done", "all_wheels_on_track"):
        if key in row:
            row[key] = str(row[key]).strip() == "True"
    return row
