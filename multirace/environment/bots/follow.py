"""``bot:follow@SPEED``: keeps the centre line at SPEED m/s, slowing behind a car in its way."""
from __future__ import annotations

import dataclasses

from .base import Bot, speed_in_traffic


@dataclasses.dataclass
class FollowBot(Bot):
    """The centre line at `speed`; it takes the pace of a slower car ahead instead of running into it."""

    kind = "follow"

    def steer(self, at):
        return at.pursue(speed_in_traffic(self.speed, at.traffic, at.spec), 0.0)
