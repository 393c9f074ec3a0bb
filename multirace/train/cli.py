"""`multirace train` and `multirace evaluate`: argument definitions and handlers (hooked into multirace.cli)."""
from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

from ..environment.rewards import NAMED_REWARDS
from ..options import COUNT, POSITIVE, POSITIVE_INT, SEED, input_file, number, output_file
from ..resources import agent_argument

PARTS = ("held-out", "perturbations", "traffic", "heats", "scenarios")  # the parts of `multirace evaluate`'s report


def add_train_parser(sub) -> None:
    p = sub.add_parser("train", help="train a camera agent with PPO self-play (shared parameters)",
                       description="PPO with shared parameters from the camera: every car is the learner. "
                                   "Writes FILE.pt (agent file), FILE.png (learning curve), FILE.train.json, "
                                   "FILE.ckpt/ (checkpoint, snapshots) and FILE.deepracer/ (DeepRacer-for-Cloud "
                                   "training folder).")
    p.add_argument("--track", default="reinvent_base",
                   help="track(s), comma-separated (bundled names or .npy paths; train-split: every bundled "
                        "track outside the held-out split; default reinvent_base)")
    p.add_argument("--reverse", default="no", choices=("no", "yes", "both"), help="direction(s) (default no)")
    p.add_argument("--minutes", type=POSITIVE, default=10.0, help="wall-clock budget (default 10)")
    p.add_argument("--out", metavar="FILE.pt", type=output_file, help="agent file to write (required)")
    p.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
    p.add_argument("--config", default="fast", metavar="PRESET",
                   help="hyperparameter preset: fast (default), throughput (fast with the update beside the next "
                        "rollout and 8 cars per worker: more agent-steps per second), deepracer (the console's PPO "
                        "defaults), race (traffic, opponent pool, collision penalty; use with --init), tiny")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting (JSON value), e.g. --set epochs=4 --set gamma=0.995; "
                        "see `multirace train --list-settings`")
    p.add_argument("--list-settings", action="store_true", help="print every setting with its doc and exit")
    p.add_argument("--action-space", default=None, metavar="JSON", type=shipped_action_space,
                   help="model_metadata.json with the action space (or a shipped one by name: "
                        "action_space_racer.json)")
    p.add_argument("--reward", default=None,
                   help="a named reward: 'progress' (built-in, default), 'centre' (DeepRacer default); or a reward "
                        ".py file (the shipped example: reward_speed_progress.py)")
    p.add_argument("--network", default=None, help="MULTIRACE_SMALL_CNN or DEEP_CONVOLUTIONAL_NETWORK_SHALLOW")
    p.add_argument("--envs", type=POSITIVE_INT, default=None, help="worker processes (default 2)")
    p.add_argument("--cars", type=number(int, minimum=1, maximum=8), default=None,
                   help="learning cars per env (default 4)")
    p.add_argument("--init", default=None, metavar="AGENT.pt", type=agent_argument,
                   help="initialise the policy from an agent file (or a shipped agent's name)")
    p.add_argument("--resume", default=None, metavar="CKPT", type=input_file,
                   help="resume from FILE.ckpt/checkpoint.pt")
    p.add_argument("--robust", action="store_true",
                   help="domain randomisation with a curriculum, opponent pool (PFSP), nature adversary and "
                        "procedural tracks")
    p.add_argument("--privileged", action="store_true",
                   help="learning by cheating: PPO of a state policy (the teacher) on the privileged state, then "
                        "DAgger of the camera policy from it (writes FILE.pt and FILE.teacher.pt; continuous "
                        "action spaces)")
    p.add_argument("--teacher", default=None, metavar="FILE.teacher.pt", type=input_file,
                   help="--privileged: reuse the teacher an earlier run wrote (its whole budget then goes to the "
                        "camera student)")
    p.add_argument("--stop-on-success", action="store_true",
                   help="stop at the first evaluation that finishes every lap with no off-track")
    p.add_argument("--engine", default="local", choices=("local", "rllib"),
                   help="local (default) or rllib (Ray RLlib PPO, one shared policy; pip install -e \".[rllib]\")")
    p.add_argument("--address", "--ray-address", dest="address", default=None, metavar="ADDR",
                   help="--engine rllib: Ray cluster to run on, passed to ray.init(address=...) "
                        "(e.g. auto, or ray://HEAD:10001); default: a local Ray")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)


