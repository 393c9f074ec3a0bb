"""League definitions: `league.toml` parsed against its declared fields, with errors naming the file and field."""
from __future__ import annotations

import dataclasses
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
from pathlib import Path

from ..environment.rules import FORMATS
from ..resources import league_dir


TOML = "league.toml"
DB = "results.sqlite"
SUBMISSIONS = "submissions"
REPLAYS = "replays"
DEFAULT_TOML = league_dir() / "default.toml"
TIME_TRIAL_FORMAT = "reset_rule"  # time trials run under the AWS Summit reset rule
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
    time_trial: dict | None  # {"laps", "trials", "max_steps"}
    head_to_head: dict | None  # {"cars", "laps", "trials", "max_steps"}
    source: str = TOML


_DEFAULTS = {"step_budget": 1.0 / 15, "max_retries": 2, "match_timeout": 600.0, "replays": True,
             "replay_image_every": 0}


def _field(table: dict, key: str, kind, source: str, where: str, default=dataclasses.MISSING):
    if key not in table:
        if default is dataclasses.MISSING:
            raise LeagueError(f"{source}: missing key '{where}{key}'")
        return default
    value = table[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(value, bool) and bool not in kinds:
        raise LeagueError(f"{source}: '{where}{key}' must be {kinds[0].__name__}, got {value!r}")
    if not isinstance(value, kinds):
        raise LeagueError(f"{source}: '{where}{key}' must be {kinds[0].__name__}, got {value!r}")
    return value


def _positive_int(table, key, source, where, default=dataclasses.MISSING, minimum=1):
    value = _field(table, key, int, source, where, default)
    if value is not None and value < minimum:
        raise LeagueError(f"{source}: '{where}{key}' must be at least {minimum}, got {value}")
    return value


def parse_config(text: str, source: str = TOML) -> LeagueConfig:
    """Parse and validate league.toml text; LeagueError names the file and field on any problem."""
    from ..environment.bots import parse_bot
    from ..sim.tracks import TrackError, load_track

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise LeagueError(f"{source}: not valid TOML ({exc})") from None
    known = {"league", "tracks", "time_trial", "head_to_head"}
    for key in data:
        if key not in known:
            raise LeagueError(f"{source}: unknown section or key '{key}' (known: {', '.join(sorted(known))})")
    league = _field(data, "league", dict, source, "")
    name = _field(league, "name", str, source, "league.")
    if not name.strip() or len(name) > LEAGUE_NAME_LENGTH or not name.isprintable():
        raise LeagueError(f"{source}: 'league.name' must be 1 to {LEAGUE_NAME_LENGTH} printable characters (no "
                          f"control characters or line breaks), got {name[:80]!r}")
    seeds = _field(league, "seeds", list, source, "league.")
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**32 for s in seeds):
        raise LeagueError(f"{source}: 'league.seeds' must be a non-empty list of integers 0 to 2^32-1, "
                          f"got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise LeagueError(f"{source}: 'league.seeds' has duplicates: {seeds!r}")
    bots = _field(league, "bots", list, source, "league.", [])
    for bot in bots:
        if not isinstance(bot, str) or not bot.startswith("bot:"):
            raise LeagueError(f"{source}: 'league.bots' entries must look like \"bot:follow@1.5\", got {bot!r}")
        try:
            parse_bot(bot)
        except (ValueError, KeyError) as exc:
            raise LeagueError(f"{source}: 'league.bots' entry {bot!r}: {exc}") from None
    if len(set(bots)) != len(bots):
        raise LeagueError(f"{source}: 'league.bots' has duplicates")
    budget = _field(league, "step_budget", (float, int), source, "league.", _DEFAULTS["step_budget"])
    if not 0 < budget <= 10:
        raise LeagueError(f"{source}: 'league.step_budget' must be in (0, 10] seconds, got {budget}")
    retries = _positive_int(league, "max_retries", source, "league.", _DEFAULTS["max_retries"], minimum=0)
    timeout = _field(league, "match_timeout", (float, int), source, "league.", _DEFAULTS["match_timeout"])
    if timeout <= 0:
        raise LeagueError(f"{source}: 'league.match_timeout' must be positive, got {timeout}")
    replays = _field(league, "replays", bool, source, "league.", _DEFAULTS["replays"])
    image_every = _positive_int(league, "replay_image_every", source, "league.", _DEFAULTS["replay_image_every"],
                                minimum=0)
    for key in league:
        if key not in {"name", "seeds", "bots", "step_budget", "max_retries", "match_timeout", "replays",
                       "replay_image_every"}:
            raise LeagueError(f"{source}: unknown key 'league.{key}'")

    raw_tracks = _field(data, "tracks", list, source, "")
    if not raw_tracks:
        raise LeagueError(f"{source}: 'tracks' must list at least one [[tracks]] table")
    tracks = []
    for i, entry in enumerate(raw_tracks):
        where = f"tracks[{i}]."
        if not isinstance(entry, dict):
            raise LeagueError(f"{source}: 'tracks[{i}]' must be a table with 'name' and 'directions'")
        track = _field(entry, "name", str, source, where)
        try:
            load_track(track)  # loads and validates it: a track every match can race
        except (TrackError, FileNotFoundError, ValueError) as exc:
            raise LeagueError(f"{source}: '{where}name': unusable track {track!r} ({exc})") from None
        directions = _field(entry, "directions", list, source, where, ["forward"])
        if not directions or any(d not in ("forward", "reverse") for d in directions) \
                or len(set(directions)) != len(directions):
            raise LeagueError(f"{source}: '{where}directions' must list \"forward\" and/or \"reverse\", "
                              f"got {directions!r}")
        for key in entry:
            if key not in ("name", "directions"):
                raise LeagueError(f"{source}: unknown key '{where}{key}'")
        tracks.append(TrackSpec(track, tuple(directions)))

    def section(key, fields):
        table = data.get(key)
        if table is None:
            return None
        if not isinstance(table, dict):
            raise LeagueError(f"{source}: '{key}' must be a table")
        out = {}
        for field, default, minimum in fields:
            out[field] = _positive_int(table, field, source, f"{key}.", default, minimum)
        fmt = table.get("format")
        for extra in table:
            if extra not in {f for f, _, _ in fields} | {"format", "enabled"}:
                raise LeagueError(f"{source}: unknown key '{key}.{extra}'")
        if not _field(table, "enabled", bool, source, f"{key}.", True):
            return None
        return out, fmt

    tt = section("time_trial", [("laps", 3, 1), ("trials", 1, 1), ("max_steps", None, 1)])
    if tt is not None:
        tt, fmt = tt
        if fmt is not None and fmt != TIME_TRIAL_FORMAT:
            if fmt not in FORMATS:
                raise LeagueError(f"{source}: 'time_trial.format' is {fmt!r}, an unknown format "
                                  f"(known: {', '.join(FORMATS)})")
            raise LeagueError(f"{source}: 'time_trial.format' must be {TIME_TRIAL_FORMAT!r} (time trials run "
                              f"under the reset rule), got {fmt!r}")
    h2h = section("head_to_head", [("cars", 2, 2), ("laps", 3, 1), ("trials", 1, 1), ("max_steps", None, 1)])
    if h2h is not None:
        h2h, fmt = h2h
        if fmt is not None and fmt != "head_to_head":
            raise LeagueError(f"{source}: 'head_to_head.format' must be 'head_to_head', got {fmt!r}")
        if h2h["cars"] > 8:
            raise LeagueError(f"{source}: 'head_to_head.cars' must be 2 to 8, got {h2h['cars']}")
    if tt is None and h2h is None:
        raise LeagueError(f"{source}: needs a [time_trial] or a [head_to_head] section")
    return LeagueConfig(name=name, tracks=tracks, seeds=list(seeds), bots=list(bots), step_budget=float(budget),
                        max_retries=int(retries), match_timeout=float(timeout), replays=replays,
                        replay_image_every=int(image_every), time_trial=tt, head_to_head=h2h, source=source)


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
