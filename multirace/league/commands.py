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
                                            "worker processes; safe to kill and run again.")
    run.add_argument("dir", help="the league folder")
    run.add_argument("--workers", type=POSITIVE_INT, default=None, help="worker processes (default: one per core)")
    run.add_argument("--ray", metavar="ADDRESS", default=None,
                     help="run matches as Ray tasks on this cluster (e.g. auto or ray://host:10001)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=_cmd_run)
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