FLAG_OF_FIELD = {"tracks": "--track", "reverse": "--reverse", "minutes": "--minutes", "seed": "--seed",
                 "action_space": "--action-space", "reward": "--reward", "network": "--network", "num_envs": "--envs",
                 "cars_per_env": "--cars", "stop_on_success": "--stop-on-success", "progress": "--no-progress"}


def config_from_args(args):
    from .config import make_config

    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        try:
            overrides[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key.strip()] = value
    from .splits import expand_tracks

    tracks = tuple(expand_tracks(t.strip() for t in args.track.split(",") if t.strip()))
    if args.robust:
        overrides.setdefault("robust", True)
    if args.privileged or args.teacher:
        overrides.setdefault("privileged", True)
    flags = {"tracks": tracks, "reverse": args.reverse, "minutes": args.minutes, "seed": args.seed,
             "action_space": args.action_space, "reward": shipped_or_given(args.reward, ".py"),
             "network": args.network, "num_envs": args.envs, "cars_per_env": args.cars,
             "stop_on_success": True if args.stop_on_success else None,
             "progress": False if args.no_progress else None}
    for key in overrides:
        if flags.get(key) is not None:
            raise ValueError(f"--set {key}: {FLAG_OF_FIELD[key]} sets it too; give it once")
    config = make_config(args.config, **{key: value for key, value in flags.items() if key not in overrides},
                         **overrides)
    for key in ("camera", "tracks", "bots", "rivals"):
        setattr(config, key, tuple(getattr(config, key)))
    if config.robust:
        from .robust import apply_robust

        apply_robust(config, explicit=set(overrides))
    check_inputs(config)
    return config


def shipped_or_given(path: str | None, suffix: str) -> str | None:
    """A file option as given, or the shipped file of that name (agents/: `action_space_racer.json`,
    `reward_speed_progress.py`) when there is no such file here."""
    from ..resources import agents_dir

    if path is None or path in NAMED_REWARDS or Path(path).exists():
        return path
    shipped = agents_dir() / Path(path).name
    return str(shipped) if shipped.suffix == suffix and shipped.is_file() else path


def shipped_action_space(text: str) -> str:
    """--action-space's type: an existing file, or a shipped action space by name."""
    return input_file(shipped_or_given(text, ".json"))


def check_inputs(config) -> None:
    """Refuse, before any work starts, a network that does not exist, a track or action space that does not
    load, a reward file that is not there: one line naming the option (in the worker processes they would
    end in a traceback)."""
    from ..environment.actions import load_action_space
    from ..environment.randomize import Randomization
    from ..racing.nets import NETWORKS

    if config.network not in NETWORKS:
        raise ValueError(f"--network: unknown network {config.network!r}; choose from {', '.join(NETWORKS)}")
    check_tracks(config.tracks, "--track")
    check_tracks(config.eval_tracks, "--set eval_tracks")
    try:
        Randomization.from_config(config.eval_randomize)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"--set eval_randomize: {exc}") from None
    if config.reward not in NAMED_REWARDS and not Path(config.reward).is_file():
        raise ValueError(f"--reward: {config.reward}: no such file (give {', '.join(NAMED_REWARDS)} or a reward "
                         f".py file)")
    try:
        load_action_space(config.action_space)
    except (ValueError, OSError) as exc:
        raise ValueError(f"--action-space: {exc}") from None
    if config.rivals:
        check_rivals(config)
    if config.eval_bots:
        from .rivals import race_opponents

        try:
            race_opponents(config.eval_bots)
        except (ValueError, OSError) as exc:
            raise ValueError(f"--set eval_bots: {exc}") from None


def check_rivals(config) -> None:
    """Refuse rivals that do not load, or more cars than a race holds."""
    import numpy as np

    from ..environment.race_env import MAX_CARS
    from .rivals import RivalSeat

    cars = config.cars_per_env + len(config.bots) + config.rival_cars
    if config.rival_cars < 1 or cars > MAX_CARS:
        raise ValueError(f"--set rival_cars: {config.rival_cars} rival cars beside {config.cars_per_env} learning "
                         f"cars and {len(config.bots)} bots; a race holds 1 to {MAX_CARS} cars and rivals need a car")
    try:
        RivalSeat(config.rivals, np.random.default_rng(0))
    except (ValueError, OSError) as exc:
        raise ValueError(f"--set rivals: {exc}") from None


