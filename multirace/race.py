"""Running a race between entrants (agent files and bots) and writing its result record.

Every entrant is a `Controller` that turns its car's camera image (its LIDAR
scan too, if it reads one; for bots, the privileged state) into a command
(steering degrees, speed m/s).
The env is built with the full continuous command range so that entrants with
different action spaces can race each other; each controller maps its own
actions to commands. A controller that fails forfeits; the race goes on.
"""
from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

from .bots import parse_bot
from .env import RaceEnv

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
    uses_lidar: bool = False  # the race env scans the LIDAR when any entrant reads it

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


def make_controller(spec: str, **agent_options) -> Controller:
    """A controller from `bot:KIND@SPEED` or the path of an agent file."""
    if spec.startswith("bot:"):
        return BotController(spec)
    from .agentfile import AgentController  # torch is only needed for agent files

    return AgentController(Path(spec), **agent_options)


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@dataclasses.dataclass
class RaceConfig:
    """What race to run."""

    track: str = "reinvent_base"
    reverse: bool = False
    race: str = "time_trial"
    laps: int = 3
    seed: int = 0
    obstacles: int | None = None
    max_steps: int | None = None
    renderer: str = "fast"


def run_race(controllers: list[Controller], config: RaceConfig, recorders=()) -> dict:
    """Race `controllers` against each other; returns the result record (DESIGN.md format).

    `recorders` get `start(env)`, `step(env, observations, rewards, infos)` and
    `finish(env, result)` calls (replays, sim-trace logs, videos).
    """
    if not controllers:
        raise ValueError("a race needs at least one entrant")
    env = RaceEnv(track=config.track, reverse=config.reverse, num_cars=len(controllers), race=config.race,
                  laps=config.laps, obstacles=config.obstacles, action_space=COMMAND_SPACE,
                  lidar=any(c.uses_lidar for c in controllers),
                  max_steps=config.max_steps, renderer=config.renderer,
                  car_names=[c.name for c in controllers])
    try:
        observations, infos = env.reset(seed=config.seed)
        for i, controller in enumerate(controllers):
            controller.reset(env, i)
        for recorder in recorders:
            recorder.start(env)
        while env.agents:
            actions = {}
            for i, agent in enumerate(env.possible_agents):
                if not env.races[i].racing:
                    continue
                try:
                    actions[agent] = controllers[i].act(observations[agent], infos[agent])
                except Forfeit as exc:
                    env.forfeit(i, str(exc))
            observations, rewards, _, _, infos = env.step(actions)
            for recorder in recorders:
                recorder.step(env, observations, rewards, infos)
        result = race_result(env, controllers, config)
        for recorder in recorders:
            recorder.finish(env, result)
        return result
    finally:
        env.close()


def race_result(env: RaceEnv, controllers: list[Controller], config: RaceConfig) -> dict:
    """The result record of a finished race."""
    positions = env.ranks()
    cars = []
    for i, race in enumerate(env.races):
        controller = controllers[i]
        cars.append({
            "name": controller.name,
            "file_sha256": controller.file_sha256,
            "position": positions[i],
            "laps": race.laps,
            "lap_times": list(race.lap_times),
            "best_lap": race.best_lap,
            "total_time": race.finish_time,
            "resets": race.resets,
            "penalties": race.penalties,
            "collisions": len(race.collisions),
            "collisions_caused": race.collisions_caused(),
            "progress": round(race.race_progress(env.track.length, env.rules.laps), 2),
            "status": race.status,
            "reason": race.reason,
        })
    cars.sort(key=lambda c: c["position"])
    return {"format": config.race, "track": env.track.name, "reverse": config.reverse, "seed": config.seed,
            "laps": config.laps, "cars": cars}
