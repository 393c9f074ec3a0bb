"""Scripted drivers: pure pursuit on the track's centre line (or a lane).

They use privileged state (the car's true pose and the track), so they are
the demo, the test driver, the expert for imitation, and the league's bots:
``follow@1.5`` keeps the centre line at 1.5 m/s, ``lanes@1.0`` changes lane
every few seconds at 1.0 m/s, ``pass@2.0`` keeps the centre line at 2 m/s
and overtakes slower cars with side room to spare (the expert that teaches
imitation agents to pass, `multirace imitate --traffic`), and
``racingline`` (or ``racingline@F``) drives the track's racing line at the
fastest speeds the tyres and drive train allow (`sim.racingline`), scaled by
F (default 1.0; ``@0.8`` is a gentler driver): every track's reference lap.
"""
from __future__ import annotations

import dataclasses
import math
import re

from ..sim.car import CarSpec
from ..sim.racingline import plan_racing_line
from ..sim.tracks import Track

BOT_KINDS = ("follow", "lanes", "pass", "racingline")
_BOT_PATTERN = re.compile(r"^(?:bot:)?(?P<kind>[a-z]+)(?:@(?P<speed>[0-9]*\.?[0-9]+))?$")


@dataclasses.dataclass
class PurePursuit:
    """Steers toward a point `lookahead` metres ahead on a path parallel to the centre line."""

    speed: float = 1.0  # m/s
    lookahead: float = 0.45  # metres (grows with speed)
    lateral: float = 0.0  # target offset from the centre line, + left

    def command(self, track: Track, spec: CarSpec, pose, segment_hint=None) -> tuple[float, float]:
        """(steering degrees, speed m/s) for a car whose body centre is at `pose` (x, y, yaw)."""
        x, y, yaw = pose
        rear_x = x - spec.wheelbase / 2 * math.cos(yaw)
        rear_y = y - spec.wheelbase / 2 * math.sin(yaw)
        proj = track.project(x, y, segment_hint)
        lookahead = self.lookahead + 0.25 * self.speed
        tx, ty, _ = track.point_at(proj.s + lookahead, self.lateral)
        alpha = math.atan2(ty - rear_y, tx - rear_x) - yaw
        distance = math.hypot(tx - rear_x, ty - rear_y)
        steer = math.atan2(2.0 * spec.wheelbase * math.sin(alpha), distance)
        steer = max(-spec.max_steer, min(spec.max_steer, steer))
        return math.degrees(steer), self.speed


