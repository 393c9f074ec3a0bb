"""`multirace league init|submit|run|table`: the command-line glue."""
from __future__ import annotations

import functools
import sqlite3
import sys
from pathlib import Path

from ..options import POSITIVE_INT, output_file
from ..resources import agent_argument
from .config import DB, TOML, LeagueError
from .runner import run_league
from .submissions import init_league, submit
from .table import FORMATS as TABLE_FORMATS


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
    sub_.add_argument("file", type=agent_argument, help="agent file (.pt) or a shipped agent's name")
    sub_.add_argument("--name", required=True, help="the entrant's name in the league")
    sub_.set_defaults(func=_cmd_submit)
    run = league_sub.add_parser("run", help="run every pending match (resumable)",
                                description="Builds the schedule and runs the matches without a result, in "
                                            "worker processes (with schedule = \"uncertainty\", batch after "
                                            "batch until its budget); safe to kill and run again.")
    run.add_argument("dir", help="the league folder")
    run.add_argument("--workers", type=POSITIVE_INT, default=None, help="worker processes (default: one per core)")
    run.add_argument("--ray", metavar="ADDRESS", default=None,
                     help="run matches as Ray tasks on this cluster (e.g. auto or ray://host:10001)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--watch", action="store_true",
                     help="keep running: play the matches each newly uploaded version needs (Ctrl-C to stop)")
    run.add_argument("--poll", type=float, default=2.0, help="with --watch: seconds between looks (default 2)")
    run.set_defaults(func=_cmd_run)
    _add_web_commands(league_sub)
    table = league_sub.add_parser("table", help="print or export the league table",
                                  description="Ratings (OpenSkill Plackett-Luce ordinal), time-trial standings "
                                              "and clean driving. Only reads the league folder (a read-only "
                                              "one works); writes only the files asked for.")
    table.add_argument("dir", help="the league folder")
    table.add_argument("--format", dest="table_format", default="text", choices=TABLE_FORMATS,
                       help="text (terminal tables, the default), md, csv, json or html (a self-contained page)")
    table.add_argument("--out", metavar="FILE", type=output_file, help="write the table to FILE instead of printing it")
    table.add_argument("--plot", metavar="FILE.png", type=output_file,
                       help="also write the ratings-over-rounds plot as a PNG")
    table.set_defaults(func=_cmd_table)


def _store_errors(command):
    """A league command whose SQLite store fails mid-way (disk full, damaged meanwhile) ends in a LeagueError
    naming the store, not a traceback; what was committed before stays committed."""
    @functools.wraps(command)
    def run(args) -> int:
        try:
            return command(args)
        except sqlite3.Error as exc:
            raise LeagueError(f"{Path(args.dir) / DB}: {type(exc).__name__}: {exc} (results written before this "
                              "were committed; fix the cause and run the command again)") from None
    return run


@_store_errors
def _cmd_init(args) -> int:
    folder = init_league(args.dir, args.template)
    print(f"created league {folder} (edit {folder / TOML}, then 'multirace league submit {folder} FILE.pt "
          f"--name NAME')")
    return 0


@_store_errors
def _cmd_submit(args) -> int:
    try:
        row = submit(args.dir, args.file, args.name)
    except LeagueError as exc:
        print(f"multirace league submit: {exc}", file=sys.stderr)
        return 1
    print(f"submitted {row['name']} ({row['sha256'][:12]}) as {row['file']}")
    return 0


@_store_errors
def _cmd_run(args) -> int:
    if args.watch:
        from .watch import watch_league

        print(f"watching {args.dir} for new versions (Ctrl-C to stop)", flush=True)
        ran = watch_league(args.dir, workers=args.workers, ray_address=args.ray, poll=max(args.poll, 0.1),
                           say=lambda line: print(line, flush=True))
        print(f"league run --watch: stopped after {ran} matches")
        return 0
    stats = run_league(args.dir, workers=args.workers, ray_address=args.ray, progress=not args.quiet)
    print(f"league run: {stats['ran']} matches run, {stats['failed']} failed, {stats['scheduled']} scheduled, "
          f"{stats['wall_seconds']:.1f} s")
    return 0


@_store_errors
def _cmd_table(args) -> int:
    from .table import write_table

    text = write_table(args.dir, args.table_format, args.out, args.plot)
    for written in (args.out, args.plot):
        if written:
            print(f"wrote {written}")
    else:
        sys.stdout.write(text)
    return 0


def _add_web_commands(league_sub) -> None:
    """`league serve DIR` and `league entrant add DIR NAME`."""
    serve = league_sub.add_parser("serve", help="serve the league as a web app (leaderboard, uploads, replays)",
                                  description="Leaderboard, entrant and match pages with race videos and "
                                              "rerun's web viewer, uploads with entrant tokens, a JSON API. "
                                              "Run `league run DIR --watch` beside it to play new entries.")
    serve.add_argument("dir", help="the league folder")
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    serve.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    serve.add_argument("--max-upload-mb", type=float, default=None, help="largest agent file accepted (default 256)")
    serve.add_argument("--uploads-per-hour", type=int, default=20, help="uploads per entrant per hour (default 20)")
    serve.set_defaults(func=_cmd_serve)
    entrant = league_sub.add_parser("entrant", help="entrants who upload from the web")
    entrant_sub = entrant.add_subparsers(dest="entrant_command", required=True)
    add = entrant_sub.add_parser("add", help="create an entrant and print its upload token (shown once)")
    add.add_argument("dir", help="the league folder")
    add.add_argument("name", help="the entrant's name in the league")
    add.set_defaults(func=_cmd_entrant_add)


@_store_errors
def _cmd_serve(args) -> int:
    from .web.server import serve

    if not 0 < args.port < 65536:
        raise LeagueError("--port: must be 1 to 65535")
    if args.max_upload_mb is not None and not 0 < args.max_upload_mb <= 256:
        raise LeagueError("--max-upload-mb: must be above 0 and at most 256")
    if args.uploads_per_hour < 1:
        raise LeagueError("--uploads-per-hour: must be at least 1")
    limit = int(args.max_upload_mb * 2**20) if args.max_upload_mb else None
    serve(args.dir, args.host, args.port, upload_limit=limit, uploads_per_hour=args.uploads_per_hour)
    return 0


@_store_errors
def _cmd_entrant_add(args) -> int:
    from .entrants import add_entrant

    token = add_entrant(args.dir, args.name)
    print(f"entrant {args.name!r} created. Their upload token (shown only now; the league keeps only its hash):")
    print(token)
    return 0
