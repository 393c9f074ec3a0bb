"""``bot:racingline[@SCALE]``: the track's racing line at the fastest speeds the tyres and drive train allow.

`sim.racingline` plans the line; SCALE (0.1-1.0, default 1.0) scales its speed
profile (``@0.8`` is a gentler driver): every track's reference lap.
"""
from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

from ...sim.car import CarSpec
from ...sim.racingline import plan_racing_line
from .base import Bot, Situation, pursuit_steer, speed_in_traffic
from .passing import PASS_BEHIND, PASS_GAP, ROAD_MARGIN

if TYPE_CHECKING:
    from ...sim.tracks import Track

LINE_LOOKAHEAD = 0.3  # m, plus LINE_LOOKAHEAD_TIME seconds of travel: where a racing-line driver aims
LINE_LOOKAHEAD_TIME = 0.15
DRIVE_LEAD = 0.1  # s: a racing-line driver commands the profile's speed this far ahead (the drive train's lag)


@dataclasses.dataclass
class RacingLineBot(Bot):
    """The racing line at `speed` (a scale, 0.1-1.0) times its speed profile (`racing_line_command`)."""

    kind = "racingline"
    number_is_speed = False
    usage = "racingline, racingline@SCALE: the racing line, its speeds x SCALE"

    @property
    def name(self) -> str:
        return f"bot:racingline@{self.speed_text}" if self.speed_text else "bot:racingline"

    @classmethod
    def parse(cls, text: str, number: str | None) -> Bot:
        scale = float(number or 1.0)
        if not 0.1 <= scale <= 1.0:
            raise ValueError(f"bot {text!r}: racing-line scale {scale} outside 0.1-1.0")
        return cls(speed=scale, speed_text=number or "")

    def steer(self, at):
        return racing_line_command(at, self.speed)


def racing_line_command(at: Situation, scale: float):
    """(steering degrees, speed m/s) of a driver on the racing line at `scale` times its speed profile, in the
    situation `at`: pure pursuit of a point ahead on the line, and the profile's speed
    `DRIVE_LEAD` seconds ahead (so it brakes at the braking point, not after it); it keeps the bots' courtesy
    behind a car (one on its way in to the line counts as in its way), and it does not steer for its line
    through a car beside it."""
    track, spec, proj, traffic = at.track, at.spec, at.proj, at.traffic
    line = plan_racing_line(track, spec)
    x, y, yaw = at.pose
    i, n = line.index_at(proj.s), len(line.points)
    here = line.speed[i] * scale
    ahead = int(round((LINE_LOOKAHEAD + LINE_LOOKAHEAD_TIME * here) / line.spacing))
    tx, ty = line.points[(i + ahead) % n]
    to_line = 0.0  # how far across its way in to the line runs (a car there is in its way)
    if traffic:
        aim = track.project(tx, ty, at.segment_hint)  # the aim point: a point of its own
        hold = line_blocked_alongside(track, spec, proj, aim.lateral, traffic)
        if hold is None:
            to_line = aim.lateral - proj.lateral
        else:  # a car beside it on the way to the line: keep clear of it, parallel to the centre line
            tx, ty, _ = track.point_at(aim.s, hold)
    rear_x = x - spec.wheelbase / 2 * math.cos(yaw)
    rear_y = y - spec.wheelbase / 2 * math.sin(yaw)
    steer = pursuit_steer(spec, rear_x, rear_y, yaw, tx, ty)
    lead = int(round(here * DRIVE_LEAD / line.spacing))
    speed = scale * float(line.speed[(i + lead) % n])
    speed = speed_in_traffic(max(spec.min_speed, min(spec.max_speed, speed)),
                             [(along, path_offset(lateral, to_line), other) for along, lateral, other in traffic], spec)
    return steer, speed


def path_offset(lateral: float, to_line: float) -> float:
    """Sideways distance from a car `lateral` off this one to the path from this car to a point `to_line` off
    it (0 where the car is on that path): a car beside the racing line's way in is in the way too."""
    low, high = min(0.0, to_line), max(0.0, to_line)
    return lateral - low if lateral < low else (lateral - high if lateral > high else 0.0)


def line_blocked_alongside(track: Track, spec: CarSpec, proj, line_lateral: float, traffic) -> float | None:
    """The lateral offset a racing-line driver at `proj` should hold instead of steering for its line at
    `line_lateral`, or None if its way there is clear. A car beside it (overlapping it along the track) on the
    side the line is, nearer than the line plus a car's width and `PASS_GAP`, would be hit from the side, and
    slowing does not help with a car beside rather than ahead: the driver keeps `PASS_GAP` of side room to it
    (within `ROAD_MARGIN` of the road's edge) until it has passed or been passed."""
    clear = spec.width + PASS_GAP
    toward = line_lateral - proj.lateral
    hold = None
    for along, other, _ in traffic:
        if abs(track.wrap_ds(along)) < spec.length + PASS_BEHIND / 2 and other * toward > 0 \
                and abs(other) < abs(toward) + clear:
            keep = proj.lateral + other - math.copysign(clear, other)
            if hold is None or abs(keep - line_lateral) > abs(hold - line_lateral):
                hold = keep  # the car that keeps it furthest from its line
    if hold is None:
        return None
    return min(max(hold, -(proj.right_width - ROAD_MARGIN)), proj.left_width - ROAD_MARGIN)
