"""The `multirace` command line."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from .atomic import OutputError, write_text
from .environment.formats import FORMATS
from .options import (COUNT, NON_NEGATIVE, POSITIVE, POSITIVE_INT, SEED, SHARE, HelpLater, Parser, input_file,
                      number, output_file)
from .text import display_name, laps_text
from .resources import agent_argument, list_agents, list_tracks


def _format_time(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def print_result(result: dict, console: Console) -> None:
    """The race result as a table."""
    direction = " (reverse)" if result["reverse"] else ""
    table = Table(title=f"{result['format']} on {result['track']}{direction}, {laps_text(result['laps'])}, "
                        f"seed {result['seed']}")
    for column in ("pos", "agent", "laps", "best lap", "total time", "resets", "penalties", "collisions",
                   "status"):
        table.add_column(column)
    for car in result["cars"]:  # names and reasons are data (agent files are anyone's): never markup
        status = escape(car["status"] + (f" ({display_name(car['reason'])})" if car["reason"] else ""))
        table.add_row(str(car["position"]), escape(display_name(car["name"])), str(car["laps"]),
                      _format_time(car["best_lap"]),
                      _format_time(car["total_time"]), str(car["resets"]), str(car["penalties"]),
                      str(car["collisions"]), status)
    console.print(table)


def cmd_race(args) -> int:
    from .racing.runner import RaceConfig, make_controller, run_race

    controllers = [make_controller(spec) for spec in args.entrants]
    race_format = args.format or ("time_trial" if len(controllers) == 1 else "head_to_head")
    config = RaceConfig(track=args.track, reverse=args.reverse, race=race_format, laps=args.laps,
                        seed=args.seed, obstacles=args.obstacles, max_steps=args.max_steps)
    recorders = []
    if getattr(args, "replay", None):
        from .recording.replay import ReplayRecorder

        recorders.append(ReplayRecorder(args.replay))
    if getattr(args, "simtrace", None):
        from .recording.simtrace import SimTraceRecorder

        recorders.append(SimTraceRecorder(args.simtrace, controllers))  # notes the commands given
    if getattr(args, "eval_metrics", None):
        from .deepracer.logs import EvaluationMetricsRecorder

        recorders.append(EvaluationMetricsRecorder(args.eval_metrics))
    if getattr(args, "video", None):
        from .recording.video import VideoRecorder

        recorders.append(VideoRecorder(args.video))
    result = run_race(controllers, config, recorders=recorders)
    print_result(result, Console(width=120))
    if args.json:
        write_text(args.json, json.dumps(result, indent=2))
    for option, what in (("json", "the result record"), ("replay", "the replay (`multirace replay FILE`)"),
                         ("simtrace", "the DeepRacer sim-trace"), ("eval_metrics", "DeepRacer's evaluation metrics"),
                         ("video", "the top-down race video")):
        if getattr(args, option, None):
            print(f"wrote {getattr(args, option)}: {what.replace('FILE', getattr(args, option))}")
    return 0


def cmd_replay(args) -> int:
    from .recording.replay_reader import format_summary, open_viewer, replay_summary

    if getattr(args, "video", None):
        from .recording.replay_video import replay_video

        made = replay_video(args.file, args.video)
        print(f"wrote {made['file']}: {made['frames']} frames ({made['steps']} steps at {made['fps']:g} fps)")
        if not args.summary:
            return 0
    if not args.summary:
        return open_viewer(args.file)
    summary = replay_summary(args.file, poses=False)
    print(format_summary(summary))
    if args.json:
        write_text(args.json, json.dumps(summary, indent=2))
    return 0


def cmd_explain(args) -> int:
    from .tools.explain import explain

    out = args.out if args.out is not None else f"{Path(args.agent).stem}_gradcam.mp4"
    result = explain(args.agent, track=args.track, steps=args.steps, out=out, replay=args.replay,
                     reverse=args.reverse, seed=args.seed, target=args.target, scale=args.scale)
    print(f"wrote {result['out']}: Grad-CAM of {result['agent']} over {result['frames']} frames on "
          f"{result['track']}" + (f", replay {result['replay']}" if result["replay"] else ""))
    if result["status"] != "not_finished" and result["frames"] < args.steps:
        print(f"the run ended ({result['status']}) after {result['frames']} of --steps {args.steps}: explain drives "
              "one lap at most (a 1-lap time trial)")
    print(f"heat on the track (road + borders + centre line): {100 * result['heat_on_track']:.1f}% of the mass, "
          f"on {100 * result['track_fraction']:.1f}% of the image; on the lines {result['lines_lift']:.2f}x "
          "their area share")
    if args.json:
        write_text(args.json, json.dumps(result, indent=2))
    return 0


def cmd_plot(args) -> int:
    from .recording.plot import plot_simtrace

    out = plot_simtrace(args.trace, args.out, track=args.track)
    print(f"wrote {out}")
    return 0


INSPECT_PRINT_LIMIT = 20_000  # characters of an agent's metadata `agent inspect` prints (--json: all)


def cmd_agent_inspect(args) -> int:
    from .racing.agentfile import inspect_agent_isolated

    info = inspect_agent_isolated(args.file)  # under memory and time limits: the file may be anyone's
    if args.json:
        print(json.dumps(info, indent=2))
        return 0 if info["valid"] else 1
    console = Console(width=120)
    console.print(f"[bold]{escape(display_name(info['file'], 1000))}[/bold]  ({info['size_bytes']} bytes)")
    console.print(f"sha256      {info['sha256']}")
    if info["valid"]:
        console.print(f"name        {escape(display_name(info['name']))}")
        console.print(f"network     {info['network']}  ({info['parameters']:,} parameters, "
                      f"{info['outputs']} outputs{', value head' if info['value_head'] else ''})")
    else:
        console.print(f"[red]invalid[/red]     {escape(display_name(info['error'], 1000))}")
    if "metadata" in info:
        console.print("model_metadata:")
        text = json.dumps(info["metadata"], indent=2)
        if len(text) <= INSPECT_PRINT_LIMIT:
            console.print_json(text)
        else:  # a huge metadata: its start, plainly (rich's JSON rendering of megabytes takes minutes)
            console.print(f"{text[:INSPECT_PRINT_LIMIT]}\n... ({len(text) - INSPECT_PRINT_LIMIT:,} more characters "
                          "of metadata; --json prints them all)", markup=False, highlight=False)
    return 0 if info["valid"] else 1


def cmd_agent_list(args) -> int:
    from .racing.agentfile import agent_summary
    from .resources import agents_dir, shipped_figures

    figures = shipped_figures()
    rows = [{**agent_summary(agents_dir() / f"{name}.pt"), **figures.get(name, {"held_out": "-", "traffic": "-"})}
            for name in list_agents()]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    table = Table(title="shipped agents (race, evaluate, explain, inspect, export or submit them by name)")
    for column in ("name", "sensor", "actions", "made by", "held out (agents/README)", "traffic"):
        table.add_column(column)
    for row in rows:
        table.add_row(escape(row["name"]), " + ".join(row["sensor"]), row["actions"],
                      escape(f"{row['made_by']}; {row['network']}, {row['parameters']:,} parameters, "
                             f"{row['size_bytes'] / 1e6:.2f} MB"), escape(row["held_out"]), escape(row["traffic"]))
    console = Console(width=160)
    console.print(table)
    console.print(f"files in {agents_dir()}; how each was made and how it races: {agents_dir() / 'README.md'}",
                  soft_wrap=True)
    return 0


def cmd_agent_export(args) -> int:
    from .deepracer.export import export_agent

    print(f"wrote {export_agent(args.file, args.out)} (agent/model.pb + model_metadata.json for a DeepRacer car)")
    return 0


def cmd_agent_blend(args) -> int:
    from .racing.blend import blend_agents

    path = blend_agents(args.first, args.second, args.share, args.out, name=args.name)
    print(f"wrote {path}: {args.share:g} x {args.first} + {1 - args.share:g} x {args.second}")
    return 0


def cmd_agent_import(args) -> int:
    from .deepracer.importer import import_model

    print(f"wrote {import_model(args.path, args.out, name=args.name)}")
    return 0


def cmd_imitate(args) -> int:
    import shlex

    from .environment.bots import parse_bot
    from .racing.nets import NETWORKS
    from .sensors.suite import parse_sensors
    from .train.imitate import DEFAULT_TRACKS, ImitationConfig, run_dagger
    from .train.splits import expand_tracks

    if args.network not in NETWORKS:
        raise ValueError(f"--network: unknown network {args.network!r}; choose from {', '.join(NETWORKS)}")
    if args.expert:
        try:
            parse_bot(args.expert)
        except ValueError as exc:
            raise ValueError(f"--expert: {exc}") from None
    command = ["multirace", "imitate", "--out", args.out, "--tracks", *(args.tracks or DEFAULT_TRACKS),
               "--minutes", f"{args.minutes:g}", "--seed", str(args.seed), "--network", args.network, "--speed",
               f"{args.speed:g}"]
    args.tracks = expand_tracks(args.tracks or DEFAULT_TRACKS)
    for option, value in (("--expert", args.expert), ("--randomize", args.randomize)):
        if value:
            command += [option, value]
    if args.procedural_tracks:
        command += ["--procedural-tracks", str(args.procedural_tracks)]
    if args.init:
        command += ["--init", args.init]
    if args.max_samples != ImitationConfig.max_samples:
        command += ["--max-samples", str(args.max_samples)]
    if args.action_space:
        command += ["--action-space", args.action_space]
    if args.one_direction:
        command += ["--one-direction"]
    if args.name:
        command += ["--name", args.name]
    traffic = tuple(b.strip() for b in (args.traffic or "").split(",") if b.strip())
    for bot in traffic:
        try:
            parse_bot(bot)
        except ValueError as exc:
            raise ValueError(f"--traffic: {exc}") from None
    if traffic:
        command += ["--traffic", ",".join(traffic)]
    if args.traffic_share != 1.0:
        command += ["--traffic-share", f"{args.traffic_share:g}"]
    if args.sensor:
        parse_sensors(args.sensor, "--sensor")
        command += ["--sensor", *args.sensor]
    if args.lidar:
        command += ["--lidar"]
    config = ImitationConfig(out=args.out, tracks=tuple(args.tracks), both_directions=not args.one_direction,
                             minutes=args.minutes, seed=args.seed, network=args.network,
                             action_space=args.action_space, expert_speed=args.speed, traffic=traffic,
                             name=args.name, threads=args.threads, lidar=args.lidar, expert=args.expert,
                             sensor=tuple(args.sensor or ImitationConfig.sensor),
                             randomize=args.randomize, procedural_tracks=args.procedural_tracks,
                             max_samples=args.max_samples, init=args.init, traffic_share=args.traffic_share,
                             command=shlex.join(command))
    summary = run_dagger(config)
    print(f"wrote {summary['out']}: {summary['iterations']} DAgger iterations, {summary['samples']} samples, "
          f"final loss {summary['final_loss']}, {summary['wall_seconds']} s")
    return 0


def cmd_bench(args) -> int:
    from .tools.bench import format_table, run_bench, run_profile
    from .tools.profile import format_profile

    console = Console(width=120)
    progress = lambda line: console.print(f"[dim]{line}[/dim]")  # noqa: E731
    if args.profile:
        figures = run_profile(progress=progress, racing=args.racing)
        workload = "racing cars" if args.racing else "random drivers"
        rows, title = format_profile(figures), f"where a {figures['cars']}-car env step goes ({workload}, this machine)"
    else:
        figures = run_bench(seconds=args.seconds, replay_seconds=args.replay_seconds, progress=progress)
        rows, title = format_table(figures), "multirace bench (one run, this machine)"
    table = Table(title=title)
    table.add_column("figure")
    table.add_column("value", justify="right")
    for label, value in rows:
        table.add_row(label, value)
    console.print(table)
    if args.json:
        write_text(args.json, json.dumps(figures, indent=2))
    return 0


def _entrants_help() -> str:
    from .environment.bots import bot_kinds_help

    return (f"agent files, shipped agents by name ({', '.join(list_agents())}), bot:KIND@SPEED ({bot_kinds_help()}) "
            "or teacher:FILE.teacher.pt (an RL teacher of train --privileged)")


def _add_race_parser(sub) -> None:
    """The `race` subcommand."""
    race = sub.add_parser("race", help="race agent files and bots against each other",
                          description="Race agent files (.pt) and scripted bots (bot:follow@1.5, "
                                      "bot:lanes@1.0, bot:racingline) and print the result.")
    race.add_argument("entrants", nargs="+", help=HelpLater(_entrants_help))
    race.add_argument("--track", default="reinvent_base",
                      help=f"bundled track name or .npy path (bundled: {', '.join(list_tracks())})")
    race.add_argument("--reverse", action="store_true", help="race the track in the other direction")
    race.add_argument("--format", "--race", dest="format", default=None, choices=FORMATS,
                      help="race format (default: time_trial for one car, head_to_head for more)")
    race.add_argument("--laps", type=POSITIVE_INT, default=3, help="laps to race (default 3)")
    race.add_argument("--obstacles", type=number(int, minimum=0, maximum=6), default=None,
                      help="boxes on track (0-6; format default)")
    race.add_argument("--seed", type=SEED, default=0, help="seed for grid, obstacles and noise")
    race.add_argument("--max-steps", type=POSITIVE_INT, default=None, help="stop the race after this many 15 Hz steps")
    race.add_argument("--json", metavar="FILE", type=output_file, help="write the result record as JSON")
    race.add_argument("--replay", metavar="FILE.rrd", type=output_file, help="record the race to a rerun replay file")
    race.add_argument("--simtrace", metavar="FILE.csv", type=output_file,
                      help="write a DeepRacer sim-trace CSV (one row per car per step, episode = car slot)")
    race.add_argument("--eval-metrics", metavar="FILE.json", type=output_file,
                      help="write DeepRacer's evaluation metrics JSON of the first car (one trial per lap)")
    race.add_argument("--video", metavar="FILE.mp4", type=output_file,
                      help="write the top-down race view as an MP4 (15 fps)")
    race.set_defaults(func=cmd_race)


def _add_agent_parser(sub) -> None:
    """The `agent` subcommand."""
    agent = sub.add_parser("agent", help="list, inspect, blend, export and import agent files",
                           description="Tools for agent files (.pt: weights + model_metadata).")
    agent_sub = agent.add_subparsers(dest="agent_command", required=True)
    listing = agent_sub.add_parser("list", help="the agents shipped with multirace: figures and paths",
                                   description="List the shipped agents (network, sensors, action space, how "
                                               "each was made, size) and the folder that holds them.")
    listing.add_argument("--json", action="store_true", help="print the list as JSON (with each file's path)")
    listing.set_defaults(func=cmd_agent_list)
    inspect = agent_sub.add_parser("inspect", help="print an agent file's metadata, size and hash",
                                   description="Validate an agent file and print its model_metadata, "
                                               "parameter count and sha256 (exit 1 if invalid).")
    inspect.add_argument("file", type=agent_argument, help="agent file (.pt) or a shipped agent's name")
    inspect.add_argument("--json", action="store_true", help="print the information as JSON")
    inspect.set_defaults(func=cmd_agent_inspect)
    export = agent_sub.add_parser("export", help="write an agent as the .tar.gz a DeepRacer car loads",
                                  description="Write the car's archive: one frozen TensorFlow graph (agent/model.pb, "
                                              "the car's node names) and model_metadata.json.")
    export.add_argument("file", type=agent_argument, help="agent file (.pt) or a shipped agent's name")
    export.add_argument("--out", required=True, metavar="MODEL.tar.gz", type=output_file, help="archive to write")
    export.set_defaults(func=cmd_agent_export)
    blend = agent_sub.add_parser("blend", help="write a weight-space blend of two agent files (WiSE-FT)",
                                 description="Write SHARE x FIRST's weights + (1 - SHARE) x SECOND's as an agent "
                                             "file: two fine-tunes of one start (a fast time-trial agent and a "
                                             "cautious traffic student, say) blended to keep some of each. Both "
                                             "must be the same network on the same sensors and action space.")
    blend.add_argument("first", type=agent_argument, help="agent file (.pt) or a shipped agent's name")
    blend.add_argument("second", type=agent_argument, help="agent file (.pt) or a shipped agent's name")
    blend.add_argument("--share", required=True, type=SHARE, help="share of FIRST's weights (0-1)")
    blend.add_argument("--out", required=True, metavar="FILE.pt", type=output_file, help="agent file to write")
    blend.add_argument("--name", default=None, help="agent name in the metadata (default: file stem)")
    blend.set_defaults(func=cmd_agent_blend)
    imported = agent_sub.add_parser("import", help="turn a DeepRacer model into an agent file",
                                    description="Read a car archive (.tar.gz), a folder, a frozen .pb with its "
                                                "model_metadata.json, or a training checkpoint folder (model/ with "
                                                ".ckpt files), and write an equivalent agent file.")
    imported.add_argument("path", help="DeepRacer model: .tar.gz, folder, model.pb or checkpoint folder")
    imported.add_argument("--out", required=True, metavar="FILE.pt", type=output_file, help="agent file to write")
    imported.add_argument("--name", default=None, help="agent name in the metadata (default: file stem)")
    imported.set_defaults(func=cmd_agent_import)


def _add_imitate_parser(sub) -> None:
    """The `imitate` subcommand."""
    imitate = sub.add_parser("imitate", help="train a camera agent by DAgger imitation of the scripted driver",
                             description="Train a camera CNN by DAgger: the learner drives, the scripted "
                                         "pure-pursuit driver labels every image with the nearest action, "
                                         "the data is aggregated and the net retrained; writes an agent file.")
    imitate.add_argument("--out", required=True, metavar="FILE.pt", type=output_file, help="agent file to write")
    imitate.add_argument("--tracks", nargs="+", default=None, metavar="TRACK",
                         help="tracks to train on; the word train-split names every bundled track outside "
                              "the held-out split (default: reinvent_base reInvent2019_track Oval_track "
                              "Bowtie_track)")
    imitate.add_argument("--procedural-tracks", type=COUNT, default=0, metavar="N",
                         help="also drive N seeded generated tracks (default 0)")
    imitate.add_argument("--one-direction", action="store_true",
                         help="train on each track forwards only (default: both directions)")
    imitate.add_argument("--minutes", type=POSITIVE, default=4.0, help="wall-clock training budget (default 4)")
    imitate.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
    imitate.add_argument("--network", default="MULTIRACE_SMALL_CNN", metavar="NAME",
                         help="MULTIRACE_SMALL_CNN (default, under 1 MB) or DEEP_CONVOLUTIONAL_NETWORK_SHALLOW "
                              "(DeepRacer's shallow net, about 23 MB at 120x160)")
    imitate.add_argument("--action-space", default=None, metavar="JSON", type=input_file,
                         help="DeepRacer model_metadata.json with the action space (default: 10 actions, "
                              "steering -30..30 by 15 x speed 0.5, 1.0; with --init: the init file's, and a new "
                              "one must fit its net: any continuous range, or as many discrete actions)")
    imitate.add_argument("--speed", type=number(float, minimum=0.1, maximum=4.0), default=1.0,
                         help="the default pass expert's speed in m/s (default 1.0)")
    imitate.add_argument("--expert", default=None, metavar="BOT",
                         help="the expert as a bot spec, e.g. racingline@0.9 (default: pass@SPEED)")
    imitate.add_argument("--randomize", default=None, choices=("mild", "strong"),
                         help="domain randomisation of every episode (default: none)")
    imitate.add_argument("--traffic", default=None, metavar="BOTS",
                         help="bots in the envs (all, or --traffic-share of them), comma-separated (e.g. "
                              "follow@1.0,lanes@1.0), started ahead of the learner")
    imitate.add_argument("--init", default=None, metavar="AGENT.pt", type=agent_argument,
                         help="start from this agent file's net (its network, image size, action space)")
    imitate.add_argument("--max-samples", type=POSITIVE_INT, default=40000, metavar="N",
                         help="dataset cap; beyond it new samples replace random old ones (default 40000; "
                              "each 120x160 sample is 19 kB)")
    imitate.add_argument("--sensor", nargs="+", default=None, metavar="NAME",
                         help="the sensor list the agent reads: FRONT_FACING_CAMERA (default) or "
                              "STEREO_CAMERAS, and optionally LIDAR or SECTOR_LIDAR (DeepRacer's) and SPEED "
                              "(multirace's; not on DeepRacer's cars) (e.g. --sensor FRONT_FACING_CAMERA SECTOR_LIDAR)")
    imitate.add_argument("--traffic-share", type=SHARE, default=1.0, metavar="F",
                         help="share of the envs that hold the --traffic bots (default 1; the rest drive alone)")
    imitate.add_argument("--lidar", action="store_true",
                         help="the agent also reads DeepRacer's 64-beam LIDAR (shorthand for --sensor "
                              "FRONT_FACING_CAMERA LIDAR)")
    imitate.add_argument("--name", default=None, help="agent name in the metadata (default: file stem)")
    imitate.add_argument("--threads", type=POSITIVE_INT, default=None,
                         help="torch threads (default: all cores on an idle machine, 1 on a busy one)")
    imitate.set_defaults(func=cmd_imitate)


def _add_replay_parser(sub) -> None:
    """The `replay` subcommand."""
    replay = sub.add_parser("replay", help="open a race replay (.rrd) in the rerun viewer, or summarise it",
                            description="Open a race replay in the rerun viewer where one is available; "
                                        "--summary prints what the recording holds.")
    replay.add_argument("file", metavar="FILE.rrd", type=input_file,
                        help="a replay written by `multirace race --replay`")
    replay.add_argument("--summary", action="store_true", help="print cars, laps, events and duration")
    replay.add_argument("--json", metavar="FILE", type=output_file,
                        help="with --summary: also write the summary as JSON")
    replay.add_argument("--video", metavar="FILE.mp4", type=output_file,
                        help="render the top-down race view from the recorded poses to an MP4 (no viewer needed)")
    replay.set_defaults(func=cmd_replay)


def _add_explain_parser(sub) -> None:
    """The `explain` subcommand."""
    explain = sub.add_parser("explain", help="Grad-CAM heat maps of what an agent looks at while it drives",
                             description="Drive an agent file alone on a track (1-car time trial) and write "
                                         "Grad-CAM heat maps of its chosen actions over its camera frames.")
    explain.add_argument("agent", metavar="AGENT.pt", type=agent_argument, help="an agent file or a shipped agent's name")
    explain.add_argument("--track", default="reinvent_base", help="track name or .npy (default reinvent_base)")
    explain.add_argument("--reverse", action="store_true", help="drive the track the other way round")
    explain.add_argument("--out", metavar="FILE.mp4|FILE.png", type=output_file,
                         help="an MP4 of every frame, or a PNG strip of a few (default AGENT_gradcam.mp4)")
    explain.add_argument("--steps", type=POSITIVE_INT, default=150,
                         help="steps to drive at most (default 150, 10 s); the run ends after one lap")
    explain.add_argument("--replay", metavar="FILE.rrd", type=output_file,
                         help="also record the run with the heat maps as a replay")
    explain.add_argument("--seed", type=SEED, default=0)
    explain.add_argument("--target", choices=("steer", "speed"), default="steer",
                         help="continuous action spaces: explain the steering or the speed mean (default steer)")
    explain.add_argument("--scale", type=number(int, minimum=1, maximum=16), default=3,
                         help="upscale the camera frames this many times (default 3)")
    explain.add_argument("--json", metavar="FILE", type=output_file, help="write the figures as JSON")
    explain.set_defaults(func=cmd_explain)


def _add_plot_parser(sub) -> None:
    """The `plot` subcommand."""
    plot = sub.add_parser("plot", help="plot a sim-trace CSV: the path coloured by speed and reward",
                          description="Draw the track with the driven path coloured by speed and by reward: a "
                                      "row of panels per episode (in a race's sim-trace, per car), up to 8.")
    plot.add_argument("trace", metavar="TRACE.csv", type=input_file, help="a DeepRacer sim-trace CSV")
    plot.add_argument("--out", metavar="FILE.png", type=output_file, help="PNG to write (default: TRACE.png)")
    plot.add_argument("--track", default=None, help="track name or .npy (default: guessed from track_len)")
    plot.set_defaults(func=cmd_plot)


def _add_bench_parser(sub) -> None:
    """The `bench` subcommand."""
    bench = sub.add_parser("bench", help="measure env throughput, renderer ratios, worker scaling and memory",
                           description="Benchmark (not a test): agent-steps/s for 1-8 cars with the fast and "
                                       "PyBullet renderers, the physics+warp floor, two workers over one, peak "
                                       "memory and replay cost, all from one run.")
    bench.add_argument("--json", metavar="FILE", type=output_file, help="write the figures as JSON")
    bench.add_argument("--seconds", type=POSITIVE, default=3.0, help="time per measurement (default 3)")
    bench.add_argument("--replay-seconds", type=NON_NEGATIVE, default=240.0,
                       help="race time of the replay-cost race (0 skips it; default 240, the reset-rule window)")
    bench.add_argument("--profile", action="store_true",
                       help="instead: the per-stage split of a 4-car env step (commands, dynamics, contacts, rules, "
                            "params, reward, render) and the renderer's frames/s alone")
    bench.add_argument("--racing", action="store_true",
                       help="with --profile: the cars driven as a head-to-head race (bots that keep their gaps, "
                            "no boxes) instead of random drivers in a bunch")
    bench.set_defaults(func=cmd_bench)


def build_parser() -> Parser:
    """The `multirace` parser: each subcommand registers its own parser."""
    parser = Parser(prog="multirace", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    _add_race_parser(sub)
    _add_agent_parser(sub)
    _add_imitate_parser(sub)
    _add_replay_parser(sub)
    _add_explain_parser(sub)
    _add_plot_parser(sub)
    _add_bench_parser(sub)

    from .train.cli import add_evaluate_parser, add_train_parser

    add_train_parser(sub)
    add_evaluate_parser(sub)

    from .league.commands import add_league_commands

    add_league_commands(sub)
    return parser


def main(argv=None) -> int:
    """Run the command line; bad input is a one-line error (naming the option, file or field) and exit code 2."""
    from .environment.rewards import RewardFunctionError  # light: the reward module imports no heavy library

    parser = build_parser()
    try:
        args = parser.parse_args(argv)  # every argument is checked here, before any work
    except SystemExit as exc:  # --help, or a bad argument (one line, from options.Parser)
        return exc.code
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, OutputError, RewardFunctionError) as exc:  # TrackError... are ValueErrors
        print(f"multirace {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the output piped into a reader that stopped (`| head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        return 1


if __name__ == "__main__":
    sys.exit(main())
