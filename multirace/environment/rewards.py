"""DeepRacer reward functions: loading, the default, and the call guard.

A reward function is ``reward_function(params) -> float`` where `params` is
the dict of the 27 keys the DeepRacer simulator passes (see `PARAM_KEYS`), in
DeepRacer's units. A file written for the DeepRacer console runs unchanged:
it is executed as a module and its `reward_function` is used.
"""
from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from typing import Callable

REWARD_LIMIT = 1e5

PARAM_KEYS = (
    "all_wheels_on_track", "x", "y", "heading", "distance_from_center", "projection_distance",
    "progress", "steps", "speed", "steering_angle", "track_width", "track_length", "waypoints",
    "closest_waypoints", "is_left_of_center", "is_reversed", "closest_objects", "objects_location",
    "objects_left_of_center", "object_in_camera", "objects_speed", "objects_heading",
    "objects_distance_from_center", "objects_distance", "is_crashed", "is_offtrack", "sim_time",
)


class RewardFunctionError(RuntimeError):
    """A reward function could not be loaded, raised, or returned a bad value."""


def follow_centre_line(params: dict) -> float:
    """The DeepRacer console's default example: reward staying near the centre line."""
    track_width = params["track_width"]
    distance_from_center = params["distance_from_center"]
    marker_1 = 0.1 * track_width
    marker_2 = 0.25 * track_width
    marker_3 = 0.5 * track_width
    if distance_from_center <= marker_1:
        reward = 1.0
    elif distance_from_center <= marker_2:
        reward = 0.5
    elif distance_from_center <= marker_3:
        reward = 0.1
    else:
        reward = 1e-3  # likely crashed / close to off track
    return float(reward)


class RewardFunction:
    """A reward function with a label for error messages (its file, or its name)."""

    def __init__(self, function: Callable[[dict], float], label: str):
        self.function = function
        self.label = label

    def __call__(self, params: dict, step: int, car: str) -> float:
        """Call the function; raise RewardFunctionError naming the file, step and car on failure."""
        try:
            value = self.function(params)
        except Exception as exc:
            raise RewardFunctionError(
                f"reward function {self.label} raised at step {step} for {car}: "
                f"{type(exc).__name__}: {exc}") from exc
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise RewardFunctionError(
                f"reward function {self.label} returned {value!r} at step {step} for {car}; "
                "expected a number") from None
        if not math.isfinite(value) or abs(value) > REWARD_LIMIT:
            raise RewardFunctionError(
                f"reward function {self.label} returned {value} at step {step} for {car}; "
                f"expected a finite number in [-{REWARD_LIMIT:g}, {REWARD_LIMIT:g}]")
        return value

    def __getstate__(self):
        # functions loaded from files are re-loaded in worker processes
        if self.label.endswith(".py") and Path(self.label).exists():
            return {"label": self.label}
        return self.__dict__

    def __setstate__(self, state):
        if "function" not in state:
            state = load_reward_function(state["label"]).__dict__
        self.__dict__.update(state)


def load_reward_function(spec=None) -> RewardFunction:
    """A RewardFunction from None (the console default), a callable, or a path to a `.py` file."""
    if spec is None:
        return RewardFunction(follow_centre_line, "follow_centre_line (default)")
    if isinstance(spec, RewardFunction):
        return spec
    if callable(spec):
        return RewardFunction(spec, getattr(spec, "__name__", repr(spec)))
    path = Path(spec)
    if not path.is_file():
        raise RewardFunctionError(f"reward function file {path}: no such file")
    module_name = f"multirace_reward_{abs(hash(str(path.resolve())))}"
    try:
        module_spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(module_spec)
        sys.modules[module_name] = module
        module_spec.loader.exec_module(module)
    except Exception as exc:
        raise RewardFunctionError(f"reward function file {path}: cannot be loaded: "
                                  f"{type(exc).__name__}: {exc}") from exc
    function = getattr(module, "reward_function", None)
    if not callable(function):
        raise RewardFunctionError(f"reward function file {path}: defines no reward_function(params)")
    return RewardFunction(function, str(path))
