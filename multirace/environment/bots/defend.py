"""``bot:defend@SPEED``: the racing line at up to SPEED m/s, covering the inside of the next corner when followed.

A training opponent for overtaking: alone it drives the racing line (its speed
profile, capped at SPEED); with a car less than `FOLLOWED_WITHIN` behind it
moves across to the inside of the next corner, so a pass must be made round
the outside or on the way out of the corner. It never moves across a car that
already overlaps it (`racingline.line_blocked_alongside`): it keeps side room
to that car instead.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ...sim.racingline import plan_racing_line
from .base import Bot, Situation, speed_in_traffic
from .racingline import line_blocked_alongside, racing_line_command

FOLLOWED_WITHIN = 1.5  # m; a car this close behind is defended against
CORNER_AHEAD = 3.0  # m of racing line looked along for the next corner
CORNER_TURN = 0.35  # rad; the line turning this much within CORNER_AHEAD is a corner
COVER_MARGIN = 0.05  # m between the car's inside and the road's inside edge when it covers


@dataclasses.dataclass
class DefendBot(Bot):
    """The racing line at up to `speed` m/s; followed, the inside of the next corner (`cover_line`)."""

    kind = "defend"

    def steer(self, at):
        cover = cover_line(at) if followed(at) else None
        if cover is None:  # alone: the racing line
            steer, speed = racing_line_command(at, 1.0)
            return steer, min(speed, self.speed)
        hold = line_blocked_alongside(at.track, at.spec, at.proj, cover, at.traffic)  # never across a car beside
        line = plan_racing_line(at.track, at.spec)
        speed = min(self.speed, float(line.speed[line.index_at(at.proj.s)]))
        return at.pursue(speed_in_traffic(speed, at.traffic, at.spec), cover if hold is None else hold)


def followed(at: Situation) -> bool:
    """Whether a car is less than `FOLLOWED_WITHIN` behind (along the track)."""
    return any(-FOLLOWED_WITHIN < at.track.wrap_ds(ahead) < 0.0 for ahead, _, _ in at.traffic)


def cover_line(at: Situation) -> float | None:
    """The lateral offset that covers the inside of the corner within `CORNER_AHEAD` (None: no corner there):
    the car's inside `COVER_MARGIN` from the road's inside edge."""
    line = plan_racing_line(at.track, at.spec)
    ahead = (line.index_at(at.proj.s) + np.arange(int(CORNER_AHEAD / line.spacing))) % len(line.points)
    turn = float(np.sum(line.curvature[ahead] * line.distance[ahead]))  # how far the line turns, + left
    if abs(turn) < CORNER_TURN:
        return None
    left = turn > 0  # turning left: the inside is on the left
    inside = at.proj.left_width if left else at.proj.right_width
    offset = max(0.0, inside - at.spec.width / 2 - COVER_MARGIN)
    return offset if left else -offset
