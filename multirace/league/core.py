"""Leagues: a folder of submitted agents, a deterministic schedule, resumable parallel runs, ratings.

A league is a folder::

    league.toml        the definition (see league/default.toml)
    submissions/       agent files stored by content hash: <sha256>.pt
    results.sqlite     submissions, schedule and results (written transactionally)
    replays/           one rerun recording per match: <match_id>.rrd
    table.md/.csv/...  generated tables (``multirace league table``)

Security: agent files are untrusted. The league process never loads one:
validation at submit time and every race run in worker subprocesses (loading
there is ``torch.load(weights_only=True)``, which refuses pickles that would
import or call code), each match under a wall-clock timeout. A worker that
crashes or hangs is killed and replaced; only its match is retried (a bounded
number of times) and then recorded as failed with the reason.

Resumability: each result is written in one SQLite transaction together with
the schedule row it fulfils (``INSERT OR IGNORE`` keyed by the match id), and
its replay is written under a temporary name and renamed into place before the
result is committed. Killed at any moment and run again, the league runs only
the matches that have no result yet.
"""
from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import queue
import select
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
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
    from ..sim.tracks import TrackError, resolve_track_path

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
    if not name.strip():
        raise LeagueError(f"{source}: 'league.name' must not be empty")
    seeds = _field(league, "seeds", list, source, "league.")
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        raise LeagueError(f"{source}: 'league.seeds' must be a non-empty list of integers, got {seeds!r}")
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
            resolve_track_path(track)
        except (TrackError, FileNotFoundError, ValueError) as exc:
            raise LeagueError(f"{source}: '{where}name': unknown track {track!r} ({exc})") from None
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


# ------------------------------------------------------------------ store
SCHEMA = """
CREATE TABLE IF NOT EXISTS submissions (
    name TEXT PRIMARY KEY,
    sha256 TEXT NOT NULL UNIQUE,
    file TEXT NOT NULL,
    metadata TEXT NOT NULL,
    step_budget REAL,
    submitted_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS schedule (
    match_id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL UNIQUE,
    kind TEXT NOT NULL,
    round INTEGER NOT NULL,
    spec TEXT NOT NULL,
    status TEXT NOT NULL DEFAULT 'pending' CHECK (status IN ('pending', 'done', 'failed')),
    attempts INTEGER NOT NULL DEFAULT 0,
    last_error TEXT
);
CREATE TABLE IF NOT EXISTS results (
    match_id TEXT PRIMARY KEY REFERENCES schedule(match_id),
    status TEXT NOT NULL CHECK (status IN ('ok', 'failed')),
    result TEXT,
    reason TEXT,
    replay TEXT,
    wall_seconds REAL,
    recorded_at REAL NOT NULL
);
"""


def connect(folder) -> sqlite3.Connection:
    """The league's SQLite store (created if missing), in WAL mode with a generous busy timeout."""
    path = Path(folder) / DB
    conn = sqlite3.connect(path, timeout=60.0, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=FULL")
    conn.execute("PRAGMA foreign_keys=ON")
    conn.executescript(SCHEMA)
    return conn


class _Tx:
    """`with _Tx(conn):` one IMMEDIATE transaction, committed on success, rolled back on error."""

    def __init__(self, conn):
        self.conn = conn

    def __enter__(self):
        self.conn.execute("BEGIN IMMEDIATE")
        return self.conn

    def __exit__(self, kind, exc, tb):
        self.conn.execute("COMMIT" if kind is None else "ROLLBACK")
        return False


# ------------------------------------------------------------------ init / submit
def init_league(folder, template=None) -> Path:
    """Create a league folder from a template league.toml (default: league/default.toml)."""
    folder = Path(folder)
    if (folder / TOML).exists():
        raise LeagueError(f"{folder / TOML}: already exists; this folder is a league already")
    template = Path(template) if template else DEFAULT_TOML
    text = template.read_text() if template.is_file() else DEFAULT_TOML_TEXT
    parse_config(text, str(template))
    folder.mkdir(parents=True, exist_ok=True)
    (folder / SUBMISSIONS).mkdir(exist_ok=True)
    (folder / REPLAYS).mkdir(exist_ok=True)
    (folder / TOML).write_text(text)
    connect(folder).close()
    return folder


def _worker_command() -> list[str]:
    return [sys.executable, "-m", "multirace.league.core", "worker"]


def validate_in_subprocess(path, step_budget: float, timeout: float = SUBMIT_TIMEOUT) -> dict:
    """Validate an agent file exactly as a race would (safe load, metadata, smoke inference), in a subprocess.

    Returns {"ok": True, "name", "sha256", "metadata"} or {"ok": False, "error"}.
    """
    request = json.dumps({"op": "validate", "path": str(Path(path).resolve()), "step_budget": step_budget})
    try:
        proc = subprocess.run(_worker_command(), input=request + "\n", capture_output=True, text=True,
                              timeout=timeout, env=_worker_env())
    except subprocess.TimeoutExpired:
        return {"ok": False, "error": f"{path}: validation did not finish within {timeout:.0f} s"}
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or "").strip().splitlines()[-1:] or [f"exit code {proc.returncode}"]
        return {"ok": False, "error": f"{path}: validation crashed ({tail[0]})"}
    return json.loads(lines[-1])


