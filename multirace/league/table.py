"""League tables: OpenSkill ratings, time-trial standings, clean driving; Markdown, CSV, JSON, HTML, PNG.

Each league stage (`config.STAGES`) feeds its tables: a solo stage's time
trials the time-trial standings, a heat stage's heats the ratings.

Ratings: OpenSkill's Plackett-Luce model, one update per head-to-head heat
with the heat's finishing order, heats taken in schedule order (so the
ratings are deterministic); the rating shown is the ordinal, mu - 3 sigma.
Time-trial standings (reset rule): best lap, completion rate (the share of
trials that completed every lap), average lap. Clean driving: collisions the
entrant was at fault for (the README's "Race rules": once per incident) per
lap driven, and the penalties it collected, over all its races.
"""
from __future__ import annotations

import base64
import csv
import html
import io
import json
import math
import os
from pathlib import Path

from ..atomic import write_bytes, write_text
from ..text import TEXT_LENGTH, display_name
from .config import STAGES, load_config
from .schedule import current_schedule, entrants
from .store import connect

COLUMNS = ["rank", "entrant", "rating", "mu", "sigma", "heats", "wins", "avg_position", "tt_best_lap",
           "tt_completion", "tt_avg_lap", "collisions_caused_per_lap", "penalties", "forfeits"]
# what people read (text, Markdown, HTML); CSV and JSON keep the identifiers above
HEADERS = {"rank": "#", "entrant": "entrant", "rating": "rating", "mu": "mu", "sigma": "sigma", "heats": "heats",
           "wins": "wins", "avg_position": "avg place", "tt_best_lap": "TT best lap (s)",
           "tt_completion": "TT finish rate", "tt_avg_lap": "TT avg lap (s)",
           "collisions_caused_per_lap": "at-fault collisions / lap", "penalties": "penalties", "forfeits": "forfeits"}
TEXT_COLUMNS = {"entrant"}  # left-aligned; numbers right-aligned


def _mean(values):
    return sum(values) / len(values) if values else None


