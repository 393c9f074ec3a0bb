"""Scripted drivers (bots), one file per kind, registered by name in `BOTS`.

They read privileged state (their car's true pose, the track and the other
cars, from the race's `RaceState`), so they are the demo, the test driver,
the expert for imitation, and the league's bots. ``follow@1.5`` keeps the
centre line at 1.5 m/s, ``lanes@1.0`` changes lane every few seconds at
1.0 m/s, ``pass@2.0`` keeps the centre line at 2 m/s and overtakes slower
cars with side room to spare, ``racingline`` (or ``racingline@F``) drives the
track's racing line at F (default 1.0) times the fastest speeds the tyres and
drive train allow, ``defend@1.5`` drives the racing line at up to 1.5 m/s
and covers the inside of the next corner from a car close behind, and
``weave@1.0`` drifts from side to side and brakes without warning, as a
camera car in traffic does.

A new bot is a `base.Bot` subclass in a file of its own (its `kind` and
`steer`) and one line in `BOTS`.
"""
from __future__ import annotations

import re

from .base import FOLLOW_DISTANCE, LANE_HALF_WIDTH, STOP_DISTANCE, Bot, PurePursuit, Situation, speed_in_traffic
from .defend import DefendBot
from .follow import FollowBot
from .lanes import LanesBot
from .passing import PASS_AHEAD, PASS_BEHIND, PASS_GAP, RETURN_STEP, ROAD_MARGIN, PassBot, passing_line
from .racingline import RacingLineBot, line_blocked_alongside, racing_line_command
from .weave import WeaveBot

BOTS: dict[str, type[Bot]] = {  # KIND -> its driver: a new bot is one file and one line here
    "follow": FollowBot,
    "lanes": LanesBot,
    "pass": PassBot,
    "racingline": RacingLineBot,
    "defend": DefendBot,
    "weave": WeaveBot,
}
BOT_KINDS = tuple(BOTS)
_BOT_PATTERN = re.compile(r"^(?:bot:)?(?P<kind>[a-z]+)(?:@(?P<speed>[0-9]*\.?[0-9]+))?$")

__all__ = ["BOTS", "BOT_KINDS", "FOLLOW_DISTANCE", "LANE_HALF_WIDTH", "PASS_AHEAD", "PASS_BEHIND", "PASS_GAP",
           "RETURN_STEP", "ROAD_MARGIN", "STOP_DISTANCE", "Bot", "PurePursuit", "Situation", "line_blocked_alongside",
           "parse_bot", "passing_line", "racing_line_command", "speed_in_traffic"]


def parse_bot(text: str) -> Bot:
    """Parse `bot:follow@1.5` / `lanes@1.0` / `racingline@0.9` into its bot; ValueError with the accepted form
    otherwise. KIND@SPEED sets a speed in m/s; for `racingline` the number scales its speed profile
    (default 1.0)."""
    match = _BOT_PATTERN.match(text.strip())
    kind = match["kind"] if match else None
    if kind not in BOTS or (match["speed"] is None and BOTS[kind].number_is_speed):
        raise ValueError(f"bot {text!r}: expected bot:KIND@SPEED with KIND one of {', '.join(BOT_KINDS)}, "
                         "e.g. bot:follow@1.5, or bot:racingline[@SCALE]")
    return BOTS[kind].parse(text, match["speed"])


def bot_kinds_help() -> str:
    """The bot kinds for a command's help: ``KIND: ...`` as `bot:KIND@SPEED` reads them."""
    speed_kinds = ", ".join(kind for kind, bot in BOTS.items() if bot.number_is_speed)
    others = [bot.usage for bot in BOTS.values() if not bot.number_is_speed]
    return "; ".join([f"KIND: {speed_kinds} at SPEED m/s", *others])