def submit(folder, path, name: str, step_budget: float | None = None, validate: bool = True) -> dict:
    """Validate an agent file and store it in the league by content hash; returns its submission row.

    `step_budget` overrides the league's per-step inference budget for this entrant
    (None: the league's). `validate=False` skips validation (for tests of in-race misbehaviour).
    """
    folder = Path(folder)
    config = load_config(folder)
    path = Path(path)
    if not path.is_file():
        raise LeagueError(f"{path}: no such agent file")
    if not name or not name.strip() or name.startswith("bot:") or len(name) > 64:
        raise LeagueError(f"--name: {name!r} is not a valid entrant name (1-64 characters, not 'bot:...')")
    if name in config.bots:
        raise LeagueError(f"--name: {name!r} is a bot of this league")
    data = path.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    conn = connect(folder)
    try:
        row = conn.execute("SELECT name FROM submissions WHERE sha256=?", (sha,)).fetchone()
        if row:
            raise LeagueError(f"{path}: refused: duplicate of submission {row[0]!r} (same sha256 {sha[:12]})")
        row = conn.execute("SELECT sha256 FROM submissions WHERE name=?", (name,)).fetchone()
        if row:
            raise LeagueError(f"--name: refused: an entrant named {name!r} is already submitted")
        metadata = {}
        if validate:
            check = validate_in_subprocess(path, step_budget or config.step_budget)
            if not check.get("ok"):
                raise LeagueError(f"refused: {check.get('error')}")
            metadata = check.get("metadata") or {}
        stored = folder / SUBMISSIONS / f"{sha}.pt"
        stored.parent.mkdir(exist_ok=True)
        if not stored.exists():
            tmp = stored.with_name(f".{sha}.{os.getpid()}.tmp")
            tmp.write_bytes(data)
            os.replace(tmp, stored)
        with _Tx(conn):
            conn.execute("INSERT INTO submissions (name, sha256, file, metadata, step_budget, submitted_at) "
                         "VALUES (?, ?, ?, ?, ?, ?)",
                         (name, sha, f"{SUBMISSIONS}/{sha}.pt", json.dumps(metadata, sort_keys=True), step_budget,
                          time.time()))
        return {"name": name, "sha256": sha, "file": str(stored), "metadata": metadata}
    finally:
        conn.close()


# ------------------------------------------------------------------ schedule
def entrants(folder, config: LeagueConfig, conn) -> list[dict]:
    """Every entrant, in a deterministic order: the league's bots, then submissions by name."""
    out = [{"name": bot, "spec": bot, "sha256": None, "step_budget": None} for bot in config.bots]
    for name, sha, file, budget in conn.execute(
            "SELECT name, sha256, file, step_budget FROM submissions ORDER BY name"):
        out.append({"name": name, "spec": file, "sha256": sha, "step_budget": budget})
    return out