def compute_table(folder) -> dict:
    """Everything a league table shows, from the SQLite store (deterministic for the same results). It only
    reads the store (a read-only league folder works): matches not yet in the store's schedule count as
    pending."""
    from openskill.models import PlackettLuce

    folder = Path(folder)
    config = load_config(folder)
    conn = connect(folder, readonly=True)
    try:
        league_entrants = entrants(folder, config, conn)
        current = {row["match_id"] for row in current_schedule(config, league_entrants, conn)}
        rows = conn.execute(
            "SELECT s.match_id, s.seq, s.kind, s.round, s.spec, r.status, r.result, r.reason, r.replay "
            "FROM schedule s LEFT JOIN results r USING (match_id) ORDER BY s.seq").fetchall()
        names = [e["name"] for e in league_entrants]
    finally:
        conn.close()
    rows = [r for r in rows if r[0] in current]
    unscheduled = len(current) - len(rows)  # new entrants' matches, scheduled by the next `league run`
    model = PlackettLuce()
    ratings = {name: model.rating(name=name) for name in names}
    stats = {name: {"heats": 0, "wins": 0, "positions": [], "tt_trials": 0, "tt_finished": 0, "tt_best": [],
                    "tt_laps": [], "laps": 0, "caused": 0, "penalties": 0, "forfeits": 0, "forfeit_reasons": []} for name in names}
    history = []  # (round, {name: ordinal}) after each head-to-head round
    matches, failed = [], []
    current_round = None
    pending = 0

    def snapshot(round_no):
        history.append({"round": round_no, "ordinal": {n: round(ratings[n].ordinal(), 4) for n in names}})

    for match_id, seq, kind, round_no, spec, status, result, reason, replay in rows:
        spec = json.loads(spec)
        if status is None:
            pending += 1
            continue
        entry = {"match_id": match_id, "seq": seq, "kind": kind, "round": round_no, "track": spec["track"],
                 "reverse": spec["reverse"], "seed": spec["seed"], "status": status,
                 "entrants": [e["name"] for e in spec["entrants"]], "replay": replay}
        if status == "failed":
            entry["reason"] = reason
            failed.append({"match_id": match_id, "kind": kind, "entrants": entry["entrants"], "reason": reason})
            matches.append(entry)
            continue
        result = json.loads(result)
        cars = [c for c in result["cars"] if c["name"] in stats]
        entry["order"] = [c["name"] for c in sorted(cars, key=lambda c: c["position"])]
        entry["cars"] = [{k: c[k] for k in ("name", "position", "laps", "best_lap", "total_time", "status", "reason")}
                         for c in cars]
        matches.append(entry)
        _add_car_totals(stats, cars)
        stage = STAGES.get(kind)
        if stage is not None and stage.solo:  # a time trial: the time-trial table
            _add_time_trial(stats, cars)
        elif stage is not None and len(cars) >= 2:  # a heat: the ratings
            if current_round is not None and round_no != current_round:
                snapshot(current_round)
            current_round = round_no
            _rate_heat(model, ratings, stats, cars)
    if current_round is not None:
        snapshot(current_round)
    standings = [_standing(name, stats[name], ratings[name]) for name in names]
    has_h2h = any(s["heats"] for s in standings)
    standings.sort(key=lambda s: ((-s["rating"]) if has_h2h else 0,
                                  s["tt_best_lap"] if s["tt_best_lap"] is not None else math.inf,
                                  s["entrant"]))
    for i, s in enumerate(standings, 1):
        s["rank"] = i
    time_trials = sorted((s for s in standings if s["tt_completion"] is not None),
                         key=lambda s: (s["tt_best_lap"] if s["tt_best_lap"] is not None else math.inf,
                                        -s["tt_completion"], s["entrant"]))
    pending += unscheduled
    return {"league": config.name, "scheduled": len(current), "recorded": len(current) - pending, "pending": pending,
            "failed": failed, "standings": standings,
            "time_trials": [{"rank": i, **{k: s[k] for k in ("entrant", "tt_best_lap", "tt_completion", "tt_avg_lap")}}
                            for i, s in enumerate(time_trials, 1)],
            "rating_history": history, "matches": matches,
            "tracks": [{"name": t.name, "directions": list(t.directions)} for t in config.tracks]}


def _add_car_totals(stats: dict, cars: list) -> None:
    """Laps, at-fault collisions, penalties and forfeits of every car of a recorded match."""
    for car in cars:
        s = stats[car["name"]]
        s["laps"] += car["laps"]
        s["caused"] += car.get("collisions_caused", 0) or 0
        s["penalties"] += car.get("penalties", 0) or 0
        if car["status"] == "forfeit":
            s["forfeits"] += 1
            if car["reason"] and car["reason"] not in s["forfeit_reasons"]:
                s["forfeit_reasons"].append(car["reason"])


def _rate_heat(model, ratings: dict, stats: dict, cars: list) -> None:
    """A head-to-head heat: every car's rating updated from the finishing order, its heats, places and wins."""
    ordered = sorted(cars, key=lambda c: c["position"])
    teams = [[ratings[c["name"]]] for c in ordered]
    new = model.rate(teams, ranks=[c["position"] for c in ordered])
    for c, team in zip(ordered, new):
        ratings[c["name"]] = team[0]
        s = stats[c["name"]]
        s["heats"] += 1
        s["positions"].append(c["position"])
        s["wins"] += c["position"] == 1


def _add_time_trial(stats: dict, cars: list) -> None:
    """A time trial's finishes, best lap and lap times."""
    for car in cars:
        s = stats[car["name"]]
        s["tt_trials"] += 1
        s["tt_finished"] += car["status"] == "finished"
        if car["best_lap"] is not None:
            s["tt_best"].append(car["best_lap"])
        s["tt_laps"].extend(car["lap_times"] if "lap_times" in car else [])