def cmd_train(args) -> int:
    if args.list_settings:
        from .config import describe

        print(describe())
        return 0
    if not args.out:
        raise ValueError("--out FILE.pt is required")
    config = config_from_args(args)
    if args.engine == "rllib":
        if config.privileged:
            raise ValueError("--privileged: a local-engine option (the teacher and its student run in multirace's "
                             "own loops)")
        if args.resume or args.init:
            raise ValueError("--engine rllib: --resume and --init are local-engine options (resume an RLlib run "
                             "with ray.rllib.algorithms.Algorithm.from_checkpoint(FILE.rllib))")
        from .rllib import train_rllib

        return train_rllib(config, args.out, envs=args.envs, address=args.address)
    command = shlex.join(["multirace", *sys.argv[1:]]) if sys.argv and sys.argv[0].endswith("multirace") else None
    if config.privileged:
        return report_privileged(config, args, command)
    from .ppo import train
    from .run import evaluation_runs

    summary = train(config, args.out, init=args.init, resume=args.resume, command=command)

    def when(seconds):
        return f"{seconds} s" if seconds is not None else "none"

    target = config.eval_laps * len(evaluation_runs(config))  # laps of one evaluation, over all its runs
    laps = f"{target}/{target}"
    print(f"wrote {summary['out']}: {summary['iterations']} iterations, {summary['agent_steps']} agent-steps in "
          f"{summary['wall_seconds']} s ({summary['steps_per_s']} agent-steps/s, sampling "
          f"{summary['sample_seconds']} s, updates {summary['update_seconds']} s); first clean {laps} evaluation "
          f"(no off-track): {when(summary['first_clean_seconds'])}; first {laps} counting resets: "
          f"{when(summary['first_success_seconds'])}")
    print(f"learning curve: {Path(args.out).with_suffix('.png')}")
    return 0


def report_privileged(config, args, command) -> int:
    """Run learning by cheating (`distill.train_privileged`) and print both stages' figures."""
    if args.resume:
        raise ValueError("--privileged: --resume is for PPO from the camera (--init starts the camera student "
                         "from an agent file, --teacher reuses a trained teacher)")
    from .distill import train_privileged

    summary = train_privileged(config, args.out, command=command, init=args.init, teacher_file=args.teacher)
    teacher, student = summary["teacher"], summary["student"]
    for name, evaluation, ratio in (("teacher", teacher["selected"], teacher["ratio"]),
                                    ("student", student["evaluation"], student["ratio"])):
        if not evaluation:
            print(f"{name}: not evaluated")
            continue
        lap = f"{evaluation['best_lap']:.2f} s" if evaluation.get("best_lap") else "none"
        target = evaluation.get("target", config.eval_laps)
        print(f"{name}: {evaluation['laps']}/{target} laps, {evaluation['resets']} off-track resets, best "
              f"lap {lap}" + (f" ({ratio}x the racing line's {summary['racing_line_lap']:.2f} s)" if ratio else ""))
    for name, stage in (("teacher", teacher), ("student", student)):
        reached = ", ".join(f"{key.replace('_', ' ')} at {m['seconds']:.0f} s ({m['agent_steps']} agent-steps)"
                            for key, m in stage["milestones"].items())
        if stage.get("reused"):
            print(f"{name}: reused from {stage['reused']} (trained in {stage.get('trained_seconds')} s)")
        else:
            print(f"{name} first evaluations: {reached or 'none clean'}")
    teacher_note = f"(from the teacher {summary['teacher_file']})" if teacher.get("reused") else \
        f"and {summary['teacher_file']} (teacher)"
    print(f"wrote {summary['out']} (camera agent) {teacher_note} in "
          f"{summary['wall_seconds']} s: teacher {teacher['wall_seconds']} s, {teacher['agent_steps']} agent-steps; "
          f"student {student['wall_seconds']} s, {student['agent_steps']} agent-steps")
    return 0


def check_tracks(tracks, option: str) -> None:
    """Load every track named (a bundled name or a .npy path); the first that does not load is a ValueError
    naming `option`."""
    from ..sim.tracks import load_track

    for track in tracks:
        try:
            load_track(track)
        except (ValueError, OSError) as exc:
            raise ValueError(f"{option}: {exc}") from None


