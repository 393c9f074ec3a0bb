"""``bot:pass@SPEED``: keeps the centre line at SPEED m/s and overtakes slower cars with side room to spare.

The expert that teaches imitation agents to pass (`multirace imitate --traffic`).
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from ...sim.car import CarSpec
from .base import FOLLOW_DISTANCE, STOP_DISTANCE, Bot

if TYPE_CHECKING:
    from ...sim.tracks import Track

PASS_AHEAD = 4.0  # m; a slower car closer than this ahead is overtaken
PASS_BEHIND = 0.5  # m; a car being passed keeps steering the pass until this far behind
PASS_GAP = 0.12  # m of side room a passing car leaves between its side and the other's
ROAD_MARGIN = 0.03  # m between a passing car's centre and the road edge (its outer wheels may leave the road)
RETURN_STEP = 0.08  # m; with nothing in the way, the target line is this much nearer the centre than the car


@dataclasses.dataclass
class PassBot(Bot):
    """The centre line at `speed`, going wide round slower cars (`passing_line`)."""

    kind = "pass"

    def steer(self, at):
        lateral, speed = passing_line(at.track, at.spec, at.proj, at.traffic, self.speed)
        return at.pursue(speed, lateral)


def passing_line(track: Track, spec: CarSpec, proj, traffic, speed: float) -> tuple[float, float]:
    """(lateral target, speed) of a driver that keeps the centre line and overtakes slower cars wide.

    Every slower car from `PASS_BEHIND` behind to `PASS_AHEAD` ahead (and any car alongside) is in the
    way. The driver steers for the line nearest its own that keeps `PASS_GAP` of side room to all of
    them: the centre line, or one side of one of them (so it passes on the side it is already on and
    does not weave); where its own line is already clear it holds it rather than close in on the car
    it passes. Where no line is clear, or while the car ahead is still in its way, it holds back at
    that car's pace instead of running into it. With nothing in the way it drifts back to the centre
    line gently (`RETURN_STEP`), so it never cuts in on a car it has just passed, and a camera driver
    that imitates it, which cannot see that car any more, learns the same slow return.
    """
    in_window = []
    for ahead, lateral, other_speed in traffic:
        along = track.wrap_ds(ahead)
        if -PASS_BEHIND < along < PASS_AHEAD and (other_speed < speed - 0.2 or along < spec.length):
            in_window.append((along, proj.lateral + lateral, other_speed))
    if not in_window:
        return proj.lateral - max(-RETURN_STEP, min(RETURN_STEP, proj.lateral)), speed
    clear = spec.width + PASS_GAP  # centre-to-centre offset of a clean pass
    left_limit, right_limit = proj.left_width - ROAD_MARGIN, -(proj.right_width - ROAD_MARGIN)
    lines = [0.0] + [min(max(other + side * clear, right_limit), left_limit)
                     for _, other, _ in in_window for side in (1.0, -1.0)]

    def room(line: float) -> float:
        return min(abs(line - other) for _, other, _ in in_window)

    clear_lines = [line for line in lines if room(line) >= clear - 1e-6]
    if room(proj.lateral) >= clear and right_limit <= proj.lateral <= left_limit:
        target = proj.lateral  # already clear of them all: hold this line, never close in on a car to pass it
    else:
        target = (min(clear_lines, key=lambda line: abs(line - proj.lateral)) if clear_lines
                  else max(lines, key=room))
    for along, other, other_speed in in_window:  # not yet beside it: close in slower than it drives
        if 0.0 < along < FOLLOW_DISTANCE and abs(proj.lateral - other) < spec.width + PASS_GAP / 2:
            speed = spec.min_speed if along < STOP_DISTANCE else min(speed, max(spec.min_speed, 0.9 * other_speed))
    return target, speed
