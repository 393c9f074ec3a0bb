"""``reset_rule``: the AWS Summit rules, a 4-minute window and up to 3 resets; the next off-track ends the run.
Ranked by best lap, then laps, then progress. The league's time trials race it."""
from __future__ import annotations

import dataclasses
import math

from ..rules import CarRace, RaceRules


@dataclasses.dataclass
class ResetRule(RaceRules):
    """The reset rule: no time penalties, 3 resets, a 240 s window, scored on the best lap."""

    name: str = "reset_rule"
    max_resets: int | None = 3
    time_limit: float | None = 240.0
    off_track_penalty: float = 0.0

    projects_standings = False  # scored on the best lap: the standings are the ranking
    league_stage = "time_trial"

    def rank_key(self, car: CarRace, track_length: float):
        """Best lap first, then laps, then distance driven."""
        best = car.best_lap if car.best_lap is not None else math.inf
        return (best, -car.laps, -(car.distance - car.start_distance))
