"""League definitions: `league.toml` parsed against its declared fields, with errors naming the file and field.

The league's stages (its `[time_trial]` and `[head_to_head]` sections) come from the race formats that name a
league stage (`RaceRules.league_stage`, `environment.formats`): a solo format's stage races each entrant alone
(time trials, scored in the time-trial table), a multi-car format's stage races heats (rated)."""
from __future__ import annotations

import dataclasses
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
from pathlib import Path

from ..environment.formats import FORMATS, league_stages
from ..resources import league_dir


TOML = "league.toml"
DB = "results.sqlite"
SUBMISSIONS = "submissions"
REPLAYS = "replays"
DEFAULT_TOML = league_dir() / "default.toml"
SUBMIT_TIMEOUT = 120.0
WORKER_STARTUP_TIMEOUT = 120.0
LEAGUE_NAME_LENGTH = 100


class LeagueError(ValueError):
    """A league folder or command is malformed; the message names the file and the field."""


# ------------------------------------------------------------------ definition
@dataclasses.dataclass
class TrackSpec:
    name: str
    directions: tuple[str, ...] = ("forward",)


@dataclasses.dataclass(frozen=True)
class Stage:
    """A league stage: a league.toml section (and the `kind` of its scheduled matches) racing one format."""

    name: str  # the section, e.g. "time_trial"
    race: str  # the format its matches race, e.g. "reset_rule"
    solo: bool  # each entrant races alone (scored in the time-trial table); else heats of several (rated)


STAGES = {name: Stage(name, rules.name, rules.solo) for name, rules in league_stages().items()}


@dataclasses.dataclass
class LeagueConfig:
    """A parsed, validated league.toml."""

    name: str
    tracks: list[TrackSpec]
    seeds: list[int]
    bots: list[str]
    step_budget: float
    max_retries: int
    match_timeout: float
    replays: bool
    replay_image_every: int
    stages: dict  # the enabled stages' settings, by stage name (`STAGES`): solo {"laps", "trials", "max_steps"},
    # heats also {"cars", "schedule", "opponents", "stop_sigma", "batch"}
    source: str = TOML

    @property
    def time_trial(self) -> dict | None:
        return self.stages.get("time_trial")

    @property
    def head_to_head(self) -> dict | None:
        return self.stages.get("head_to_head")


REQUIRED = object()  # a Field without a default


@dataclasses.dataclass(frozen=True)
class Field:
    """A declared league.toml field: its type, default (REQUIRED if none) and allowed range."""

    kind: type | tuple
    default: object = REQUIRED
    minimum: float | None = None  # inclusive
    above: float | None = None  # exclusive lower bound
    maximum: float | None = None  # inclusive


_LAPS, _TRIALS, _MAX_STEPS = Field(int, 3, minimum=1), Field(int, 1, minimum=1), Field(int, None, minimum=1)


def _stage_fields(stage: Stage) -> dict:
    """The keys of a stage's section: every stage's, and the heats' own for a multi-car one."""
    fields = {"enabled": Field(bool, True), "format": Field(str, stage.race)}
    if not stage.solo:
        fields["cars"] = Field(int, 2, minimum=2, maximum=8)
    fields.update(laps=_LAPS, trials=_TRIALS, max_steps=_MAX_STEPS)
    if not stage.solo:
        fields.update(schedule=Field(str, "round_robin"), opponents=Field(int, None, minimum=1),
                      stop_sigma=Field((float, int), None, above=0), batch=Field(int, None, minimum=1))
    return fields


SCHEMA = {  # every section, key, type and range league.toml may hold
    "league": {"name": Field(str), "seeds": Field(list), "bots": Field(list, []),
               "step_budget": Field((float, int), 1.0 / 15, above=0, maximum=10),
               "max_retries": Field(int, 2, minimum=0), "match_timeout": Field((float, int), 600.0, above=0),
               "replays": Field(bool, True), "replay_image_every": Field(int, 0, minimum=0)},
    "tracks": {"name": Field(str), "directions": Field(list, ["forward"])},  # each [[tracks]] table
    **{name: _stage_fields(stage) for name, stage in STAGES.items()},
}


def _section(table, fields: dict, source: str, where: str) -> dict:
    """The values of one TOML table checked against its declared fields (unknown keys, types, ranges)."""
    if not isinstance(table, dict):
        raise LeagueError(f"{source}: '{where.rstrip('.')}' must be a table")
    for key in table:
        if key not in fields:
            raise LeagueError(f"{source}: unknown key '{where}{key}' (known: {', '.join(fields)})")
    out = {}
    for key, field in fields.items():
        if key not in table:
            if field.default is REQUIRED:
                raise LeagueError(f"{source}: missing key '{where}{key}'")
            out[key] = field.default
            continue
        value = table[key]
        kinds = field.kind if isinstance(field.kind, tuple) else (field.kind,)
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            raise LeagueError(f"{source}: '{where}{key}' must be {kinds[0].__name__}, got {value!r}")
        if ((field.minimum is not None and value < field.minimum) or (field.above is not None and value <= field.above)
                or (field.maximum is not None and value > field.maximum)):
            low = f"at least {field.minimum}" if field.minimum is not None else f"above {field.above}"
            high = f" and at most {field.maximum}" if field.maximum is not None else ""
            raise LeagueError(f"{source}: '{where}{key}' must be {low}{high}, got {value}")
        out[key] = value
    return out


SCHEDULES = ("round_robin", "uncertainty")
UNCERTAINTY_ONLY = ("opponents", "stop_sigma", "batch")


