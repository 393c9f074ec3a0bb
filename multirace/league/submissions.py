"""Creating a league folder and submitting agent files to it (validated in a worker subprocess)."""
from __future__ import annotations

import hashlib
import re
import stat
import json
import os
import sqlite3
import subprocess
import time
from pathlib import Path

from ..atomic import AtomicOutput, output_error, write_text
from .config import (DB, DEFAULT_TOML, REPLAYS, SUBMISSIONS, SUBMIT_TIMEOUT, TOML, LeagueError, load_config,
                     parse_config)
from .store import _Tx, connect, create_store
from .worker import _worker_command, _worker_env


MAX_SUBMISSION_BYTES = 256 * 2**20  # as an agent file's limit
ENTRANT_NAME = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9 _.+@:-]{0,62}[A-Za-z0-9_.+@:-])?")


def init_league(folder, template=None) -> Path:
    """Create a league folder from a template league.toml (default: league/default.toml)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise LeagueError(f"{folder}: exists and is not a folder; choose a new folder for the league")
    if (folder / TOML).exists():
        raise LeagueError(f"{folder / TOML}: already exists; this folder is a league already")
    if (folder / DB).exists():
        raise LeagueError(f"{folder / DB}: already exists (a league's results without its league.toml); "
                          "choose a new folder, or put the league's league.toml back")
    template = Path(template) if template else DEFAULT_TOML
    if not template.is_file():
        raise LeagueError(f"{template}: no such league definition (--from names a league.toml file)")
    try:
        text = template.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise LeagueError(f"{template}: unreadable ({exc})") from None
    parse_config(text, str(template))
    try:
        for made in (folder, folder / SUBMISSIONS, folder / REPLAYS):
            made.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LeagueError(f"{folder}: cannot create the league folder here ({exc.strerror or exc})") from None
    write_text(folder / TOML, text)
    create_store(folder)
    return folder


def _read_submission(path: Path) -> bytes:
    """The bytes of a submitted file, read once: a regular file (no FIFO or device) under the agent-file size
    limit. The open file itself is checked (a path swapped for a FIFO after a check cannot block the read)."""
    refused = f"{path}: refused: not a regular file under {MAX_SUBMISSION_BYTES // 2**20} MB"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise LeagueError(f"{path}: cannot be read ({exc.strerror})") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_SUBMISSION_BYTES:
        os.close(fd)
        raise LeagueError(refused)
    with open(fd, "rb") as handle:
        data = handle.read(MAX_SUBMISSION_BYTES + 1)
    if len(data) > MAX_SUBMISSION_BYTES:  # it grew while being read
        raise LeagueError(refused)
    return data


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


def check_entrant_name(name, config) -> None:
    """Raise LeagueError unless `name` can be an entrant of the league: the name pattern, not a bot's name."""
    if not isinstance(name, str) or not ENTRANT_NAME.fullmatch(name) or name.startswith("bot:"):
        raise LeagueError(f"--name: {name!r} is not a valid entrant name: 1-64 letters, digits, spaces and "
                          "_ . - + @ : (starting with a letter or digit), not 'bot:...'")
    if name in config.bots:
        raise LeagueError(f"--name: {name!r} is a bot of this league")


def submit(folder, path, name: str, step_budget: float | None = None, validate: bool = True) -> dict:
    """Validate an agent file and store it in the league by content hash; returns its submission row.

    `step_budget` overrides the league's per-step inference budget for this entrant
    (None: the league's). `validate=False` skips validation (for tests of in-race misbehaviour).
    """
    folder = Path(folder)
    config = load_config(folder)
    path = Path(path)
    if not path.exists():
        raise LeagueError(f"{path}: no such agent file")
    check_entrant_name(name, config)
    data = _read_submission(path)
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
        stored = folder / SUBMISSIONS / f"{sha}.pt"
        output = AtomicOutput(stored.resolve())
        copy = output.tmp  # the copy is what is validated and stored
        try:
            try:
                copy.write_bytes(data)
            except OSError as exc:
                raise output_error(stored, exc) from None
            if validate:
                check = validate_in_subprocess(copy, step_budget or config.step_budget)
                if not check.get("ok"):
                    raise LeagueError(f"refused: {str(check.get('error')).replace(str(copy), str(path))}")
                metadata = check.get("metadata") or {}
            try:
                with _Tx(conn):  # the file and its row appear together for every reader of the store
                    conn.execute("INSERT INTO submissions (name, sha256, file, metadata, step_budget, "
                                 "submitted_at) VALUES (?, ?, ?, ?, ?, ?)",
                                 (name, sha, f"{SUBMISSIONS}/{sha}.pt", json.dumps(metadata, sort_keys=True),
                                  step_budget, time.time()))
                    output.commit()
            except sqlite3.IntegrityError:
                raise LeagueError(f"--name: refused: {name!r} or this file (sha256 {sha[:12]}) was submitted "
                                  "meanwhile by another submit") from None
        finally:
            output.discard()
        return {"name": name, "sha256": sha, "file": str(stored), "metadata": metadata}
    finally:
        conn.close()
