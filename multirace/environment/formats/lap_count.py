"""``lap_count``: the most laps in a fixed window (`time_limit`, 120 s). Cars keep lapping until the window
ends, which finishes every run still going; `laps` is no finish line here. Off-tracks cost 2 s and a reset, the
car at fault in a collision pays 5 s, as head-to-head. Ranked by laps, then the race clock (penalties
counted) at each car's last completed lap, then distance driven."""
from __future__ import annotations

import dataclasses

from ..rules import CarRace, RaceRules


@dataclasses.dataclass
class LapCount(RaceRules):
    """Laps in `time_limit` seconds."""

    name: str = "lap_count"
    time_limit: float | None = 120.0
    penalise_striker: bool = True

    projects_standings = False  # no finishing time to project: the standings are the ranking
    solo = False

    def finished(self, race: CarRace) -> bool:
        return False  # only the window ends a run

    def window_end(self) -> tuple[str, str]:
        return "finished", f"{self.time_limit:g} s window ended"

    def rank_key(self, car: CarRace, track_length: float):
        """Laps first, then the race clock at the last completed lap (the earlier, the better), then distance."""
        return (-car.laps, car.lap_start_time if car.laps else 0.0, -(car.distance - car.start_distance))