def add_evaluate_parser(sub) -> None:
    p = sub.add_parser("evaluate", help="robustness report of an agent: held-out tracks, perturbations, traffic",
                       description="Race an agent over held-out tracks and a grid of perturbations and report lap "
                                   "completion, mean best lap, off-tracks per lap and collisions per lap in "
                                   "traffic, as a table and a PNG.")
    p.add_argument("agents", nargs="+", metavar="FILE.pt", type=racer_argument,
                   help="agent file(s), shipped agents' names or teacher:FILE.teacher.pt (an RL teacher of "
                        "train --privileged, raced from its privileged state) to evaluate")
    p.add_argument("--json", metavar="FILE", type=output_file, help="write the report as JSON")
    p.add_argument("--png", metavar="FILE.png", type=output_file,
                   help="write the report plot (default: next to --json, else AGENT.eval.png in the working folder)")
    p.add_argument("--tracks", default=None,
                   help="comma-separated tracks (default: the declared held-out split, less any track the agent "
                        "trained on)")
    p.add_argument("--directions", choices=("forward", "reverse", "both"), default="forward",
                   help="race the held-out tracks forwards (default), in reverse or both")
    p.add_argument("--randomize", choices=("mild", "strong"), default=None,
                   help="domain randomisation on the held-out tracks (default: none)")
    p.add_argument("--laps", type=POSITIVE_INT, default=2, help="laps per run (default 2)")
    p.add_argument("--seeds", type=POSITIVE_INT, default=1, help="seeds per cell (default 1)")
    p.add_argument("--quick", action="store_true",
                   help="fewer perturbations, and 3 tracks of the declared held-out split the agent did not train on")
    p.add_argument("--heats", type=COUNT, default=0, metavar="N",
                   help="also run N head-to-head heats (seeds K..K+N-1, --first-heat K, 3 laps) per heat track "
                        "against the field and report first places and collisions caused per lap (default 0: none)")
    p.add_argument("--first-heat", type=POSITIVE_INT, default=1, metavar="K",
                   help="the first heat's seed (default 1): a second run with --first-heat N+1 adds new heats to a "
                        "first run's N")
    p.add_argument("--heat-tracks", default=None, metavar="TRACKS",
                   help="comma-separated heat tracks (default: reinvent_base and the first held-out track the "
                        "agent did not train on)")
    p.add_argument("--field", default=None, metavar="ENTRANTS",
                   help="comma-separated heat opponents: agent files, shipped agents' names, teacher:FILE.teacher.pt or "
                        "bot specs (default: "
                        "the other shipped agents and bot:follow@1.0)")
    p.add_argument("--scenarios", type=COUNT, default=0, metavar="N",
                   help="also run the overtake scenarios (a slower car ahead on a straight, in a chicane, a car "
                        "alongside into a corner, two cars side by side ahead), seeds 0..N-1 each, and report the "
                        "share passed cleanly (default 0: none)")
    p.add_argument("--scenario-track", default="reinvent_base", metavar="TRACK",
                   help="the track of the overtake scenarios (default reinvent_base)")
    p.add_argument("--parts", default=",".join(PARTS), metavar="PARTS",
                   help=f"comma-separated parts of the report to run (default: all of {','.join(PARTS)}; heats "
                        "need --heats, scenarios --scenarios)")
    p.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args) -> int:
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        raise ValueError(f"--parts: {', '.join(unknown) or 'nothing'} is not a part; choose from {', '.join(PARTS)}")
    if args.tracks:
        check_tracks([t.strip() for t in args.tracks.split(",") if t.strip()], "--tracks")
    check_tracks([args.scenario_track], "--scenario-track")
    from .evaluate import run_evaluation

    return run_evaluation(args)


def racer_argument(spec: str) -> str:
    """`agent_argument`, or ``teacher:PATH`` (an RL teacher file of `train --privileged`, raced from its
    privileged state): the argparse `type` of `evaluate`'s racers."""
    import argparse

    from ..racing.entrant import TEACHER_PREFIX, teacher_spec  # not at import: the CLI's parser stays light

    if spec.startswith(TEACHER_PREFIX):
        if not Path(teacher_spec(spec)[0]).is_file():
            raise argparse.ArgumentTypeError(f"{spec}: no such teacher file")
        return spec
    return agent_argument(spec)