def _match_id(spec: dict) -> str:
    canonical = json.dumps(spec, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def build_schedule(config: LeagueConfig, entries: list[dict]) -> list[dict]:
    """The full deterministic schedule: a list of {"match_id", "kind", "round", "spec"} in schedule order.

    Time trials: every entrant, per track, direction, seed and trial. Head-to-head:
    every K-subset of entrants (so every pair meets equally often) per track,
    direction, seed and trial; a heat's grid order is the subset rotated by
    (block + trial) mod K, so over blocks each entrant starts from each slot.
    A round is one (track, direction, seed, trial) block of heats.
    """
    schedule = []
    blocks = [(t.name, d == "reverse", seed) for t in config.tracks for d in t.directions for seed in config.seeds]

    def entrant_spec(e):
        budget = e["step_budget"] if e["step_budget"] is not None else config.step_budget
        return {"name": e["name"], "spec": e["spec"], "sha256": e["sha256"], "step_budget": budget}

    if config.time_trial:
        tt = config.time_trial
        for b, (track, reverse, seed) in enumerate(blocks):
            for trial in range(tt["trials"]):
                for e in entries:
                    spec = {"kind": "time_trial", "race": TIME_TRIAL_FORMAT, "track": track, "reverse": reverse,
                            "seed": seed, "trial": trial, "laps": tt["laps"], "max_steps": tt["max_steps"],
                            "entrants": [entrant_spec(e)]}
                    schedule.append({"kind": "time_trial", "round": b * tt["trials"] + trial, "spec": spec})
    if config.head_to_head and len(entries) >= 2:
        h = config.head_to_head
        k = min(h["cars"], len(entries))
        heats = list(itertools.combinations(range(len(entries)), k))
        round_no = 0
        for b, (track, reverse, seed) in enumerate(blocks):
            for trial in range(h["trials"]):
                for j, heat in enumerate(heats):
                    shift = (b * h["trials"] + trial + j) % k
                    grid = heat[shift:] + heat[:shift]
                    spec = {"kind": "head_to_head", "race": "head_to_head", "track": track, "reverse": reverse,
                            "seed": seed, "trial": trial, "laps": h["laps"], "max_steps": h["max_steps"],
                            "entrants": [entrant_spec(entries[i]) for i in grid]}
                    schedule.append({"kind": "head_to_head", "round": round_no, "spec": spec})
                round_no += 1
    for row in schedule:
        row["match_id"] = _match_id(row["spec"])
        row["spec"]["match_id"] = row["match_id"]
    return schedule


def sync_schedule(folder, config: LeagueConfig, conn) -> list[dict]:
    """Insert the schedule's new rows (existing rows keep their seq); returns the current schedule."""
    schedule = build_schedule(config, entrants(folder, config, conn))
    with _Tx(conn):
        known = {row[0] for row in conn.execute("SELECT match_id FROM schedule")}
        seq = conn.execute("SELECT COALESCE(MAX(seq), -1) FROM schedule").fetchone()[0]
        for row in schedule:
            if row["match_id"] in known:
                continue
            seq += 1
            conn.execute("INSERT INTO schedule (match_id, seq, kind, round, spec) VALUES (?, ?, ?, ?, ?)",
                         (row["match_id"], seq, row["kind"], row["round"], json.dumps(row["spec"], sort_keys=True)))
    return schedule


# ------------------------------------------------------------------ worker side
def _worker_env() -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("MKL_NUM_THREADS", "1")
    package_root = str(Path(__file__).resolve().parents[2])  # the folder that holds `multirace`
    env["PYTHONPATH"] = package_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def run_match(spec: dict, folder, replay_tmp: str | None, image_every: int = 0) -> dict:
    """Run one scheduled match (in a worker process); returns the race result record."""
    from ..racing.runner import RaceConfig, make_controller, run_race

    folder = Path(folder)
    controllers = []
    for e in spec["entrants"]:
        if e["spec"].startswith("bot:"):
            controller = make_controller(e["spec"])
        else:
            controller = make_controller(str(folder / e["spec"]), step_budget=e["step_budget"])
        controller.name = e["name"]
        controllers.append(controller)
    config = RaceConfig(track=spec["track"], reverse=spec["reverse"], race=spec["race"], laps=spec["laps"],
                        seed=spec["seed"], max_steps=spec["max_steps"])
    recorders = []
    if replay_tmp:
        from ..recording.replay import ReplayRecorder

        recorders.append(ReplayRecorder(replay_tmp, image_every=image_every))
    return run_race(controllers, config, recorders=recorders)


def _handle(request: dict) -> dict:
    if request.get("op") == "validate":
        from ..racing.agentfile import AgentFileError, load_agent

        try:
            agent = load_agent(request["path"], step_budget=request["step_budget"])
        except (AgentFileError, FileNotFoundError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True, "name": agent.name, "sha256": agent.sha256, "metadata": agent.metadata}
    if request.get("op") == "match":
        spec = request["spec"]
        final = request.get("replay")
        tmp = f"{final}.{os.getpid()}.tmp" if final else None
        start = time.perf_counter()
        result = run_match(spec, request["folder"], tmp, request.get("image_every", 0))
        if tmp:
            os.replace(tmp, final)
        return {"ok": True, "result": result, "wall_seconds": time.perf_counter() - start}
    return {"ok": False, "error": f"unknown request {request.get('op')!r}"}


def worker_main() -> int:
    """A league worker: reads one JSON request per line on stdin, answers one JSON line each on stdout.

    The protocol channel is the original stdout; anything the race code prints goes to stderr.
    """
    channel = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    if "--serve" in sys.argv:  # a long-lived match worker: import the heavy parts, then say so
        from ..racing import agentfile, runner  # noqa: F401

        channel.write(json.dumps({"ready": True}) + "\n")
        channel.flush()
    for line in sys.stdin:
        if not line.strip():
            continue
        request = json.loads(line)
        try:
            answer = _handle(request)
        except Exception as exc:  # a bug or environment problem: report it, the parent retries
            import traceback

            answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}",
                      "traceback": traceback.format_exc()[-2000:]}
        channel.write(json.dumps(answer, default=float) + "\n")
        channel.flush()
    return 0


