"""The driver interface: every car that is not a learner is driven by a `Driver`.

A driver answers one call, ``drive(state, car, observation)``: given the
race's published `RaceState` (``env.race_state``), the index of the car it
drives and, where it reads one, that car's observation (a camera image and
LIDAR scan for an agent file, the privileged state vector for an RL
teacher), it returns the car's command: (steering degrees, speed m/s).
Scripted bots (`environment.bots`), the racing layer's entrants (agent files,
imported DeepRacer models, bots: `racing.entrant.Controller`), DAgger's
experts and the training scenarios' scripted cars are all drivers.

A driver maps its own actions to a command, once: the race env takes its
cars' commands through `CommandSpace`, whose actions are those commands, and
takes a `Command` as the car's command whatever its action space (how
self-play's pool opponents drive beside a learner of another action space).
"""
from __future__ import annotations

import math

from .actions import ActionSpace
from .race_state import CarState, RaceState

COMMAND_METADATA = {  # any DeepRacer command: what a driver may return
    "action_space": {"steering_angle": {"low": -30.0, "high": 30.0}, "speed": {"low": 0.1, "high": 4.0}},
    "action_space_type": "continuous",
}


class Driver:
    """A car's driver: `drive` turns the race state (and the car's observation, if it reads one) into a command."""

    name: str = "driver"

    def drive(self, state: RaceState, car: int, observation=None) -> tuple[float, float]:
        """(steering degrees, speed m/s) for car `car` of the race `state`."""
        raise NotImplementedError


def car_pose(car: CarState) -> tuple[float, float, float]:
    """The car's body-centre pose (x, y, yaw), as scripted drivers steer from it."""
    return car.x, car.y, car.yaw


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
        if type(action) in (tuple, Command) and len(action) == 2 and all(type(value) is float for value in action):
            steer, speed = action
            if math.isfinite(steer) and math.isfinite(speed) and self.low[0] <= steer <= self.high[0] \
                    and self.low[1] <= speed <= self.high[1]:
                return action
        return super().command(action)


DRIVER_COMMANDS = CommandSpace()  # how a race env reads a `Command`, whatever its own action space
