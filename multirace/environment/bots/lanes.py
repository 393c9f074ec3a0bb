"""``bot:lanes@SPEED``: changes lane every `lane_period` seconds at SPEED m/s."""
from __future__ import annotations

import dataclasses

from .base import Bot, speed_in_traffic


@dataclasses.dataclass
class LanesBot(Bot):
    """The middle of the left lane, then of the right one, `lane_period` seconds each, slowing behind a car."""

    lane_period: float = 4.0  # seconds between lane changes
    kind = "lanes"

    def steer(self, at):
        lane = int(at.time // self.lane_period) % 2
        lateral = (at.proj.left_width if lane == 0 else -at.proj.right_width) / 2
        return at.pursue(speed_in_traffic(self.speed, at.traffic, at.spec), lateral)
