"""DeepRacer reward functions: loading, the default, and the call guard.

A reward function is ``reward_function(params) -> float`` where `params` is
the dict of the 27 keys the DeepRacer simulator passes (see `PARAM_KEYS`), in
DeepRacer's units. A file written for the DeepRacer console runs unchanged:
it is executed as a module and its `reward_function` is used.

A reward function is the user's own code, not data: it may read files and
open sockets. A reward FILE runs in a process of its own (`reward_process`):
a hard time limit per call that the function cannot disarm, nothing of the
run's to reach, and a clear error when that process dies. A researcher's
Python callable runs in-process under a watchdog:
a time limit per call (`CALL_TIME_LIMIT`, SIGALRM, so it holds where the env
runs in a process's main thread) on its own copy of the params. Either way,
every way it can fail (an exception, `sys.exit`, a hang, a value that is not
a finite number in range: DeepRacer requires a float) is a
`RewardFunctionError` naming the file, the step and the car. multirace's own
functions (the default, `BuiltInReward`) are called directly.

The training rewards chosen by name (`multirace train --reward NAME`) are in
`NAMED_REWARDS`, one line each: the built-in ``progress`` (`progress_reward`,
computed by the trainer, its weights in `RewardWeights`) beside the DeepRacer
console's ``centre`` (`follow_centre_line`, run by the env). An env whose
trainer computes its own reward runs `NO_REWARD`: nothing per car per step.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
import os
import signal
import sys
import threading
import time
from typing import Callable

REWARD_LIMIT = 1e5
CALL_TIME_LIMIT = 1.0  # seconds per call of a reward function
LOAD_TIME_LIMIT = 10.0  # seconds to load (execute) a reward file
RETRY_INTERVAL = 0.1  # seconds between repeated timeouts into code that caught the first
GIVE_UP_AFTER = 5.0  # seconds past the limit before the process is ended
TIMEOUT_EXIT_CODE = 124  # exit status then (as timeout(1))

PARAM_KEYS = (
    "all_wheels_on_track", "x", "y", "heading", "distance_from_center", "projection_distance",
    "progress", "steps", "speed", "steering_angle", "track_width", "track_length", "waypoints",
    "closest_waypoints", "is_left_of_center", "is_reversed", "closest_objects", "objects_location",
    "objects_left_of_center", "object_in_camera", "objects_speed", "objects_heading",
    "objects_distance_from_center", "objects_distance", "is_crashed", "is_offtrack", "sim_time",
)


class RewardFunctionError(RuntimeError):
    """A reward function could not be loaded, raised, hung, or returned a bad value."""


class _TimeUp(BaseException):
    """Raised into a reward function that overran its time limit (not an Exception: it must not be caught
    by the function's own `except Exception`)."""


class _Alarm:
    """The SIGALRM timer of the reward watchdog. Its handler is installed once per process (main thread), so
    arming and disarming it around a call are two `setitimer` calls (it runs for every car at every step)."""

    installed = False
    deadline = None  # monotonic time past which a function that keeps swallowing the timeout ends the process
    seconds = 0.0

    @classmethod
    def arm(cls, seconds: float) -> None:
        if not cls.installed:
            signal.signal(signal.SIGALRM, cls.handle)
            cls.installed = True
        cls.seconds, cls.deadline = seconds, time.monotonic() + seconds + GIVE_UP_AFTER
        signal.setitimer(signal.ITIMER_REAL, seconds, RETRY_INTERVAL)

    @classmethod
    def disarm(cls) -> None:
        signal.setitimer(signal.ITIMER_REAL, 0)
        cls.deadline = None

    @classmethod
    def handle(cls, signum, frame):
        if cls.deadline is None:  # a stray alarm after the block ended
            return
        if time.monotonic() > cls.deadline:
            sys.stderr.write(f"multirace: a reward function ignored its {cls.seconds:g} s time limit for "
                             f"{GIVE_UP_AFTER:g} s more (it catches the timeout); stopping the process\n")
            sys.stderr.flush()
            os._exit(TIMEOUT_EXIT_CODE)
        raise _TimeUp()


def private_params(params: dict) -> dict:
    """A copy of the params for one call: its lists are copies too (their items are numbers and tuples)."""
    copy = params.copy()
    for key, value in copy.items():
        if type(value) is list:
            copy[key] = value[:]
    return copy


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


@dataclasses.dataclass
class RewardWeights:
    """The training rewards' weights, in one place (`TrainConfig` has them as settings of the same names)."""

    progress_weight: float = 1.0  # "progress" reward: metres along the centre line per step / (1 m/s * dt)
    centre_weight: float = 0.1  # "progress" reward: bonus of up to this for staying near the centre line
    off_track_penalty: float = 1.0  # "progress" reward: subtracted on an off-track step
    collision_penalty: float = 0.0  # any reward: subtracted per collision the car causes (it struck a car or box)
    proximity_penalty: float = 0.0  # any reward: subtracted per step, up to this, for closing in on a car or box ahead in its lane or running alongside one too close
    proximity_gap: float = 1.0  # metres ahead within which proximity_penalty starts (0 at this gap, full when touching)
    proximity_side_room: float = 0.1  # metres of side room below which a car ahead counts as in the lane, or one alongside as too close
    braking_penalty: float = 0.0  # any reward: subtracted per step, up to this, for closing in on the car or box ahead in its lane faster than it could stop: the braking that would stop it at that car's speed before touching, over the car's braking (full at its braking limit), so it slows early for a slower car rather than rear-ending it

    @classmethod
    def of(cls, settings) -> RewardWeights:
        """The weights of an object that has them as attributes (a `TrainConfig`)."""
        return cls(**{f.name: getattr(settings, f.name) for f in dataclasses.fields(cls)})


def progress_reward(params: dict, gained: float, dt: float, weights: RewardWeights) -> float:
    """The built-in training reward ``progress``: the metres `gained` along the centre line over the step of
    `dt` seconds in units of 1 m/s, plus a bonus of up to `centre_weight` for staying near the centre line,
    minus `off_track_penalty` on an off-track."""
    width = max(params["track_width"], 1e-3)
    centre = max(0.0, 1.0 - 2.0 * params["distance_from_center"] / width)
    reward = weights.progress_weight * gained / dt + weights.centre_weight * centre
    if params["is_offtrack"]:
        reward -= weights.off_track_penalty
    return reward


class RewardFunction:
    """A reward function with a label for error messages (its file, or its name)."""

    def __init__(self, function: Callable[[dict], float], label: str):
        self.function = function
        self.label = label

    def __call__(self, params: dict, step: int, car: str) -> float:
        """Call the function on its own copy of `params`, under the time limit; raise RewardFunctionError
        naming the file, step and car on any failure."""
        main = threading.current_thread() is threading.main_thread()
        start = time.monotonic()
        try:
            if main:
                _Alarm.arm(CALL_TIME_LIMIT)
            try:
                value = self.function(private_params(params))
            finally:
                if main:
                    _Alarm.disarm()
            if time.monotonic() - start > CALL_TIME_LIMIT:  # it caught the timeout and returned late
                raise _TimeUp()
        except _TimeUp:
            raise self._error(f"did not return within {CALL_TIME_LIMIT:g} s", step, car) from None
        except SystemExit as exc:
            raise self._error(f"called sys.exit({exc.code!r})", step, car) from None
        except Exception as exc:
            raise self._error("raised", step, car, f": {type(exc).__name__}: {exc}") from exc
        if type(value) is not float:
            value = self._as_float(value, step, car)
        return self._checked(value, step, car)

    def rewards(self, params_list: list, step: int, cars: list) -> list:
        """The function's values for each car's params at `step` (the cars in order)."""
        return [self(params, step, car) for params, car in zip(params_list, cars)]

    def close(self) -> None:
        """Release what the function holds (nothing, in-process)."""

    def _checked(self, value: float, step: int, car: str) -> float:
        """`value` if it is finite and within the limit, else RewardFunctionError."""
        if not math.isfinite(value) or abs(value) > REWARD_LIMIT:
            raise RewardFunctionError(
                f"reward function {self.label} returned {value} at step {step} for {car}; "
                f"expected a finite number in [-{REWARD_LIMIT:g}, {REWARD_LIMIT:g}]")
        return value

    def _as_float(self, value, step: int, car: str) -> float:
        """A returned value that is not a plain float, as one: any real number but a bool."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise self._error(f"returned {repr(value)[:80]}", step, car,
                              f"; expected a number (DeepRacer requires a float), not a {type(value).__name__}")
        try:
            return float(value)
        except OverflowError:
            raise self._error("returned a number too large for a float", step, car) from None

    def _error(self, what: str, step: int, car: str, detail: str = "") -> RewardFunctionError:
        return RewardFunctionError(f"reward function {self.label} {what} at step {step} for {car}{detail}")


class BuiltInReward(RewardFunction):
    """One of multirace's own reward functions (`follow_centre_line`): trusted code that reads the params and
    returns a float, so it is called directly, without the watchdog's timer or a copy of the params."""

    def __call__(self, params: dict, step: int, car: str) -> float:
        return self.function(params)

    def rewards(self, params_list: list, step: int, cars: list) -> list:
        function = self.function
        return [function(params) for params in params_list]


class NoReward(RewardFunction):
    """The env's reward where the trainer computes its own: every car 0.0, nothing called."""

    def __init__(self):
        super().__init__(None, "none (the trainer computes the reward)")

    def __call__(self, params: dict, step: int, car: str) -> float:
        return 0.0

    def rewards(self, params_list: list, step: int, cars: list) -> list:
        return [0.0] * len(cars)


NO_REWARD = NoReward()


@dataclasses.dataclass(frozen=True)
class NamedReward:
    """A training reward chosen by name: a DeepRacer reward function the env runs for every car
    (`function`), or a reward the trainer computes from each car's params (`trainer`: `progress_reward`'s
    signature; the env then runs `NO_REWARD`)."""

    function: Callable[[dict], float] | None = None
    trainer: Callable[[dict, float, float, RewardWeights], float] | None = None

    def env_reward(self) -> Callable[[dict], float] | RewardFunction:
        """What the env runs for this reward (its `reward_function`)."""
        return NO_REWARD if self.trainer is not None else self.function


NAMED_REWARDS = {  # `--reward NAME`; any other value names a DeepRacer reward .py file
    "progress": NamedReward(trainer=progress_reward),
    "centre": NamedReward(function=follow_centre_line),
}