def _standing(name: str, s: dict, r) -> dict:
    """One entrant's row of the standings from its totals `s` and its OpenSkill rating `r`."""
    return {
        "entrant": name,
        "rating": round(r.ordinal(), 3), "mu": round(r.mu, 3), "sigma": round(r.sigma, 3),
        "heats": s["heats"], "wins": s["wins"],
        "avg_position": round(_mean(s["positions"]), 3) if s["positions"] else None,
        "tt_best_lap": round(min(s["tt_best"]), 4) if s["tt_best"] else None,
        "tt_completion": round(s["tt_finished"] / s["tt_trials"], 4) if s["tt_trials"] else None,
        "tt_avg_lap": round(_mean(s["tt_laps"]), 4) if s["tt_laps"] else None,
        "collisions_caused_per_lap": round(s["caused"] / s["laps"], 4) if s["laps"] else None,
        "penalties": s["penalties"],
        "forfeits": s["forfeits"],
        "forfeit_reasons": s["forfeit_reasons"],
    }


# ------------------------------------------------------------------ text formats


def _text(value) -> str:
    """A table value as plain text."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3f}"
    return display_name(value, TEXT_LENGTH) if isinstance(value, str) else str(value)


def _cell(value) -> str:
    """A table value for a Markdown cell."""
    return _md(value) if isinstance(value, str) else _text(value)


def _md(text) -> str:
    """Text for a Markdown table cell or line: one line, no cell breaks, no inline HTML."""
    return (display_name(text, TEXT_LENGTH).replace("\\", "\\\\").replace("|", "\\|").replace("<", "&lt;")
            .replace(">", "&gt;"))


def _csv(value):
    """A CSV cell that no spreadsheet reads as a formula."""
    if isinstance(value, str):
        value = display_name(value)
        if value[:1] in ("=", "+", "-", "@", "\t", "\r"):
            return "'" + value
    return value


def _plain(text) -> str:
    """Text for a matplotlib label: shown as written (a `$` would start mathtext)."""
    return display_name(text).replace("$", r"\$")


def to_markdown(table: dict) -> str:
    lines = [f"# {_md(table['league'])}", "",
             f"{table['recorded']} of {table['scheduled']} matches recorded"
             + (f", {len(table['failed'])} failed" if table["failed"] else "")
             + (f", {table['pending']} pending" if table["pending"] else ""), "",
             "| " + " | ".join(HEADERS[c] for c in COLUMNS) + " |",
             "|" + "".join("---|" if c in TEXT_COLUMNS else "---:|" for c in COLUMNS)]
    for s in table["standings"]:
        lines.append("| " + " | ".join(_cell(s[c]) for c in COLUMNS) + " |")
    if table["time_trials"]:
        lines += ["", "## Time trials (reset rule)", "", "| # | entrant | best lap (s) | finish rate | avg lap (s) |",
                  "|---:|---|---:|---:|---:|"]
        for s in table["time_trials"]:
            lines.append(f"| {s['rank']} | {_md(s['entrant'])} | {_cell(s['tt_best_lap'])} | "
                         f"{_cell(s['tt_completion'])} | {_cell(s['tt_avg_lap'])} |")
    reasons = [(s["entrant"], r) for s in table["standings"] for r in s["forfeit_reasons"]]
    if reasons:
        lines += ["", "## Forfeits", ""] + [f"- {_md(name)}: {_md(reason)}" for name, reason in reasons]
    if table["failed"]:
        lines += ["", "## Failed matches", ""] + [
            f"- {f['match_id']} ({f['kind']}, {', '.join(_md(e) for e in f['entrants'])}): {_md(f['reason'])}"
            for f in table["failed"]]
    return "\n".join(lines) + "\n"


def to_csv(table: dict) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for s in table["standings"]:
        writer.writerow(["" if s[c] is None else _csv(s[c]) for c in COLUMNS])
    return out.getvalue()


def to_json(table: dict) -> str:
    return json.dumps(table, indent=2, sort_keys=True) + "\n"


def to_text(table: dict, width: int | None = None) -> str:
    """The standings and time trials as terminal tables (what `multirace league table` prints by default)."""
    from rich.console import Console
    from rich.table import Table

    console = Console(width=width or 250, record=True, file=io.StringIO(), color_system=None)  # natural widths
    summary = (f"{table['recorded']} of {table['scheduled']} matches recorded"
               + (f", {len(table['failed'])} failed" if table["failed"] else "")
               + (f", {table['pending']} pending" if table["pending"] else ""))
    standings = Table(title=f"{display_name(table['league'])}: {summary}", title_justify="left")
    for column in COLUMNS:  # long headers on two lines; values never wrapped
        header = HEADERS[column] if len(HEADERS[column]) <= 9 else HEADERS[column].replace(" ", "\n", 1)
        standings.add_column(header, justify="left" if column in TEXT_COLUMNS else "right", no_wrap=True)
    for row in table["standings"]:
        standings.add_row(*(_text(row[c]) for c in COLUMNS))
    console.print(standings)
    if table["time_trials"]:
        trials = Table(title="time trials (reset rule)", title_justify="left")
        for header in ("#", "entrant", "best lap (s)", "finish rate", "avg lap (s)"):
            trials.add_column(header, justify="left" if header == "entrant" else "right")
        for row in table["time_trials"]:
            trials.add_row(str(row["rank"]), _text(row["entrant"]), _text(row["tt_best_lap"]),
                           _text(row["tt_completion"]), _text(row["tt_avg_lap"]))
        console.print(trials)
    notes = [f"forfeit: {display_name(s['entrant'])}: {display_name(r, TEXT_LENGTH)}"
             for s in table["standings"] for r in s["forfeit_reasons"]]
    notes += [f"failed match {f['match_id']} ({f['kind']}): {display_name(f['reason'], TEXT_LENGTH)}"
              for f in table["failed"]]
    for note in notes:
        console.print(note, markup=False, highlight=False)
    return "\n".join(line.rstrip() for line in console.export_text().splitlines()) + "\n"


# ------------------------------------------------------------------ plots and HTML
def _png_bytes(fig) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    return buffer.getvalue()


def rating_plot_png(table: dict) -> bytes:
    """PNG of every entrant's rating (ordinal) after each head-to-head round."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    history = table["rating_history"]
    rounds = [0] + [h["round"] + 1 for h in history]
    for s in table["standings"]:
        values = [0.0] + [h["ordinal"][s["entrant"]] for h in history]  # ordinal of a new rating is 0
        ax.plot(rounds, values, marker="o", markersize=3, label=_plain(s["entrant"]))
    ax.set_xlabel("head-to-head round")
    ax.set_ylabel("rating (mu - 3 sigma)")
    ax.set_title(f"{_plain(table['league'])}: ratings over rounds")
    ax.grid(alpha=0.3)
    if table["standings"]:
        ax.legend(fontsize=8, loc="best")
    data = _png_bytes(fig)
    plt.close(fig)
    return data


