"""`multirace league run DIR --watch`: run what is pending, then what each new version needs, until stopped.

The schedule names every entrant's file by sha256, so a new version makes new matches (those it races in)
while every other match keeps its id and its result: a watch runs only those. Each result is committed with
its schedule row as in `league run`, so a watch killed at any point and started again loses nothing.
"""
from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

from .store import connect
from .runner import run_league


def _signature(folder) -> tuple:
    """What decides the schedule: the entrants' racing files and the league definition."""
    conn = connect(folder)
    try:
        files = tuple(conn.execute("SELECT name, sha256 FROM submissions ORDER BY name").fetchall())
    finally:
        conn.close()
    return files, (Path(folder) / "league.toml").stat().st_mtime_ns


def watch_league(folder, workers: int | None = None, ray_address: str | None = None, poll: float = 2.0,
                 stop: threading.Event | None = None, say=print) -> int:
    """Run the league's pending matches whenever its entrants change, until `stop` is set or SIGTERM/SIGINT;
    returns how many matches were run."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    seen, total = None, 0
    while not stop.is_set():
        now = _signature(folder)
        if now != seen:
            stats = run_league(folder, workers=workers, ray_address=ray_address, progress=False)
            total += stats["ran"]
            if stats["ran"] or stats["failed"]:
                say(f"{time.strftime('%H:%M:%S')} league run: {stats['ran']} matches run, {stats['failed']} "
                    f"failed, {stats['scheduled']} scheduled")
            seen = now
        stop.wait(poll)
    return total
