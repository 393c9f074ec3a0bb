"""``object_avoidance``: a time trial with static boxes in alternating lanes; a crash into a box costs 5 s and a
reset `reset_behind_obstacle` (1.0 m) behind the box in the other lane."""
from __future__ import annotations

import dataclasses

from ..rules import RaceRules


@dataclasses.dataclass
class ObjectAvoidance(RaceRules):
    """The time trial with 3 boxes (0-6) that reset a car that hits one."""

    name: str = "object_avoidance"
    obstacles: int = 3

    crash_resets = True
