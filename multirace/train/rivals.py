"""Agent files as rivals in training: cars driven by shipped agents (or any agent file) beside the learners.

A `RivalSeat` is one such car in a training env: a `Driver` holding one
controller per rival agent (`racing.runner.make_controller`, loaded once in
the env's worker) that, at every race start, hands the wheel to one of them
drawn at random. The race env renders the seat's camera (and LIDAR, if its
agents read one) as it would a learner's, and the agent drives from it as it
does in a race. The learners meet the agents they will race in heats and
leagues, camera cars that weave, brake and run wide, not only scripted bots.
`race_opponents` lets a training run's evaluations race them too.
"""
from __future__ import annotations

import numpy as np

from ..environment.bots import parse_bot
from ..environment.drivers import Driver
from ..sensors.suite import race_suite

RIVAL_STEP_BUDGET = 10.0  # s of CPU per inference: a busy training machine must not make a rival forfeit


class RivalSeat(Driver):
    """A car driven, race by race, by one of `specs` (shipped agents' names or agent files), drawn with `rng`."""

    def __init__(self, specs, rng: np.random.Generator, name: str = "rival"):
        from ..racing.runner import make_controller

        if not specs:
            raise ValueError("rivals: name at least one agent (a shipped agent's name or an agent file)")
        for spec in specs:
            if spec.startswith(("bot:", "teacher:")):
                raise ValueError(f"rivals: {spec!r} is not an agent file; scripted cars go in `bots`")
        self.controllers = [make_controller(spec, step_budget=RIVAL_STEP_BUDGET) for spec in specs]
        for spec, controller in zip(specs, self.controllers):
            if getattr(controller, "error", None):
                raise ValueError(f"rivals: {spec}: {controller.error}")
        self.sensors = race_suite(controller.sensors for controller in self.controllers)
        self.rng, self.name = rng, name
        self.driver = self.controllers[0]

    def reset(self, env, car: int) -> None:
        """A new race: one of the rivals, drawn at random, takes the wheel of car `car`."""
        self.driver = self.controllers[int(self.rng.integers(len(self.controllers)))]
        self.driver.reset(env, car)

    def drive(self, state, car, observation=None) -> tuple[float, float]:
        """The drawn agent's command from its car's observation."""
        return self.driver.drive(state, car, observation)


def race_opponents(specs) -> tuple:
    """The cars a training evaluation races against (`eval_bots`): scripted bot specs (``weave@1.2``) as they
    are, agent files and shipped agents' names (``racer``) as their controllers, driving from their own cameras
    (`RaceEnv`'s driver bots)."""
    from ..racing.runner import make_controller

    opponents = []
    for spec in specs:
        try:
            parse_bot(spec)
            opponents.append(spec)
        except ValueError as not_a_bot:
            try:
                opponents.append(make_controller(spec, step_budget=RIVAL_STEP_BUDGET))
            except FileNotFoundError:
                raise ValueError(f"{not_a_bot}; nor is {spec!r} an agent file or a shipped agent's name") from None
    return tuple(opponents)
