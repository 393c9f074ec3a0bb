"""The race formats: one `RaceRules` subclass per file, one registry line per format.

Adding a format is a new file here with its `RaceRules` subclass (its defaults as field defaults, and what it
does differently as overrides) and its line in `REGISTRY`; the env (`RaceEnv(race=...)`), the CLI's `--format`
choices and the league's stages (`league_stage`) read the registry.
"""
from __future__ import annotations

import numbers

from ..rules import RaceRules
from .head_to_head import HeadToHead
from .lap_count import LapCount
from .object_avoidance import ObjectAvoidance
from .reset_rule import ResetRule
from .time_trial import TimeTrial

REGISTRY: dict[str, type[RaceRules]] = {
    "time_trial": TimeTrial,
    "reset_rule": ResetRule,
    "object_avoidance": ObjectAvoidance,
    "head_to_head": HeadToHead,
    "lap_count": LapCount,
}
FORMATS = tuple(REGISTRY)


def format_class(race: str) -> type[RaceRules]:
    """The `RaceRules` class of a named format; a ValueError listing the registry's names if there is none."""
    if race not in REGISTRY:
        raise ValueError(f"race: unknown format {race!r}; choose one of {', '.join(REGISTRY)}")
    return REGISTRY[race]


def league_stages() -> dict[str, type[RaceRules]]:
    """{league stage (a league.toml section): the format it races}, from the formats that name a stage."""
    return {cls.league_stage: cls for cls in REGISTRY.values() if cls.league_stage is not None}


def make_rules(race: str = "time_trial", laps: int = 3, obstacles: int | None = None, **overrides) -> RaceRules:
    """The rules of a named format with its defaults, overridable per field."""
    rules_class = format_class(race)
    whole = isinstance(laps, numbers.Integral) or (isinstance(laps, float) and laps.is_integer())
    if isinstance(laps, bool) or not whole or laps < 1:
        raise ValueError(f"laps: expected a whole number of at least 1, got {laps!r}")
    if obstacles is not None:
        overrides["obstacles"] = int(obstacles)
    return rules_class(laps=int(laps), **overrides)
