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
cars' commands through `actions.CommandSpace`, whose actions are those
commands, and takes an `actions.Command` as the car's command whatever its
action space (how self-play's pool opponents drive beside a learner of
another action space).
"""
from __future__ import annotations

from .race_state import CarState, RaceState


class Driver:
    """A car's driver: `drive` turns the race state (and the car's observation, if it reads one) into a command."""

    name: str = "driver"
    sensors = None  # what it reads beside the race state (a `sensors.suite.SensorSuite`); None: the state alone

    def reset(self, env, car: int) -> None:
        """Called when a race starts, with its env and the index of the car this driver drives."""

    def drive(self, state: RaceState, car: int, observation=None) -> tuple[float, float]:
        """(steering degrees, speed m/s) for car `car` of the race `state`."""
        raise NotImplementedError


def car_pose(car: CarState) -> tuple[float, float, float]:
    """The car's body-centre pose (x, y, yaw), as scripted drivers steer from it."""
    return car.x, car.y, car.yaw