# ------------------------------------------------------------------ Ray
def _ray_match(spec: dict, files: dict, want_replay: bool, image_every: int):
    """A Ray task: run one match in a scratch folder holding its agent files; (result, replay bytes, seconds)."""
    import tempfile

    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="multirace-league-") as scratch:
        scratch = Path(scratch)
        (scratch / SUBMISSIONS).mkdir()
        for rel, data in files.items():
            (scratch / rel).write_bytes(data)
        replay = scratch / "match.rrd" if want_replay else None
        result = run_match(spec, scratch, str(replay) if replay else None, image_every)
        data = replay.read_bytes() if replay else None
    return json.loads(json.dumps(result, default=float)), data, time.perf_counter() - start


def _run_on_ray(folder: Path, config: LeagueConfig, conn, todo, address: str, stats: dict, progress: bool):
    """Run pending matches as Ray tasks (agent files shipped as bytes; results written here, one transaction each)."""
    try:
        import ray
    except ImportError:
        raise LeagueError("--ray: Ray is not installed; install it with: pip install 'multirace[ray]'") from None
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}})
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_ray_match)
        file_refs = {}
        slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
        queue_ = list(todo)
        running = {}  # ObjectRef -> (match_id, spec, started)

        def launch(match_id, spec):
            files = {}
            for e in spec["entrants"]:
                if not e["spec"].startswith("bot:"):
                    if e["spec"] not in file_refs:
                        file_refs[e["spec"]] = (folder / e["spec"]).read_bytes()
                    files[e["spec"]] = file_refs[e["spec"]]
            ref = task.remote(spec, files, config.replays, config.replay_image_every)
            running[ref] = (match_id, spec, time.monotonic())

        with _progress_bar(len(todo), progress) as bar:
            bar_task = bar.add_task("ray", total=len(todo))
            while queue_ or running:
                while queue_ and len(running) < slots:
                    launch(*queue_.pop(0))
                ready, _ = ray.wait(list(running), num_returns=1, timeout=1.0)
                finished = []
                for ref in ready:
                    match_id, spec, _ = running.pop(ref)
                    try:
                        result, replay_bytes, seconds = ray.get(ref)
                        finished.append((match_id, spec, {"ok": True, "result": result, "wall_seconds": seconds},
                                         replay_bytes))
                    except Exception as exc:  # the task raised, or its worker crashed
                        finished.append((match_id, spec, {"ok": False, "error": f"ray task failed: "
                                                          f"{type(exc).__name__}: {str(exc)[:300]}"}, None))
                now = time.monotonic()
                for ref, (match_id, spec, started) in list(running.items()):
                    if now - started > config.match_timeout:
                        ray.cancel(ref, force=True)
                        running.pop(ref)
                        finished.append((match_id, spec, {"ok": False, "error": f"match timed out after "
                                         f"{config.match_timeout:.0f} s wall clock (ray task cancelled)"}, None))
                for match_id, spec, answer, replay_bytes in finished:
                    if answer["ok"]:
                        replay = None
                        if replay_bytes is not None:
                            final = folder / REPLAYS / f"{match_id}.rrd"
                            tmp = final.with_name(f"{final.name}.{os.getpid()}.tmp")
                            tmp.write_bytes(replay_bytes)
                            os.replace(tmp, final)
                            replay = f"{REPLAYS}/{final.name}"
                        record_result(conn, match_id, answer["result"], replay, answer["wall_seconds"])
                        stats["ran"] += 1
                        bar.advance(bar_task)
                    elif record_attempt_failure(conn, match_id, answer["error"], config.max_retries):
                        stats["failed"] += 1
                        bar.advance(bar_task)
                    else:
                        queue_.append((match_id, spec))
    finally:
        ray.shutdown()