def track_map_png(name: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..sim.tracks import load_track

    track = load_track(name)
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.fill(track.outer[:, 0], track.outer[:, 1], color="#555555")
    ax.fill(track.inner[:, 0], track.inner[:, 1], color="white")
    for line in (track.inner, track.outer):
        ax.plot(line[:, 0], line[:, 1], color="black", linewidth=1)
    ax.plot(track.center[:, 0], track.center[:, 1], "--", color="yellow", linewidth=0.8)
    ax.plot(track.center[0, 0], track.center[0, 1], "o", color="red")
    ax.set_aspect("equal")
    ax.set_title(f"{name} ({track.length:.1f} m)")
    ax.axis("off")
    data = _png_bytes(fig)
    plt.close(fig)
    return data


def _img(data: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def to_html(table: dict, replay_base: str = "") -> str:
    """A self-contained leaderboard page: standings, rating plot, track maps, matches with replay links.

    Replay links are `replay_base` + the path relative to the league folder."""
    def e(value) -> str:
        return html.escape(_text(value))

    def num(value) -> str:
        return f'<td class="num">{e(value)}</td>'

    head = "".join(f'<th{"" if c in TEXT_COLUMNS else " class=num"} title="{c}">{e(HEADERS[c])}</th>'
                   for c in COLUMNS)
    body = "".join("<tr>" + "".join(f"<td>{e(s[c])}</td>" if c in TEXT_COLUMNS else num(s[c]) for c in COLUMNS)
                   + "</tr>" for s in table["standings"])
    tt = "".join(f"<tr>{num(s['rank'])}<td>{e(s['entrant'])}</td>{num(s['tt_best_lap'])}"
                 f"{num(s['tt_completion'])}{num(s['tt_avg_lap'])}</tr>"
                 for s in table["time_trials"])
    maps = "".join(f"<figure>{_img(track_map_png(t['name']), t['name'])}<figcaption>{e(t['name'])} "
                   f"({e(', '.join(t['directions']))})</figcaption></figure>" for t in table["tracks"])
    match_rows = []
    for m in table["matches"]:
        replay = f'<a href="{html.escape(replay_base + m["replay"])}">replay</a>' if m.get("replay") else "-"
        outcome = " &gt; ".join(e(name) for name in m["order"]) if "order" in m else e(f"failed: {m.get('reason', '')}")
        direction = "reverse" if m["reverse"] else "forward"
        match_rows.append(f"<tr>{num(m['seq'])}<td>{e(m['kind'].replace('_', ' '))}</td>"
                          f"<td>{e(m['track'])} {direction}</td>{num(m['seed'])}<td>{outcome}</td><td>{replay}</td></tr>")
    forfeits = "".join(f"<li>{e(s['entrant'])}: {e(r)}</li>" for s in table["standings"]
                       for r in s["forfeit_reasons"])
    summary = (f"{table['recorded']} of {table['scheduled']} matches recorded, {len(table['failed'])} failed, "
               f"{table['pending']} pending")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{e(table['league'])}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
th, td {{ border: 1px solid #ccc; padding: 4px 7px; text-align: left; max-width: 18em; overflow-wrap: anywhere; }}
th {{ background: #eee; vertical-align: bottom; max-width: 7em; overflow-wrap: normal; }}
.num {{ text-align: right; }}
figure {{ display: inline-block; margin: 0 1em 1em 0; }}
</style></head><body>
<h1>{e(table['league'])}</h1>
<p>{e(summary)}. Rating: OpenSkill Plackett-Luce ordinal (mu - 3 sigma) from head-to-head finishing orders;
TT: time trials under the reset rule (finish rate: the share of trials that completed every lap); at-fault
collisions (once per incident) per lap driven; penalties collected in all races.</p>
<h2>Standings</h2>
<table><tr>{head}</tr>{body}</table>
<h2>Ratings over rounds</h2>
{_img(rating_plot_png(table), 'ratings over rounds')}
<h2>Time trials (reset rule)</h2>
<table><tr><th class=num>#</th><th>entrant</th><th class=num>best lap (s)</th><th class=num>finish rate</th>
<th class=num>avg lap (s)</th></tr>{tt}</table>
<h2>Tracks</h2>
{maps}
{'<h2>Forfeits</h2><ul>' + forfeits + '</ul>' if forfeits else ''}
<h2>Matches</h2>
<p>Replays open with <code>rerun FILE.rrd</code> or <code>multirace replay FILE.rrd</code>.</p>
<table><tr><th class=num>#</th><th>format</th><th>track</th><th class=num>seed</th><th>finishing order</th>
<th>replay</th></tr>
{''.join(match_rows)}</table>
</body></html>
"""


FORMATS = ("text", "md", "csv", "json", "html")


def write_table(folder, fmt: str = "text", out=None, plot=None) -> str:
    """Render the league table in `fmt` (one of FORMATS; text: terminal tables); writes it to `out` if given
    and the rating plot (PNG) to `plot` if given, each atomically, and nothing else (the league folder is
    only read). Returns the text."""
    folder = Path(folder)
    table = compute_table(folder)
    renderers = {"text": to_text, "md": to_markdown, "csv": to_csv, "json": to_json, "html": to_html}
    if fmt not in renderers:
        raise ValueError(f"--format: unknown table format {fmt!r}; choose one of {', '.join(renderers)}")
    if fmt == "html":
        base = os.path.relpath(folder.resolve(), Path(out).resolve().parent) if out else "."
        text = to_html(table, "" if base == "." else base.replace(os.sep, "/") + "/")
    else:
        text = renderers[fmt](table)
    if plot:
        write_bytes(plot, rating_plot_png(table))
    if out:
        write_text(out, text)
    return text


