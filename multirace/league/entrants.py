"""Entrants who submit from the web: tokens (stored only as their sha256) and versions of their agent files.

`multirace league entrant add DIR NAME` creates an entrant and prints its token once. An entrant uploads
agent files with that token; each upload goes through the checks of `league submit` (size capped, the
safe loader and the smoke inference in a subprocess) and becomes the entrant's next version. Every version's
file stays in submissions/ (by sha256) and in the `versions` table; the `submissions` row of the entrant
points at the newest, which is the one that races (the schedule then holds the matches the new version needs).
"""
from __future__ import annotations

import hashlib
import json
import os
import secrets
import sqlite3
import time
from pathlib import Path

from .config import SUBMISSIONS, LeagueError, load_config
from .store import _Tx, connect
from .submissions import MAX_SUBMISSION_BYTES, check_entrant_name, validate_in_subprocess

TOKEN_BYTES = 32
ENTRANT_TABLES = """
CREATE TABLE IF NOT EXISTS entrants (name TEXT PRIMARY KEY, token_sha256 TEXT NOT NULL UNIQUE,
                                     created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS versions (name TEXT NOT NULL, version INTEGER NOT NULL, sha256 TEXT NOT NULL UNIQUE,
                                     file TEXT NOT NULL, metadata TEXT NOT NULL, submitted_at REAL NOT NULL,
                                     PRIMARY KEY (name, version));
"""


def ensure_tables(conn) -> None:
    """Create the entrants and versions tables in a league made before they existed (no-op otherwise)."""
    conn.executescript(ENTRANT_TABLES)


def token_hash(token: str) -> str:
    """The sha256 (hex) under which a token is stored; the token itself is never stored."""
    return hashlib.sha256(token.encode("utf-8", "replace")).hexdigest()


def add_entrant(folder, name: str) -> str:
    """Create an entrant who may upload agent files; returns its token (shown once, stored hashed)."""
    config = load_config(folder)
    check_entrant_name(name, config)
    token = secrets.token_urlsafe(TOKEN_BYTES)
    conn = connect(folder)
    try:
        ensure_tables(conn)
        try:
            with _Tx(conn):
                conn.execute("INSERT INTO entrants (name, token_sha256, created_at) VALUES (?, ?, ?)",
                             (name, token_hash(token), time.time()))
        except sqlite3.IntegrityError:
            raise LeagueError(f"NAME: an entrant named {name!r} exists already") from None
    finally:
        conn.close()
    return token


def entrant_for_token(conn, token) -> str | None:
    """The name of the entrant whose token this is, or None (a missing, malformed or unknown token)."""
    if not isinstance(token, str) or not 20 <= len(token) <= 200:
        return None
    ensure_tables(conn)
    row = conn.execute("SELECT name FROM entrants WHERE token_sha256=?", (token_hash(token),)).fetchone()
    return row[0] if row else None


def versions_of(conn, name: str) -> list[dict]:
    """An entrant's versions, oldest first: {"version", "sha256", "metadata", "submitted_at", "racing"}."""
    ensure_tables(conn)
    current = conn.execute("SELECT sha256, metadata, submitted_at FROM submissions WHERE name=?", (name,)).fetchone()
    rows = conn.execute("SELECT version, sha256, metadata, submitted_at FROM versions WHERE name=? ORDER BY version",
                        (name,)).fetchall()
    out = [{"version": v, "sha256": sha, "metadata": json.loads(meta), "submitted_at": at}
           for v, sha, meta, at in rows]
    if current and not any(v["sha256"] == current[0] for v in out):  # submitted with `league submit`
        out.append({"version": len(out) + 1, "sha256": current[0], "metadata": json.loads(current[1]),
                    "submitted_at": current[2]})
    for v in out:
        v["racing"] = bool(current) and v["sha256"] == current[0]
    return out


def _write_copy(folder: Path, sha: str, data: bytes) -> Path:
    """The upload written under a unique temporary name in submissions/ (what is validated, then renamed)."""
    copy = (folder / SUBMISSIONS).resolve() / f".{sha}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    with open(copy, "xb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    return copy


