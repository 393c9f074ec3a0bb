"""What an entrant is: a `Controller`, the driver (`environment.drivers.Driver`) of one car in a race.

Every entrant (an agent file, a scripted bot, an imported DeepRacer model)
maps its car's camera image (its LIDAR scan too, if it reads one; for bots,
the privileged state in the race's `RaceState`) to a command (steering
degrees, speed m/s). The race env takes those commands as they are
(`COMMAND_SPACE`): each entrant maps its own actions to commands, once. A
controller that must leave the race raises `Forfeit`; the race goes on.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

from ..environment.bots import parse_bot
from ..environment.actions import DRIVER_COMMANDS
from ..environment.drivers import Driver
from ..sensors.suite import SensorSuite

if TYPE_CHECKING:
    from ..environment.race_env import RaceEnv

COMMAND_SPACE = DRIVER_COMMANDS  # what the race env accepts: any DeepRacer command, as its entrant gives it
TEACHER_PREFIX = "teacher:"  # an entrant or expert spec naming an RL teacher file (`racing.teacher_net`)


class Forfeit(Exception):
    """Raised by a controller whose agent must leave the race; the message is the reason."""


class Controller(Driver):
    """An entrant: drives its car from the race state and its observation to a (steering deg, speed m/s) command."""

    name: str = "controller"
    file_sha256: str | None = None
    sensors: SensorSuite = SensorSuite()  # what it reads; the race's env provides what every entrant reads
    env: RaceEnv | None = None  # the race it drives in, and its car there (`reset`)
    car: int = 0

    def reset(self, env: RaceEnv, car: int) -> None:
        """Called at the start of a race with the env and the car index it drives."""
        self.env, self.car = env, car

    def act(self, observation, info) -> tuple[float, float]:
        """This step's command: `drive` on the race state the env published last (none before a race)."""
        return self.drive(self.env.race_state if self.env is not None else None, self.car, observation)


class BotController(Controller):
    """A scripted car (`bot:follow@1.5`, `bot:lanes@1.0`), driving from privileged state."""

    def __init__(self, spec: str):
        self.bot = parse_bot(spec)
        self.name = self.bot.name

    def drive(self, state, car, observation=None):
        return self.bot.drive(state, car)


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


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
