"""The `multirace` command line."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table

from .rules import FORMATS
from .tracks import TrackError, list_tracks


def _format_time(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def print_result(result: dict, console: Console) -> None:
    """The race result as a table."""
    direction = " (reverse)" if result["reverse"] else ""
    table = Table(title=f"{result['format']} on {result['track']}{direction}, {result['laps']} laps, "
                        f"seed {result['seed']}")
    for column in ("pos", "agent", "laps", "best lap", "total time", "resets", "penalties", "collisions",
                   "status"):
        table.add_column(column)
    for car in result["cars"]:
        status = car["status"] + (f" ({car['reason']})" if car["reason"] else "")
        table.add_row(str(car["position"]), car["name"], str(car["laps"]), _format_time(car["best_lap"]),
                      _format_time(car["total_time"]), str(car["resets"]), str(car["penalties"]),
                      str(car["collisions"]), status)
    console.print(table)


def cmd_race(args) -> int:
    from .race import RaceConfig, make_controller, run_race

    controllers = [make_controller(spec) for spec in args.entrants]
    config = RaceConfig(track=args.track, reverse=args.reverse, race=args.format, laps=args.laps,
                        seed=args.seed, obstacles=args.obstacles, max_steps=args.max_steps)
    result = run_race(controllers, config)
    print_result(result, Console(width=120))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="multirace", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    race = sub.add_parser("race", help="race agent files and bots against each other",
                          description="Race agent files (.pt) and scripted bots (bot:follow@1.5, "
                                      "bot:lanes@1.0) and print the result.")
    race.add_argument("entrants", nargs="+", help="agent files or bot:KIND@SPEED (KIND: follow, lanes)")
    race.add_argument("--track", default="reinvent_base",
                      help=f"bundled track name or .npy path (bundled: {', '.join(list_tracks())})")
    race.add_argument("--reverse", action="store_true", help="race the track in the other direction")
    race.add_argument("--format", default=None, choices=FORMATS,
                      help="race format (default: time_trial for one car, head_to_head for more)")
    race.add_argument("--laps", type=int, default=3, help="laps to race (default 3)")
    race.add_argument("--obstacles", type=int, default=None, help="boxes on track (0-6; format default)")
    race.add_argument("--seed", type=int, default=0, help="seed for grid, obstacles and noise")
    race.add_argument("--max-steps", type=int, default=None, help="stop the race after this many 15 Hz steps")
    race.add_argument("--json", metavar="FILE", help="write the result record as JSON")
    race.set_defaults(func=cmd_race)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "format", "x") is None:
        args.format = "time_trial" if len(args.entrants) == 1 else "head_to_head"
    try:
        return args.func(args)
    except (TrackError, ValueError, FileNotFoundError) as exc:
        print(f"multirace {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
