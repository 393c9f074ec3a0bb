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

from ..environment.race_env import RaceEnv
from ..resources import resolve_agent_path
from ..sensors.suite import race_suite
from .entrant import COMMAND_SPACE, TEACHER_PREFIX, BotController, Controller, Forfeit


def make_controller(spec: str, **agent_options) -> Controller:
    """A controller from `bot:KIND@SPEED`, `teacher:PATH` (an RL teacher file, `racing.teacher_net`), the
    path of an agent file, or a shipped agent's name (`dagger_fast`)."""
    if spec.startswith("bot:"):
        return BotController(spec)
    if spec.startswith(TEACHER_PREFIX):
        from .teacher_net import TeacherController

        return TeacherController.load(spec)
    from .agentfile import AgentController  # torch is only needed for agent files

    return AgentController(resolve_agent_path(spec), **agent_options)


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
    bots: tuple = ()  # cars the env drives after the entrants: bot specs (`follow@0.8`) or `Driver`s (RaceEnv)
    randomize: str | dict | None = None  # domain randomisation (see environment.randomize)
    camera: tuple = (120, 160)  # (height, width) of every entrant's camera
    grayscale: bool = True
    start: tuple = ()  # ((car, (arc length, lateral offset)), ...): set-up starts instead of the grid (scenarios)


def run_race(controllers: list[Controller], config: RaceConfig, recorders=()) -> dict:
    """Race `controllers` against each other; returns the result record.

    The record: {"format", "track", "reverse", "seed", "laps", "cars": [{"car", "name", "file_sha256",
    "position", "laps", "lap_times", "best_lap", "total_time", "resets", "off_tracks", "penalties",
    "collisions", "collisions_caused", "progress", "status", "reason"}]} in finishing order.

    `recorders` get `start(env)`, `step(env, observations, rewards, infos)` and
    `finish(env, result)` calls (replays, sim-trace logs, videos).
    """
    if not controllers:
        raise ValueError("a race needs at least one entrant")
    env = RaceEnv(track=config.track, reverse=config.reverse, num_cars=len(controllers), race=config.race,
                  laps=config.laps, obstacles=config.obstacles, bots=config.bots, action_space=COMMAND_SPACE,
                  sensor=race_suite(c.sensors for c in controllers).names, randomize=config.randomize,
                  camera=config.camera, grayscale=config.grayscale,
                  max_steps=config.max_steps, renderer=config.renderer,
                  car_names=[c.name for c in controllers])
    try:
        observations, infos = env.reset(seed=config.seed)
        if config.start:
            observations = env.move_cars(dict(config.start), clear=False)
            infos = env.standing_infos()
        for i, controller in enumerate(controllers):
            controller.reset(env, i)
        for recorder in recorders:
            recorder.start(env)
        while env.agents:
            actions = {}
            for i, agent in enumerate(env.possible_agents):
                if not env.race_state.cars[i].racing:
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
    except BaseException:  # a race that failed (or was interrupted) leaves no half-written recording
        for recorder in recorders:
            getattr(recorder, "discard", lambda: None)()
        raise
    finally:
        env.close()


def race_result(env: RaceEnv, controllers: list[Controller], config: RaceConfig) -> dict:
    """The result record of a finished race (from its last `RaceState`): every car, the entrants' and the env's
    bots, in finishing order."""
    state = env.race_state
    cars = []
    for i, car in enumerate(state.cars):
        race = car.race
        cars.append({
            "car": f"car_{i}",  # its slot: entrants first, in the order given, then the env's bots
            "name": car.name,
            "file_sha256": controllers[i].file_sha256 if i < len(controllers) else None,
            "position": car.rank,
            "laps": race.laps,
            "lap_times": list(race.lap_times),
            "best_lap": race.best_lap,
            "total_time": race.finish_time,
            "resets": race.resets,
            "off_tracks": race.off_tracks,
            "penalties": race.penalties,
            "collisions": len(race.collisions),
            "collisions_caused": race.collisions_caused(),
            "progress": round(race.race_progress(state.track.length, state.rules.laps), 2),
            "status": race.status,
            "reason": race.reason,
        })
    cars.sort(key=lambda c: c["position"])
    return {"format": config.race, "track": state.track.name, "reverse": config.reverse, "seed": config.seed,
            "laps": config.laps, "cars": cars}
