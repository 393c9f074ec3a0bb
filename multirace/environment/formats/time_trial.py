"""``time_trial``: N laps alone against the clock; an off-track costs 2 s and a reset onto the centre line where
the car left. Ranked by total time (time + penalties)."""
from __future__ import annotations

import dataclasses

from ..rules import RaceRules


@dataclasses.dataclass
class TimeTrial(RaceRules):
    """DeepRacer's time trial: `RaceRules` as it is."""

    name: str = "time_trial"
