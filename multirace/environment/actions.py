"""Action spaces in DeepRacer's `model_metadata.json` form.

A discrete space is a list of ``{"steering_angle": deg, "speed": m/s}``
entries; a continuous space gives ``{"steering_angle": {"low", "high"},
"speed": {"low", "high"}}`` bounds. Units are DeepRacer's: degrees (+ left)
and metres per second.
"""
from __future__ import annotations

import json
import math
import operator
from pathlib import Path

import numpy as np
from gymnasium import spaces

MAX_STEER_DEG = 30.0
SPEED_RANGE = (0.1, 4.0)
MAX_ACTIONS = 1000  # discrete actions in one space (DeepRacer's consoles offer far fewer)
MAX_METADATA_BYTES = 2**20
DEFAULT_STEERING = (-30.0, -15.0, 0.0, 15.0, 30.0)
DEFAULT_SPEEDS = (0.5, 1.0)


class ActionSpaceError(ValueError):
    """A model_metadata action space is malformed; the message names the file and field."""


class ActionSpace:
    """A DeepRacer action space: maps policy outputs to (steering deg, speed m/s)."""

    def __init__(self, metadata: dict, source: str = "<dict>"):
        self.source = source
        raw = metadata.get("action_space")
        if raw is None:
            raise ActionSpaceError(f"{source}: field 'action_space' is missing")
        implied = "continuous" if isinstance(raw, dict) else "discrete"
        self.kind = str(metadata.get("action_space_type", implied)).lower()
        if self.kind == "discrete":
            self.actions = self._parse_discrete(raw, source)
            self.space = spaces.Discrete(len(self.actions))
        elif self.kind == "continuous":
            self.low, self.high = self._parse_continuous(raw, source)
            self.space = spaces.Box(low=np.array(self.low, np.float32), high=np.array(self.high, np.float32))
        else:
            raise ActionSpaceError(f"{source}: field 'action_space_type' is {self.kind!r}, "
                                   "expected 'discrete' or 'continuous'")

    @staticmethod
    def _check_command(steer, speed, where: str) -> tuple[float, float]:
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in (steer, speed)):
            raise ActionSpaceError(f"{where}: steering_angle and speed must be numbers, got {steer!r:.40} and "
                                   f"{speed!r:.40}")
        steer, speed = float(steer), float(speed)
        if not (math.isfinite(steer) and math.isfinite(speed)):
            raise ActionSpaceError(f"{where}: steering_angle and speed must be finite")
        if abs(steer) > MAX_STEER_DEG:
            raise ActionSpaceError(f"{where}: steering_angle {steer} outside [-30, 30] degrees")
        if not SPEED_RANGE[0] <= speed <= SPEED_RANGE[1]:
            raise ActionSpaceError(f"{where}: speed {speed} outside [{SPEED_RANGE[0]}, {SPEED_RANGE[1]}] m/s")
        return steer, speed

    def _parse_discrete(self, raw, source) -> list[tuple[float, float]]:
        if not isinstance(raw, list) or not raw:
            raise ActionSpaceError(f"{source}: field 'action_space' must be a non-empty list for a discrete space")
        if len(raw) > MAX_ACTIONS:
            raise ActionSpaceError(f"{source}: {len(raw)} discrete actions, more than the {MAX_ACTIONS} allowed")
        actions = []
        for k, entry in enumerate(raw):
            where = f"{source}: action_space[{k}]"
            if not isinstance(entry, dict) or "steering_angle" not in entry or "speed" not in entry:
                raise ActionSpaceError(f"{where}: needs 'steering_angle' and 'speed'")
            if "index" in entry and entry["index"] != k:
                raise ActionSpaceError(f"{where}: 'index' is {entry['index']}, expected {k}")
            actions.append(self._check_command(entry["steering_angle"], entry["speed"], where))
        return actions

    def _parse_continuous(self, raw, source):
        try:
            steer, speed = raw["steering_angle"], raw["speed"]
            low = self._check_command(steer["low"], speed["low"], f"{source}: action_space low")
            high = self._check_command(steer["high"], speed["high"], f"{source}: action_space high")
        except (KeyError, TypeError):
            raise ActionSpaceError(f"{source}: continuous 'action_space' needs steering_angle and speed "
                                   "with 'low' and 'high'") from None
        if low[0] > high[0] or low[1] > high[1]:
            raise ActionSpaceError(f"{source}: action_space low is above high")
        return low, high

    @property
    def discrete(self) -> bool:
        return self.kind == "discrete"

    def command(self, action) -> tuple[float, float]:
        """(steering degrees, speed m/s) for a policy action (index or [steer, speed])."""
        if self.discrete:
            index = action if type(action) is int else self._index(action)  # a plain int: the usual action
            if not 0 <= index < len(self.actions):
                raise ValueError(f"action {index}: out of range; this space has actions 0-{len(self.actions) - 1}")
            return self.actions[index]
        try:
            steer, speed = np.asarray(action, dtype=np.float64).reshape(2)
        except (TypeError, ValueError):
            raise ValueError(f"action {action!r}: expected [steering degrees, speed m/s]") from None
        if not (math.isfinite(steer) and math.isfinite(speed)):
            raise ValueError(f"action {action!r}: steering and speed must be finite numbers")
        return (min(max(float(steer), self.low[0]), self.high[0]),
                min(max(float(speed), self.low[1]), self.high[1]))

    def _index(self, action) -> int:
        """A discrete action given other than as an int (a numpy integer, a one-element index array) as an index."""
        if isinstance(action, np.ndarray) and action.size == 1 and np.issubdtype(action.dtype, np.integer):
            action = action.item()  # a one-element index array, as vectorised policies give
        if isinstance(action, (bool, np.bool_)):
            raise ValueError(f"action {action!r}: expected an integer index 0-{len(self.actions) - 1}")
        try:
            return operator.index(action)
        except TypeError:
            raise ValueError(f"action {action!r}: expected an integer index 0-{len(self.actions) - 1}") from None

    def greedy(self, output):
        """The greedy action for a policy net's output row: the argmax index, or the [steer, speed] mean."""
        if self.discrete:
            return int(np.argmax(output))
        return output[:2]

    def nearest(self, steer_deg: float, speed: float):
        """The action closest to a wanted command (how scripted drivers drive any space)."""
        if not self.discrete:
            return np.array(self.command([steer_deg, speed]), dtype=np.float32)
        table = np.array(self.actions)
        cost = ((table[:, 0] - steer_deg) / 30.0) ** 2 + ((table[:, 1] - speed) / 2.0) ** 2
        return int(np.argmin(cost))

    def label(self, action) -> str:
        """The sim-trace `action` column: the index, or `[steer speed]` for continuous."""
        if self.discrete:
            return str(int(action))
        steer, speed = self.command(action)
        return f"[{steer} {speed}]"

    def to_metadata(self) -> dict:
        """The `action_space` and `action_space_type` fields of model_metadata.json."""
        if self.discrete:
            raw = [{"steering_angle": s, "speed": v, "index": k} for k, (s, v) in enumerate(self.actions)]
        else:
            raw = {"steering_angle": {"low": self.low[0], "high": self.high[0]},
                   "speed": {"low": self.low[1], "high": self.high[1]}}
        return {"action_space": raw, "action_space_type": self.kind}


