"""What the league's pages and JSON API show, read from the league's SQLite store.

The leaderboard is `table.compute_table` (the same numbers as `multirace league table`) plus time-trial best
laps per track, cached until the store changes. Entrant and match views read every recorded result, those of
earlier versions included.
"""
from __future__ import annotations

import json
import re
import threading
from datetime import datetime, timezone
from pathlib import Path

from ..config import REPLAYS, load_config
from ..entrants import versions_of
from ..store import connect
from ..table import compute_table

MATCH_ID = re.compile(r"[0-9a-f]{16}")
CAR_FIELDS = ("name", "position", "status", "reason", "laps", "lap_times", "best_lap", "total_time", "resets",
              "penalties", "collisions", "collisions_caused", "progress")


def iso(timestamp) -> str | None:
    """A Unix time as an ISO 8601 UTC string (DeepRacer's JSON uses these), None for None."""
    if timestamp is None:
        return None
    return datetime.fromtimestamp(timestamp, timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


def track_label(track: str, reverse: bool) -> str:
    """How a track and direction are named in tables: `reinvent_base` or `reinvent_base (reverse)`."""
    return f"{track} (reverse)" if reverse else track


class League:
    """Read access to one league folder, with the leaderboard cached until the store changes."""

    def __init__(self, folder):
        self.folder = Path(folder).resolve()
        self.name = load_config(self.folder).name
        self._lock = threading.Lock()
        self._cached = (None, None)

    def signature(self) -> tuple:
        """What changes whenever the leaderboard may change: results, submissions, the definition."""
        conn = connect(self.folder)
        try:
            results = conn.execute("SELECT COUNT(*), MAX(recorded_at) FROM results").fetchone()
            subs = conn.execute("SELECT COUNT(*), MAX(submitted_at) FROM submissions").fetchone()
        finally:
            conn.close()
        return tuple(results) + tuple(subs) + ((self.folder / "league.toml").stat().st_mtime_ns,)

    def leaderboard(self) -> dict:
        """compute_table's table plus `tracks_tt` (track labels) and each standing's `tt_by_track`."""
        signature = self.signature()
        with self._lock:
            if self._cached[0] == signature:
                return self._cached[1]
            table = compute_table(self.folder)
            best: dict = {}
            for m in table["matches"]:
                if m["kind"] == "time_trial" and m["status"] == "ok":
                    label = track_label(m["track"], m["reverse"])
                    for car in m["cars"]:
                        if car["best_lap"] is not None:
                            slot = best.setdefault(car["name"], {})
                            slot[label] = min(slot.get(label, car["best_lap"]), car["best_lap"])
            table["tracks_tt"] = [track_label(t["name"], d == "reverse") for t in table["tracks"]
                                  for d in t["directions"]]
            for s in table["standings"]:
                s["tt_by_track"] = best.get(s["entrant"], {})
            table["signature"] = "-".join(str(x) for x in signature)
            self._cached = (signature, table)
            return table

    def _rows(self, where: str = "", args=()) -> list:
        conn = connect(self.folder)
        try:
            return conn.execute("SELECT s.match_id, s.seq, s.kind, s.round, s.spec, r.status, r.result, r.reason, "
                                "r.replay, r.recorded_at FROM schedule s JOIN results r USING (match_id) "
                                f"{where} ORDER BY r.recorded_at DESC, s.seq", args).fetchall()
        finally:
            conn.close()

    def versions_by_entrant(self) -> dict:
        """{entrant: [its versions, oldest first]} of every entrant who has submitted."""
        conn = connect(self.folder)
        try:
            names = [row[0] for row in conn.execute("SELECT name FROM submissions ORDER BY name")]
            return {name: versions_of(conn, name) for name in names}
        finally:
            conn.close()

    def _versions(self) -> dict:
        """{sha256: (entrant, version)} of every version ever submitted."""
        return {v["sha256"]: (name, v["version"]) for name, vs in self.versions_by_entrant().items() for v in vs}

    def matches(self, entrant: str | None = None, limit: int | None = None) -> list[dict]:
        """Recorded matches, newest first (optionally those `entrant` drove in), each as `match()` gives it."""
        versions = self._versions()
        out = []
        for row in self._rows():
            match = _match_view(row, versions)
            if entrant is None or entrant in [e["name"] for e in match["entrants"]]:
                out.append(match)
            if limit is not None and len(out) >= limit:
                break
        return out

    def match(self, match_id: str) -> dict | None:
        """One recorded match: kind, track, seed, entrants (with versions), per-car results; None if unknown."""
        if not MATCH_ID.fullmatch(match_id or ""):
            return None
        rows = self._rows("WHERE s.match_id=?", (match_id,))
        return _match_view(rows[0], self._versions()) if rows else None

    def replay_path(self, match_id: str) -> Path | None:
        """The replay file of a recorded match, only if it lies in the league's replays/ folder."""
        match = self.match(match_id)
        if not match or not match["replay"]:
            return None
        path = (self.folder / match["replay"]).resolve()
        if path.parent != self.folder / REPLAYS or not path.is_file():
            return None
        return path

    def entrant(self, name: str) -> dict | None:
        """An entrant's versions, matches and rating history; None if no such entrant has submitted."""
        conn = connect(self.folder)
        try:
            if not conn.execute("SELECT 1 FROM submissions WHERE name=?", (name,)).fetchone():
                return None
            versions = versions_of(conn, name)
        finally:
            conn.close()
        table = self.leaderboard()
        standing = next((s for s in table["standings"] if s["entrant"] == name), None)
        history = [{"round": h["round"], "rating": h["ordinal"].get(name)} for h in table["rating_history"]
                   if name in h["ordinal"]]
        for v in versions:
            v["submitted_at"] = iso(v["submitted_at"])
        return {"name": name, "versions": versions, "standing": standing, "rating_history": history,
                "matches": self.matches(entrant=name)}


def _match_view(row, versions: dict) -> dict:
    match_id, seq, kind, round_no, spec, status, result, reason, replay, recorded_at = row
    spec = json.loads(spec)
    entrants = []
    for e in spec["entrants"]:
        version = versions.get(e.get("sha256"), (None, None))[1] if e.get("sha256") else None
        entrants.append({"name": e["name"], "version": version, "bot": e["spec"].startswith("bot:")})
    view = {"match_id": match_id, "seq": seq, "kind": kind, "round": round_no, "track": spec["track"],
            "reverse": spec["reverse"], "track_label": track_label(spec["track"], spec["reverse"]),
            "seed": spec["seed"], "laps": spec["laps"], "status": status, "reason": reason, "replay": replay,
            "recorded_at": iso(recorded_at), "entrants": entrants, "cars": []}
    if status == "ok":
        cars = json.loads(result)["cars"]
        view["cars"] = sorted(({k: c.get(k) for k in CAR_FIELDS} for c in cars), key=lambda c: c["position"])
    return view


def deepracer_rankings(table: dict, versions: dict) -> dict:
    """The leaderboard in the shape of DeepRacer on AWS's public rankings JSON (`rankings` of `rank`,
    `rankingScore`, `userProfile.alias`, `submissionNumber`, `stats`), with multirace's own fields in `stats`."""
    rankings = []
    for s in table["standings"]:
        own = versions.get(s["entrant"], [])
        rankings.append({
            "rank": s["rank"], "rankingScore": s["rating"], "userProfile": {"alias": s["entrant"]},
            "submissionNumber": len(own) or None,
            "submittedAt": iso(own[-1]["submitted_at"]) if own else None,
            "stats": {"mu": s["mu"], "sigma": s["sigma"], "heats": s["heats"], "wins": s["wins"],
                      "avgPosition": s["avg_position"], "bestLapTime": s["tt_best_lap"],
                      "bestLapTimeByTrack": s["tt_by_track"], "avgLapTime": s["tt_avg_lap"],
                      "completionRate": s["tt_completion"], "collisionsCausedPerLap": s["collisions_caused_per_lap"],
                      "forfeits": s["forfeits"], "forfeitReasons": s["forfeit_reasons"]},
        })
    return {"leaderboard": {"name": table["league"], "raceTypes": ["TIME_TRIAL", "HEAD_TO_HEAD"],
                            "tracks": table["tracks_tt"], "scheduled": table["scheduled"],
                            "recorded": table["recorded"], "pending": table["pending"],
                            "failed": len(table["failed"]), "signature": table["signature"]},
            "rankings": rankings}
