"""The experts that label training samples (DAgger, PPO's imitation loss): drivers of one car.

An expert is a `environment.drivers.Driver`: a scripted bot (``pass@1.0``,
``racingline@0.9``; `environment.bots`) drives from the race's `RaceState`,
an RL teacher file (``teacher:PATH``, `racing.teacher_net`) from its car's privileged
state vector (`environment.state.car_features`), the observation it reads.
"""
from __future__ import annotations

import numpy as np

from ..environment.bots import PassBot, parse_bot
from ..environment.drivers import Driver
from ..environment.state import ahead_in_camera, slowed_ahead
from ..racing.entrant import TEACHER_PREFIX, teacher_spec
from ..racing.teacher_net import TeacherDriver


def make_expert(spec: str | None, default_speed: float) -> Driver:
    """The expert `spec` names: ``teacher:PATH`` (``teacher:PATH@SCALE``: at that share of its speed), a bot
    spec, or (None or "") the pass bot at `default_speed`."""
    if spec and spec.startswith(TEACHER_PREFIX):
        path, scale = teacher_spec(spec)
        return TeacherDriver.load(path, scale)
    return parse_bot(spec) if spec else PassBot(speed=float(default_speed))


def expert_command(expert: Driver, env, car: int = 0) -> tuple[float, float]:
    """(steering degrees, speed m/s) the expert commands for the env's car `car` where it stands now."""
    return expert_commands(expert, env, [car])[0]


def expert_commands(expert: Driver, env, cars, ahead_speed: float | None = None,
                    ahead_seen: bool = False) -> list[tuple[float, float]]:
    """`expert_command` for each of the env's `cars`; a teacher's net runs once for all of them. `ahead_speed`
    (m/s, a teacher only): the teacher takes the cars ahead of each to drive no faster than that
    (`state.slowed_ahead`); with `ahead_seen`, only the cars ahead that the car's front camera shows."""
    if isinstance(expert, TeacherDriver):
        states = np.stack([env.car_state(car, expert.view) for car in cars])
        if ahead_speed is not None:
            shown = [ahead_in_camera(env, car) for car in cars] if ahead_seen and expert.view == "all" else None
            states = slowed_ahead(states, ahead_speed, shown)
        return expert.drive_many(states)
    return [expert.drive(env.race_state, car, None) for car in cars]