@dataclasses.dataclass
class Bot:
    """A named scripted car: `follow` (centre line) or `lanes` (alternating lanes)."""

    kind: str
    speed: float
    lane_period: float = 4.0  # seconds between lane changes (lanes bot)
    speed_text: str = ""  # the speed as the user wrote it, so names read back as typed

    @property
    def name(self) -> str:
        if self.kind == "racingline" and not self.speed_text:
            return "bot:racingline"
        return f"bot:{self.kind}@{self.speed_text or format(self.speed, 'g')}"

    def command(self, track: Track, spec: CarSpec, pose, sim_time: float, segment_hint=None, traffic=()):
        """(steering degrees, speed m/s) at race time `sim_time`.

        `traffic` lists the other cars as (metres ahead along the track, lateral
        offset from this car, speed); a bot slows behind a car in its way.
        """
        if self.kind == "racingline":
            return racing_line_command(track, spec, pose, segment_hint, traffic, self.speed)
        if self.kind == "pass":
            proj = track.project(pose[0], pose[1], segment_hint)
            lateral, speed = passing_line(track, spec, proj, traffic, self.speed)
        else:
            lateral = 0.0
            if self.kind == "lanes":
                lane = int(sim_time // self.lane_period) % 2
                proj = track.project(pose[0], pose[1], segment_hint)
                lateral = (proj.left_width if lane == 0 else -proj.right_width) / 2
            speed = speed_in_traffic(self.speed, traffic, spec)
        return PurePursuit(speed=speed, lateral=lateral).command(track, spec, pose, segment_hint)


FOLLOW_DISTANCE = 1.2  # m; a car closer than this ahead, in the same lane, sets the pace
STOP_DISTANCE = 0.55  # m; closer than this the bot crawls
LANE_HALF_WIDTH = 0.4  # m; cars closer than this sideways are in the way (two car widths)


def speed_in_traffic(speed: float, traffic, spec: CarSpec) -> float:
    """Speed that keeps a scripted driver from running into the car ahead."""
    for ahead, lateral, other_speed in traffic:
        if 0.0 < ahead < FOLLOW_DISTANCE and abs(lateral) < LANE_HALF_WIDTH:
            if ahead < STOP_DISTANCE:
                return spec.min_speed
            speed = min(speed, max(spec.min_speed, 0.9 * other_speed))
    return speed


PASS_AHEAD = 4.0  # m; a slower car closer than this ahead is overtaken
PASS_BEHIND = 0.5  # m; a car being passed keeps steering the pass until this far behind
PASS_GAP = 0.12  # m of side room a passing car leaves between its side and the other's
ROAD_MARGIN = 0.03  # m between a passing car's centre and the road edge (its outer wheels may leave the road)
RETURN_STEP = 0.08  # m; with nothing in the way, the target line is this much nearer the centre than the car


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


def racing_line_command(track: Track, spec: CarSpec, pose, segment_hint, traffic, scale: float):
    """(steering degrees, speed m/s) of a driver on the racing line at `scale` times its speed profile:
    pure pursuit of a point ahead on the line, and the profile's speed `DRIVE_LEAD` seconds ahead (so
    it brakes at the braking point, not after it); it keeps the bots' courtesy behind a car (one on its way
    in to the line counts as in its way), and it does not steer for its line through a car beside it."""
    line = plan_racing_line(track, spec)
    x, y, yaw = pose
    proj = track.project(x, y, segment_hint)
    i, n = line.index_at(proj.s), len(line.points)
    here = line.speed[i] * scale
    ahead = int(round((LINE_LOOKAHEAD + LINE_LOOKAHEAD_TIME * here) / line.spacing))
    tx, ty = line.points[(i + ahead) % n]
    to_line = 0.0  # how far across its way in to the line runs (a car there is in its way)
    if traffic:
        aim = track.project(tx, ty, segment_hint)
        hold = line_blocked_alongside(track, spec, proj, aim.lateral, traffic)
        if hold is None:
            to_line = aim.lateral - proj.lateral
        else:  # a car beside it on the way to the line: keep clear of it, parallel to the centre line
            tx, ty, _ = track.point_at(aim.s, hold)
    rear_x = x - spec.wheelbase / 2 * math.cos(yaw)
    rear_y = y - spec.wheelbase / 2 * math.sin(yaw)
    alpha = math.atan2(ty - rear_y, tx - rear_x) - yaw
    steer = math.atan2(2.0 * spec.wheelbase * math.sin(alpha), math.hypot(tx - rear_x, ty - rear_y))
    steer = max(-spec.max_steer, min(spec.max_steer, steer))
    lead = int(round(here * DRIVE_LEAD / line.spacing))
    speed = scale * float(line.speed[(i + lead) % n])
    speed = speed_in_traffic(max(spec.min_speed, min(spec.max_speed, speed)),
                             [(along, path_offset(lateral, to_line), other) for along, lateral, other in traffic], spec)
    return math.degrees(steer), speed


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


LINE_LOOKAHEAD = 0.3  # m, plus LINE_LOOKAHEAD_TIME seconds of travel: where a racing-line driver aims
LINE_LOOKAHEAD_TIME = 0.15
DRIVE_LEAD = 0.1  # s: a racing-line driver commands the profile's speed this far ahead (the drive train's lag)


def parse_bot(text: str) -> Bot:
    """Parse `bot:follow@1.5` / `lanes@1.0` / `racingline@0.9` into a Bot; ValueError with the accepted form
    otherwise. KIND@SPEED sets a speed in m/s; for `racingline` the number scales its speed profile
    (default 1.0)."""
    match = _BOT_PATTERN.match(text.strip())
    if not match or match["kind"] not in BOT_KINDS or (match["speed"] is None and match["kind"] != "racingline"):
        raise ValueError(f"bot {text!r}: expected bot:KIND@SPEED with KIND one of {', '.join(BOT_KINDS)}, "
                         "e.g. bot:follow@1.5, or bot:racingline[@SCALE]")
    if match["kind"] == "racingline":
        scale = float(match["speed"] or 1.0)
        if not 0.1 <= scale <= 1.0:
            raise ValueError(f"bot {text!r}: racing-line scale {scale} outside 0.1-1.0")
        return Bot(kind="racingline", speed=scale, speed_text=match["speed"] or "")
    speed = float(match["speed"])
    if not 0.1 <= speed <= 4.0:
        raise ValueError(f"bot {text!r}: speed {speed} outside 0.1-4.0 m/s")
    return Bot(kind=match["kind"], speed=speed, speed_text=match["speed"])