DEFAULT_TOML_TEXT = """# An example league (multirace league init DIR copies this file to DIR/league.toml).
# Time trials run under the AWS Summit reset rule (4-minute window, 3 resets;
# scored by best lap, then laps, then progress); head-to-head heats of `cars`
# cars are every `cars`-subset of the entrants, so every pair meets equally
# often, with the grid order rotated from round to round.

[league]
name = "multirace default league"
seeds = [1, 2]                   # every race is run once per seed (and per track and direction)
bots = ["bot:follow@1.5", "bot:follow@0.8"]   # scripted entrants, besides the submitted agent files
step_budget = 0.0667             # seconds per inference step (one 15 Hz frame); slower steps forfeit
max_retries = 2                  # a match whose worker crashes or hangs is retried this often, then failed
match_timeout = 600              # wall-clock seconds per match before its worker is killed
replays = true                   # write replays/<match_id>.rrd for every match
replay_image_every = 0           # record camera images every k-th step (0: poses and events only)

[[tracks]]
name = "reinvent_base"
directions = ["forward", "reverse"]

[[tracks]]
name = "2022_summit_speedway"
directions = ["forward"]

[time_trial]
format = "reset_rule"
laps = 3
trials = 1                       # runs per entrant, track, direction and seed

[head_to_head]
cars = 2                         # cars per heat (2 to 8)
laps = 3
trials = 1                       # runs of each heat per track, direction and seed
"""


