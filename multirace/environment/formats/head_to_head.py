"""``head_to_head``: 2-8 cars on a staggered grid; the car at fault in a collision (`rules.at_fault`, the
README's "Race rules") is penalised 5 s once per incident, and a car pushed off track by it pays no off-track
penalty. Ranked by laps, then total time, then progress. The league's heats race it."""
from __future__ import annotations

import dataclasses
import math

from ..rules import CarRace, RaceRules


@dataclasses.dataclass
class HeadToHead(RaceRules):
    """Wheel to wheel: the striker pays, the order is laps first."""

    name: str = "head_to_head"
    penalise_striker: bool = True

    solo = False
    league_stage = "head_to_head"

    def rank_key(self, car: CarRace, track_length: float):
        """Laps first, then total time (finished cars), then distance driven."""
        total = car.finish_time if car.status == "finished" else math.inf
        return (-car.laps, total, -(car.distance - car.start_distance))

    def standings_key(self, projected: float) -> tuple:
        return (-self.laps, projected, 0.0)
