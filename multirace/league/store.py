"""The league's results store: one SQLite file, written in transactions; results and retries."""
from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import time
from pathlib import Path

from .config import DB, SUBMISSIONS, LeagueError


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


COLUMNS = {"submissions": {"name", "sha256", "file", "metadata", "step_budget", "submitted_at"},
           "schedule": {"match_id", "seq", "kind", "round", "spec", "status", "attempts", "last_error"},
           "results": {"match_id", "status", "result", "reason", "replay", "wall_seconds", "recorded_at"}}
BUSY_TIMEOUT = 60.0  # seconds to wait for another process's write transaction
RECOVER = ("restore results.sqlite from a backup, or start a new league with `multirace league init NEW_DIR` and "
           "submit the agents again (their files are in submissions/)")


READ_ONLY = ("make the folder and its files writable, or copy the league to a writable folder (`multirace "
             "league table` reads a read-only league)")


def _open(path: Path, readonly: bool = False) -> sqlite3.Connection:
    if readonly and not _writable(path.parent):  # a folder nobody may write to cannot hold SQLite's lock files
        immutable = not path.with_name(path.name + "-wal").exists()  # nor be written meanwhile
        uri = f"{path.resolve().as_uri()}?mode=ro" + ("&immutable=1" if immutable else "")
        return sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT, isolation_level=None)
    conn = sqlite3.connect(path, timeout=BUSY_TIMEOUT, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=FULL")
    conn.execute("PRAGMA foreign_keys=ON")
    return conn


def create_store(folder) -> None:
    """Create a new league's empty store."""
    conn = _open(Path(folder) / DB)
    conn.executescript(SCHEMA)
    conn.close()


def _writable(path: Path) -> bool:
    return os.access(path, os.W_OK)


def check_writable(folder) -> None:
    """Raise LeagueError, saying so, if the league folder or its store is read-only."""
    folder = Path(folder)
    if not (_writable(folder) and (not (folder / DB).exists() or _writable(folder / DB))):
        raise LeagueError(f"{folder}: read-only: this command records to the league's store; {READ_ONLY}")


def connect(folder, readonly: bool = False) -> sqlite3.Connection:
    """The league's SQLite store, in WAL mode with a generous busy timeout, checked first: it exists, is
    intact (SQLite's quick_check), has the expected tables, agrees with the submissions folder, and every
    stored submission still has the sha256 it was stored under.
    A damaged or missing store is a LeagueError that says how to recover; nothing is recreated silently.
    `readonly`: only read (works on a read-only folder); otherwise a read-only folder is a LeagueError saying so."""
    folder = Path(folder)
    path = folder / DB
    if not path.is_file() or path.stat().st_size == 0:
        state = "missing" if not path.exists() else "empty (truncated)"
        raise LeagueError(f"{path}: {state}: the league's history is gone; {RECOVER}")
    if not readonly:
        check_writable(folder)
    conn = None
    try:
        conn = _open(path, readonly)
        _check(conn, folder, readonly)
    except sqlite3.DatabaseError as exc:
        if conn is not None:
            conn.close()
        if isinstance(exc, sqlite3.OperationalError) and ("locked" in str(exc) or "busy" in str(exc)):
            raise LeagueError(f"{path}: busy: another process has held the store for over {BUSY_TIMEOUT:.0f} s "
                              "(a stopped or hung `multirace league` command?); try again once it has finished"
                              ) from None
        if isinstance(exc, sqlite3.OperationalError) and "readonly" in str(exc).replace("-", "").replace(" ", ""):
            raise LeagueError(f"{folder}: read-only ({exc}); {READ_ONLY}") from None
        raise LeagueError(f"{path}: damaged ({exc}); {RECOVER}") from None
    except LeagueError:
        conn.close()
        raise
    return conn


def _check(conn: sqlite3.Connection, folder: Path, readonly: bool = False) -> None:
    """Raise LeagueError unless the store is intact, has the expected tables and agrees with submissions/
    (every stored file there, with the sha256 it was stored under).

    Runs in an IMMEDIATE transaction (a plain one when `readonly`), as `submit` stores a file and its row, so
    it never sees a submission half made by a concurrent submit."""
    path = folder / DB
    check = conn.execute("PRAGMA quick_check").fetchone()[0]
    if check != "ok":
        raise LeagueError(f"{path}: damaged (SQLite integrity check: {check}); {RECOVER}")
    for table, wanted in COLUMNS.items():
        found = {row[1] for row in conn.execute(f"PRAGMA table_info({table})")}
        if not wanted <= found:
            lack = "is missing" if not found else "lacks " + ", ".join(sorted(wanted - found))
            raise LeagueError(f"{path}: not a multirace league store (table {table!r} {lack}); {RECOVER}")
    with _Tx(conn, "DEFERRED" if readonly else "IMMEDIATE"):
        rows = conn.execute("SELECT name, sha256, file FROM submissions ORDER BY name").fetchall()
        stored = {Path(row[2]).name for row in rows}
        if conn.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='versions'").fetchone():
            stored |= {Path(row[0]).name for row in conn.execute("SELECT file FROM versions")}  # earlier uploads
        on_disk = {p.name for p in (folder / SUBMISSIONS).glob("*.pt")}
    missing, unknown = sorted(stored - on_disk), sorted(on_disk - stored)
    if missing:
        raise LeagueError(f"{folder}: the store and the submissions folder disagree: {len(missing)} submitted "
                          f"file(s) missing from submissions/ ({', '.join(missing[:3])}); {RECOVER}")
    if unknown:
        raise LeagueError(f"{folder}: the store and the submissions folder disagree: {len(unknown)} file(s) in "
                          f"submissions/ that the store does not know ({', '.join(unknown[:3])}): remove them (a "
                          f"file left by an interrupted submit) or {RECOVER}")
    for name, sha, file in rows:
        problem = submission_problem(folder, name, sha, file)
        if problem:
            raise LeagueError(f"{folder}: {problem}")


def submission_problem(folder, name: str, sha: str, file: str) -> str | None:
    """Why entrant `name`'s stored file cannot be trusted (unreadable, or bytes whose sha256 is not the one
    it was stored under), or None if it can. Submissions are named by their sha256, so a file replaced or
    damaged after it was submitted shows here."""
    path = Path(folder) / file
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                digest.update(chunk)
    except OSError as exc:
        return f"entrant {name!r}: its stored file {file} cannot be read ({exc.strerror or exc})"
    if digest.hexdigest() != sha:
        return (f"entrant {name!r}: its stored file {file} was replaced or damaged after submission (sha256 "
                f"{digest.hexdigest()[:12]}, submitted as {sha[:12]}); put the submitted file back (its sha256 is "
                "its name) or submit the agent again in a new league")
    return None


class _Tx:
    """`with _Tx(conn):` one IMMEDIATE transaction (or `kind`), committed on success, rolled back on error."""

    def __init__(self, conn, kind: str = "IMMEDIATE"):
        self.conn = conn
        self.kind = kind

    def __enter__(self):
        self.conn.execute(f"BEGIN {self.kind}")
        return self.conn

    def __exit__(self, kind, exc, tb):
        self.conn.execute("COMMIT" if kind is None else "ROLLBACK")
        return False


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
