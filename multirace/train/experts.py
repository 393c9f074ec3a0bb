"""The experts that label training samples (DAgger, PPO's imitation loss): drivers of one car.

An expert is a `environment.drivers.Driver`: a scripted bot (``pass@1.0``,
``racingline@0.9``; `environment.bots`) drives from the race's `RaceState`,
an RL teacher file (``teacher:PATH``, `teacher.py`) from its car's privileged
state vector (`environment.state.car_features`), the observation it reads.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..environment.bots import PassBot, parse_bot
from ..environment.drivers import Driver

TEACHER_PREFIX = "teacher:"  # an expert spec naming a teacher file (`teacher.py`) instead of a bot


class TeacherDriver(Driver):
    """An RL teacher's state policy (`teacher_net.StatePolicyNet`), driving from its car's privileged state;
    `speed_scale` < 1 asks for that share of the teacher's speed (a margin for a student that sees less)."""

    def __init__(self, path, speed_scale: float = 1.0):
        from .teacher_net import load_teacher

        if not 0.0 < speed_scale <= 1.0:
            raise ValueError(f"expert {TEACHER_PREFIX}{path}@{speed_scale:g}: the speed scale must be in (0, 1]")
        self.net = load_teacher(path)
        self.speed_scale = float(speed_scale)
        self.low_speed = float(self.net.space.low[1])
        self.name = f"{TEACHER_PREFIX}{Path(path).name}" + (f"@{speed_scale:g}" if speed_scale != 1.0 else "")

    def drive(self, state, car, observation=None) -> tuple[float, float]:
        """The teacher's command from `observation`, its car's privileged state vector."""
        return self.drive_many(observation[None])[0]

    def drive_many(self, observations: np.ndarray) -> list[tuple[float, float]]:
        """The teacher's commands for several cars' state vectors (N, features), in one pass of its net."""
        return [(steer, max(self.low_speed, speed * self.speed_scale))
                for steer, speed in self.net.command(observations).tolist()]


def make_expert(spec: str | None, default_speed: float) -> Driver:
    """The expert `spec` names: ``teacher:PATH`` (``teacher:PATH@SCALE``: at that share of its speed), a bot
    spec, or (None or "") the pass bot at `default_speed`."""
    if spec and spec.startswith(TEACHER_PREFIX):
        path, scale = teacher_spec(spec)
        return TeacherDriver(path, scale)
    return parse_bot(spec) if spec else PassBot(speed=float(default_speed))


def teacher_spec(spec: str) -> tuple[str, float]:
    """(path, speed scale) of ``teacher:PATH`` or ``teacher:PATH@SCALE``."""
    path = spec[len(TEACHER_PREFIX):]
    head, at, tail = path.rpartition("@")
    if at:
        try:
            return head, float(tail)
        except ValueError:
            pass  # an "@" inside the file's path
    return path, 1.0


def expert_command(expert: Driver, env, car: int = 0) -> tuple[float, float]:
    """(steering degrees, speed m/s) the expert commands for the env's car `car` where it stands now."""
    return expert_commands(expert, env, [car])[0]


def expert_commands(expert: Driver, env, cars) -> list[tuple[float, float]]:
    """`expert_command` for each of the env's `cars`; a teacher's net runs once for all of them."""
    if isinstance(expert, TeacherDriver):
        return expert.drive_many(np.stack([env.car_state(car) for car in cars]))
    return [expert.drive(env.race_state, car, None) for car in cars]