def _check_schedule(name: str, heats: dict, raw: dict, source: str) -> None:
    """A heat stage's schedule is a known schedule; the uncertainty schedule's settings only come with it, and
    it races pairs."""
    if heats["schedule"] not in SCHEDULES:
        raise LeagueError(f"{source}: '{name}.schedule' must be \"round_robin\" (every pair meets) or "
                          f"\"uncertainty\" (pairs planned where the table is unsure), got {heats['schedule']!r}")
    if heats["schedule"] == "round_robin":
        for key in UNCERTAINTY_ONLY:
            if key in raw:
                raise LeagueError(f"{source}: '{name}.{key}' applies only with schedule = \"uncertainty\"")
    elif heats["cars"] != 2:
        raise LeagueError(f"{source}: '{name}.cars' must be 2 with schedule = \"uncertainty\" (it plans "
                          f"pairs), got {heats['cars']}")


def _parse_stages(data: dict, source: str) -> dict:
    """The enabled stages' sections (`STAGES`), each racing its stage's format; at least one."""
    stages = {}
    for name, stage in STAGES.items():
        if name not in data:
            continue
        section = _section(data[name], SCHEMA[name], source, f"{name}.")
        if not section.pop("enabled"):
            continue
        race = section.pop("format")
        if race != stage.race:
            if race not in FORMATS:
                raise LeagueError(f"{source}: '{name}.format' is {race!r}, an unknown format "
                                  f"(known: {', '.join(FORMATS)})")
            raise LeagueError(f"{source}: '{name}.format' must be {stage.race!r} (the league's "
                              f"{name.replace('_', ' ')} stage races it), got {race!r}")
        if not stage.solo:
            _check_schedule(name, section, data[name], source)
        stages[name] = section
    if not stages:
        raise LeagueError(f"{source}: needs a {' or a '.join(f'[{name}]' for name in STAGES)} section")
    return stages


def parse_config(text: str, source: str = TOML) -> LeagueConfig:
    """Parse and validate league.toml text against SCHEMA; LeagueError names the file and field on any problem.

    Beyond types and ranges: seeds are distinct integers 0 to 2^32-1, bots are known bot specs, every track
    loads, and at least one race format is enabled."""
    from ..environment.bots import parse_bot

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise LeagueError(f"{source}: not valid TOML ({exc})") from None
    for key in data:
        if key not in SCHEMA:
            raise LeagueError(f"{source}: unknown section or key '{key}' (known: {', '.join(sorted(SCHEMA))})")
    if "league" not in data:
        raise LeagueError(f"{source}: missing key 'league'")
    league = _section(data["league"], SCHEMA["league"], source, "league.")
    name = league["name"]
    if not name.strip() or len(name) > LEAGUE_NAME_LENGTH or not name.isprintable():
        raise LeagueError(f"{source}: 'league.name' must be 1 to {LEAGUE_NAME_LENGTH} printable characters (no "
                          f"control characters or line breaks), got {name[:80]!r}")
    seeds = league["seeds"]
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**32 for s in seeds):
        raise LeagueError(f"{source}: 'league.seeds' must be a non-empty list of integers 0 to 2^32-1, "
                          f"got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise LeagueError(f"{source}: 'league.seeds' has duplicates: {seeds!r}")
    bots = league["bots"]
    for bot in bots:
        if not isinstance(bot, str) or not bot.startswith("bot:"):
            raise LeagueError(f"{source}: 'league.bots' entries must look like \"bot:follow@1.5\", got {bot!r}")
        try:
            parse_bot(bot)
        except (ValueError, KeyError) as exc:
            raise LeagueError(f"{source}: 'league.bots' entry {bot!r}: {exc}") from None
    if len(set(bots)) != len(bots):
        raise LeagueError(f"{source}: 'league.bots' has duplicates")

    tracks = _parse_tracks(data.get("tracks"), source)

    stages = _parse_stages(data, source)
    return LeagueConfig(name=name, tracks=tracks, seeds=list(seeds), bots=list(bots),
                        step_budget=float(league["step_budget"]), max_retries=league["max_retries"],
                        match_timeout=float(league["match_timeout"]), replays=league["replays"],
                        replay_image_every=league["replay_image_every"], stages=stages,
                        source=source)


def _parse_tracks(raw_tracks, source: str) -> list:
    """The [[tracks]] tables: each track loads, its directions are "forward" and/or "reverse"."""
    from ..sim.tracks import TrackError, load_track

    if not isinstance(raw_tracks, list) or not raw_tracks:
        raise LeagueError(f"{source}: 'tracks' must list at least one [[tracks]] table")
    tracks = []
    for i, entry in enumerate(raw_tracks):
        where = f"tracks[{i}]."
        entry = _section(entry, SCHEMA["tracks"], source, where)
        try:
            load_track(entry["name"])  # loads and validates it: a track every match can race
        except (TrackError, FileNotFoundError, ValueError) as exc:
            raise LeagueError(f"{source}: '{where}name': unusable track {entry['name']!r} ({exc})") from None
        directions = entry["directions"]
        if not directions or any(d not in ("forward", "reverse") for d in directions) \
                or len(set(directions)) != len(directions):
            raise LeagueError(f"{source}: '{where}directions' must list \"forward\" and/or \"reverse\", "
                              f"got {directions!r}")
        tracks.append(TrackSpec(entry["name"], tuple(directions)))
    return tracks


def load_config(folder) -> LeagueConfig:
    path = Path(folder) / TOML
    if not path.is_file():
        raise LeagueError(f"{path}: no league definition here (create a league with 'multirace league init "
                          f"{folder}')")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise LeagueError(f"{path}: unreadable ({exc})") from None
    return parse_config(text, str(path))