def default_metadata() -> dict:
    """The default 10-action space: steering {-30,-15,0,15,30} x speed {0.5,1.0}."""
    raw = [{"steering_angle": s, "speed": v} for v in DEFAULT_SPEEDS for s in DEFAULT_STEERING]
    return {"action_space": raw, "action_space_type": "discrete"}


def load_action_space(spec) -> ActionSpace:
    """An ActionSpace from None (default), a model_metadata dict, or a path to model_metadata.json."""
    if spec is None:
        return ActionSpace(default_metadata(), "<default action space>")
    if isinstance(spec, ActionSpace):
        return spec
    if isinstance(spec, dict):
        return ActionSpace(spec, "<action_space dict>")
    path = Path(spec)
    if path.is_dir():
        raise ActionSpaceError(f"{path}: is a folder, not a model_metadata.json file")
    try:
        if path.exists() and not path.is_file():
            raise ActionSpaceError(f"{path}: not a regular file (a device, FIFO or socket)")
        if path.stat().st_size > MAX_METADATA_BYTES:
            raise ActionSpaceError(f"{path}: larger than {MAX_METADATA_BYTES // 2**20} MB; not a model_metadata.json")
        metadata = json.loads(path.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise ActionSpaceError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise ActionSpaceError(f"{path}: not UTF-8 text (model_metadata.json is UTF-8 JSON)") from None
    except json.JSONDecodeError as exc:
        raise ActionSpaceError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise ActionSpaceError(f"{path}: JSON nested too deeply") from None
    except OSError as exc:
        raise ActionSpaceError(f"{path}: cannot be read ({exc.strerror})") from None
    if not isinstance(metadata, dict):
        raise ActionSpaceError(f"{path}: expected a JSON object")
    return ActionSpace(metadata, str(path))


COMMAND_METADATA = {  # any DeepRacer command: what a driver may return
    "action_space": {"steering_angle": {"low": -30.0, "high": 30.0}, "speed": {"low": 0.1, "high": 4.0}},
    "action_space_type": "continuous",
}


class Command(tuple):
    """A driver's command given as a car's action: ``Command((steering degrees, speed m/s))``. A race env takes
    it as that car's command (read through `CommandSpace`) whatever the env's action space."""

    __slots__ = ()


class CommandSpace(ActionSpace):
    """The action space of cars whose drivers give commands: an action is (steering degrees, speed m/s).

    A driver's command (a pair of finite floats inside DeepRacer's command range, a tuple or a `Command`) is
    taken as it is; anything else is read, checked and clipped as a continuous action space's action.
    """

    def __init__(self):
        super().__init__(COMMAND_METADATA, "<driver commands>")

    def command(self, action) -> tuple[float, float]:
        """The command itself for a driver's command; a continuous space's reading of anything else."""
        if type(action) in (tuple, Command) and len(action) == 2:
            steer, speed = action
            # (inside the finite range: a NaN or an infinity fails the comparisons)
            if type(steer) is float and type(speed) is float \
                    and self.low[0] <= steer <= self.high[0] and self.low[1] <= speed <= self.high[1]:
                return action
        return super().command(action)


DRIVER_COMMANDS = CommandSpace()  # how a race env reads a `Command`, whatever its own action space