# ------------------------------------------------------------------ parent side
class _Worker:
    """A worker subprocess the league parent talks to over pipes; killed and replaced when it fails."""

    def __init__(self):
        self.proc = subprocess.Popen(_worker_command() + ["--serve"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=_worker_env(), bufsize=0)
        self.buffer = b""
        self.ready = False

    def request(self, request: dict, timeout: float) -> dict:
        """Send a request and wait up to `timeout` s; raises _WorkerFailed if it dies or hangs.

        The clock starts once the worker has started up (imports are not the match's time)."""
        if not self.ready:
            if not self._read_line(WORKER_STARTUP_TIMEOUT, "worker start-up").get("ready"):
                raise _WorkerFailed("worker process did not start properly")
            self.ready = True
        try:
            self.proc.stdin.write((json.dumps(request) + "\n").encode())
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise _WorkerFailed(f"worker process died (exit code {self.proc.poll()})") from None
        return self._read_line(timeout, "match")

    def _read_line(self, timeout: float, what: str) -> dict:
        deadline = time.monotonic() + timeout
        fd = self.proc.stdout.fileno()
        while b"\n" not in self.buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise _WorkerFailed(f"{what} timed out after {timeout:.0f} s wall clock (worker hung); killed")
            ready, _, _ = select.select([fd], [], [], min(remaining, 1.0))
            if not ready:
                continue
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                code = self.proc.wait()
                how = f"killed by signal {-code}" if code < 0 else f"exit code {code}"
                raise _WorkerFailed(f"worker process crashed ({how})")
            self.buffer += chunk
        line, self.buffer = self.buffer.split(b"\n", 1)
        return json.loads(line)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()

    def close(self) -> None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.kill()


class _WorkerFailed(Exception):
    pass


def record_result(conn, match_id: str, result: dict, replay: str | None, wall_seconds: float | None) -> bool:
    """Write a match result and mark its schedule row done, in one transaction; False if already recorded."""
    with _Tx(conn):
        cursor = conn.execute(
            "INSERT OR IGNORE INTO results (match_id, status, result, reason, replay, wall_seconds, recorded_at) "
            "VALUES (?, 'ok', ?, NULL, ?, ?, ?)",
            (match_id, json.dumps(result, sort_keys=True, default=float), replay, wall_seconds, time.time()))
        conn.execute("UPDATE schedule SET status='done' WHERE match_id=?", (match_id,))
        return cursor.rowcount == 1


def record_attempt_failure(conn, match_id: str, reason: str, max_retries: int) -> bool:
    """Count a failed attempt; after 1 + max_retries attempts record the match as failed. True if final."""
    with _Tx(conn):
        conn.execute("UPDATE schedule SET attempts=attempts+1, last_error=? WHERE match_id=?", (reason, match_id))
        attempts = conn.execute("SELECT attempts FROM schedule WHERE match_id=?", (match_id,)).fetchone()[0]
        if attempts <= max_retries:
            return False
        conn.execute("INSERT OR IGNORE INTO results (match_id, status, result, reason, replay, wall_seconds, "
                     "recorded_at) VALUES (?, 'failed', NULL, ?, NULL, NULL, ?)",
                     (match_id, f"failed after {attempts} attempts: {reason}", time.time()))
        conn.execute("UPDATE schedule SET status='failed' WHERE match_id=?", (match_id,))
        return True


def pending_matches(conn) -> list[tuple[str, dict]]:
    rows = conn.execute("SELECT s.match_id, s.spec FROM schedule s LEFT JOIN results r USING (match_id) "
                        "WHERE r.match_id IS NULL ORDER BY s.seq").fetchall()
    return [(mid, json.loads(spec)) for mid, spec in rows]


def run_league(folder, workers: int | None = None, ray_address: str | None = None, progress: bool = True,
               only_ids=None) -> dict:
    """Run every pending match of the league; returns {"ran", "failed", "skipped", "wall_seconds"}."""
    folder = Path(folder).resolve()
    config = load_config(folder)
    if ray_address:
        try:
            import ray  # noqa: F401
        except ImportError:
            raise LeagueError("--ray: Ray is not installed; install it with: pip install 'multirace[ray]'") from None
    conn = connect(folder)
    try:
        schedule = sync_schedule(folder, config, conn)
        current = {row["match_id"] for row in schedule}
        todo = [(mid, spec) for mid, spec in pending_matches(conn) if mid in current]
        if only_ids is not None:
            todo = [(mid, spec) for mid, spec in todo if mid in set(only_ids)]
        (folder / REPLAYS).mkdir(exist_ok=True)
        for stale in (folder / REPLAYS).glob("*.tmp"):
            stale.unlink(missing_ok=True)  # left by a killed run; the match is still pending
        start = time.perf_counter()
        stats = {"scheduled": len(schedule), "ran": 0, "failed": 0, "pending_at_start": len(todo)}
        if todo:
            if ray_address:
                _run_on_ray(folder, config, conn, todo, ray_address, stats, progress)
            else:
                _run_local(folder, config, conn, todo, workers or os.cpu_count() or 1, stats, progress)
        stats["wall_seconds"] = round(time.perf_counter() - start, 3)
        return stats
    finally:
        conn.close()


def _progress_bar(total: int, enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
        TimeRemainingColumn

    return Progress(TextColumn("league"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), TextColumn("{task.description}"), disable=not enabled,
                    transient=False)


def _run_local(folder: Path, config: LeagueConfig, conn, todo, n_workers: int, stats: dict, progress: bool):
    jobs: queue.Queue = queue.Queue()
    for item in todo:
        jobs.put(item)
    done: queue.Queue = queue.Queue()
    stop = threading.Event()

    def slot():
        worker = None
        try:
            while not stop.is_set():
                try:
                    match_id, spec = jobs.get(timeout=0.2)
                except queue.Empty:
                    continue
                replay = str(folder / REPLAYS / f"{match_id}.rrd") if config.replays else None
                request = {"op": "match", "spec": spec, "folder": str(folder), "replay": replay,
                           "image_every": config.replay_image_every}
                try:
                    if worker is None:
                        worker = _Worker()
                    answer = worker.request(request, config.match_timeout)
                except (_WorkerFailed, OSError, ValueError) as exc:  # died, hung, or spoke garbage
                    if worker is not None:
                        worker.kill()
                    worker = None
                    answer = {"ok": False, "error": str(exc) if isinstance(exc, _WorkerFailed)
                              else f"worker failed: {type(exc).__name__}: {exc}"}
                done.put((match_id, spec, answer, replay))
        finally:
            if worker is not None:
                worker.close()

    with _progress_bar(len(todo), progress) as bar:
        task = bar.add_task("", total=len(todo))
        threads = [threading.Thread(target=slot, daemon=True) for _ in range(max(1, min(n_workers, len(todo))))]
        for t in threads:
            t.start()
        outstanding = len(todo)
        try:
            while outstanding:
                match_id, spec, answer, replay = done.get()
                if answer.get("ok"):
                    record_result(conn, match_id, answer["result"],
                                  os.path.relpath(replay, folder) if replay else None, answer.get("wall_seconds"))
                    stats["ran"] += 1
                    outstanding -= 1
                    bar.advance(task)
                elif record_attempt_failure(conn, match_id, answer.get("error", "unknown error"),
                                            config.max_retries):
                    stats["failed"] += 1
                    outstanding -= 1
                    bar.advance(task)
                else:
                    jobs.put((match_id, spec))  # retry it (on a fresh worker if the old one failed)
                bar.update(task, description=f"{stats['failed']} failed" if stats["failed"] else "")
        finally:
            stop.set()
        for t in threads:
            t.join(timeout=10)


# ------------------------------------------------------------------ command line
def add_league_commands(sub) -> None:
    """Add `multirace league init|submit|run|table` to the CLI's subparsers."""
    league = sub.add_parser("league", help="run a league: submissions, schedule, ratings, tables",
                            description="A league is a folder: league.toml, submissions/, results.sqlite, "
                                        "replays/ and tables.")
    league_sub = league.add_subparsers(dest="league_command", required=True)
    init = league_sub.add_parser("init", help="create a league folder from league/default.toml")
    init.add_argument("dir", help="the league folder to create")
    init.add_argument("--from", dest="template", metavar="TOML", help="start from this league.toml instead")
    init.set_defaults(func=_cmd_init)
    sub_ = league_sub.add_parser("submit", help="validate an agent file and add it to the league",
                                 description="Validates the file as a race would (safe load, metadata, smoke "
                                             "inference within the league's step budget) in a subprocess, then "
                                             "stores it by sha256. Duplicates and bad files are refused.")
    sub_.add_argument("dir", help="the league folder")
    sub_.add_argument("file", help="agent file (.pt)")
    sub_.add_argument("--name", required=True, help="the entrant's name in the league")
    sub_.set_defaults(func=_cmd_submit)
    run = league_sub.add_parser("run", help="run every pending match (resumable)",
                                description="Builds the schedule and runs the matches without a result, in "
                                            "worker processes; safe to kill and run again.")
    run.add_argument("dir", help="the league folder")
    run.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    run.add_argument("--ray", metavar="ADDRESS", default=None,
                     help="run matches as Ray tasks on this cluster (e.g. auto or ray://host:10001)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=_cmd_run)
    table = league_sub.add_parser("table", help="print or export the league table",
                                  description="Ratings (OpenSkill Plackett-Luce ordinal), time-trial standings "
                                              "and clean driving; also writes DIR/ratings.png.")
    table.add_argument("dir", help="the league folder")
    table.add_argument("--format", dest="table_format", default="md", choices=("md", "csv", "json", "html"))
    table.add_argument("--out", metavar="FILE", help="write the table to FILE instead of printing it")
    table.set_defaults(func=_cmd_table)


def _cmd_init(args) -> int:
    folder = init_league(args.dir, args.template)
    print(f"created league {folder} (edit {folder / TOML}, then 'multirace league submit {folder} FILE.pt "
          f"--name NAME')")
    return 0


def _cmd_submit(args) -> int:
    try:
        row = submit(args.dir, args.file, args.name)
    except LeagueError as exc:
        print(f"multirace league submit: {exc}", file=sys.stderr)
        return 1
    print(f"submitted {row['name']} ({row['sha256'][:12]}) as {row['file']}")
    return 0


def _cmd_run(args) -> int:
    if args.workers is not None and args.workers < 1:
        raise LeagueError("--workers: must be at least 1")
    stats = run_league(args.dir, workers=args.workers, ray_address=args.ray, progress=not args.quiet)
    print(f"league run: {stats['ran']} matches run, {stats['failed']} failed, {stats['scheduled']} scheduled, "
          f"{stats['wall_seconds']:.1f} s")
    return 0


def _cmd_table(args) -> int:
    from .table import write_table

    text = write_table(args.dir, args.table_format, args.out)
    if args.out:
        print(f"wrote {args.out}")
    else:
        sys.stdout.write(text)
    return 0


# ------------------------------------------------------------------ entry point for workers
if __name__ == "__main__":
    if sys.argv[1:2] == ["worker"]:
        sys.exit(worker_main())
    print("usage: python -m multirace.league.core worker", file=sys.stderr)
    sys.exit(2)
