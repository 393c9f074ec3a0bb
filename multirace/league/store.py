"""The league's results store: one SQLite file, written in transactions; results and retries."""
from __future__ import annotations

import json
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


def _open(path: Path) -> sqlite3.Connection:
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


def connect(folder) -> sqlite3.Connection:
    """The league's SQLite store, in WAL mode with a generous busy timeout, checked first: it exists, is
    intact (SQLite's quick_check), has the expected tables, and agrees with the submissions folder.
    A damaged or missing store is a LeagueError that says how to recover; nothing is recreated silently."""
    folder = Path(folder)
    path = folder / DB
    if not path.is_file() or path.stat().st_size == 0:
        state = "missing" if not path.exists() else "empty (truncated)"
        raise LeagueError(f"{path}: {state}: the league's history is gone; {RECOVER}")
    conn = None
    try:
        conn = _open(path)
        _check(conn, folder)
    except sqlite3.DatabaseError as exc:
        if conn is not None:
            conn.close()
        if isinstance(exc, sqlite3.OperationalError) and ("locked" in str(exc) or "busy" in str(exc)):
            raise LeagueError(f"{path}: busy: another process has held the store for over {BUSY_TIMEOUT:.0f} s "
                              "(a stopped or hung `multirace league` command?); try again once it has finished"
                              ) from None
        raise LeagueError(f"{path}: damaged ({exc}); {RECOVER}") from None
    except LeagueError:
        conn.close()
        raise
    return conn


def _check(conn: sqlite3.Connection, folder: Path) -> None:
    """Raise LeagueError unless the store is intact, has the expected tables and agrees with submissions/.

    Runs in an IMMEDIATE transaction, as `submit` stores a file and its row, so it never sees a submission
    half made by a concurrent submit."""
    path = folder / DB
    check = conn.execute("PRAGMA quick_check").fetchone()[0]
    if check != "ok":
        raise LeagueError(f"{path}: damaged (SQLite integrity check: {check}); {RECOVER}")
    for table, wanted in COLUMNS.items():
        found = {row[1] for row in conn.execute(f"PRAGMA table_info({table})")}
        if not wanted <= found:
            lack = "is missing" if not found else "lacks " + ", ".join(sorted(wanted - found))
            raise LeagueError(f"{path}: not a multirace league store (table {table!r} {lack}); {RECOVER}")
    with _Tx(conn):
        stored = {Path(row[0]).name for row in conn.execute("SELECT file FROM submissions")}
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