def remove_stale_uploads(folder) -> int:
    """Delete the temporary upload files in submissions/ left by processes that no longer run (killed mid-
    upload); returns how many. A file of a live process (an upload being validated) is left alone."""
    removed = 0
    for tmp in (Path(folder) / SUBMISSIONS).glob(".*.tmp"):
        parts = tmp.name.split(".")
        pid = int(parts[2]) if len(parts) > 3 and parts[2].isdigit() else None
        if pid is not None and pid != os.getpid() and not Path(f"/proc/{pid}").exists():
            tmp.unlink(missing_ok=True)
            removed += 1
    return removed


def _refuse_duplicate(conn, name: str, sha: str) -> None:
    row = conn.execute("SELECT name FROM submissions WHERE sha256=? UNION SELECT name FROM versions WHERE sha256=?",
                       (sha, sha)).fetchone()
    if row and row[0] == name:
        raise LeagueError("refused: this file is one of your versions already (same sha256)")
    if row:
        raise LeagueError("refused: this file was submitted already by another entrant (same sha256)")


def upload_version(folder, name: str, data: bytes) -> dict:
    """Validate an uploaded agent file as `league submit` does and make it `name`'s newest (racing) version.

    Returns {"name", "version", "sha256", "metadata"}; raises LeagueError with a plain reason when refused.
    The file and its rows appear together in one transaction; a process killed before the commit leaves
    only a temporary file, never a half-made version."""
    folder = Path(folder)
    config = load_config(folder)
    if len(data) > MAX_SUBMISSION_BYTES:
        raise LeagueError(f"refused: the file is over {MAX_SUBMISSION_BYTES // 2**20} MB")
    sha = hashlib.sha256(data).hexdigest()
    conn = connect(folder)
    try:
        ensure_tables(conn)
        _refuse_duplicate(conn, name, sha)
        copy = _write_copy(folder, sha, data)
        try:
            check = validate_in_subprocess(copy, config.step_budget)
            if not check.get("ok"):
                raise LeagueError("refused: " + str(check.get("error")).replace(str(copy), "the uploaded file"))
            metadata = json.dumps(check.get("metadata") or {}, sort_keys=True)
            stored = f"{SUBMISSIONS}/{sha}.pt"
            with _Tx(conn):
                _refuse_duplicate(conn, name, sha)
                version = _record_version(conn, name, sha, stored, metadata)
                os.replace(copy, folder / stored)
        finally:
            copy.unlink(missing_ok=True)
    finally:
        conn.close()
    return {"name": name, "version": version, "sha256": sha, "metadata": json.loads(metadata)}


def _record_version(conn, name: str, sha: str, stored: str, metadata: str) -> int:
    """Inside a transaction: add the version row and point the entrant's submission at it; its number."""
    now = time.time()
    previous = conn.execute("SELECT sha256, file, metadata, submitted_at FROM submissions WHERE name=?",
                            (name,)).fetchone()
    count = conn.execute("SELECT COALESCE(MAX(version), 0) FROM versions WHERE name=?", (name,)).fetchone()[0]
    if previous and count == 0:  # the entrant's file from `league submit` becomes version 1
        count = 1
        conn.execute("INSERT INTO versions VALUES (?, 1, ?, ?, ?, ?)", (name, *previous))
    conn.execute("INSERT INTO versions VALUES (?, ?, ?, ?, ?, ?)", (name, count + 1, sha, stored, metadata, now))
    if previous:
        conn.execute("UPDATE submissions SET sha256=?, file=?, metadata=?, submitted_at=? WHERE name=?",
                     (sha, stored, metadata, now, name))
    else:
        conn.execute("INSERT INTO submissions (name, sha256, file, metadata, step_budget, submitted_at) "
                     "VALUES (?, ?, ?, ?, NULL, ?)", (name, sha, stored, metadata, now))
    return count + 1
