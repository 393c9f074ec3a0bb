"""What an entrant is: a `Controller` that turns its car's observation into a command.

Every entrant (an agent file, a scripted bot, an imported DeepRacer model)
maps its car's camera image (its LIDAR scan too, if it reads one; for bots,
the privileged state) to a command (steering degrees, speed m/s). A
controller that must leave the race raises `Forfeit`; the race goes on.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

from ..environment.bots import parse_bot
from ..sensors.suite import SensorSuite

if TYPE_CHECKING:
    from ..environment.race_env import RaceEnv

COMMAND_SPACE = {  # what the race env accepts: any DeepRacer command
    "action_space": {"steering_angle": {"low": -30.0, "high": 30.0}, "speed": {"low": 0.1, "high": 4.0}},
    "action_space_type": "continuous",
}


class Forfeit(Exception):
    """Raised by a controller whose agent must leave the race; the message is the reason."""


class Controller:
    """An entrant: maps its car's observation to a (steering deg, speed m/s) command."""

    name: str = "controller"
    file_sha256: str | None = None
    sensors: SensorSuite = SensorSuite()  # what it reads; the race's env provides what every entrant reads

    def reset(self, env: RaceEnv, car: int) -> None:
        """Called at the start of a race with the env and the car index it drives."""
        self.env, self.car = env, car

    def act(self, observation, info) -> tuple[float, float]:
        raise NotImplementedError


class BotController(Controller):
    """A scripted car (`bot:follow@1.5`, `bot:lanes@1.0`), driving from privileged state."""

    def __init__(self, spec: str):
        self.bot = parse_bot(spec)
        self.name = self.bot.name

    def act(self, observation, info):
        env, i = self.env, self.car
        return self.bot.command(env.track, env.car_spec, env.world.poses[i], env.sim_time,
                                env.races[i].segment_hint, env.traffic(i))


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
