"""`multirace evaluate`: a robustness report of agent files.

Four parts, each a list of rows (one race per row and seed); `parts` picks some:

1. held-out tracks: a time trial on every track of the declared held-out
   split (`splits.HELD_OUT_TRACKS`) that the agent did not train on (its
   metadata's training notes), forwards (``directions="both"``: and in
   reverse), optionally under a randomisation preset; `--quick` takes the
   first three. Tracks named with `--tracks` that the agent trained on are
   raced but labelled as such and left out of the held-out figures. Each
   row carries the reference lap of `bot:racingline` on the same track and
   direction (nominal car, seed 0) and the agent's best lap over it;
2. perturbation grid: a time trial on the reference track (the first training
   track, else reinvent_base) under each element of the grid: no
   perturbation, the "mild" and "strong" randomisation presets, and the nature
   adversary's uncertainty set (action noise, grip, motor, steering bias,
   camera pose, lighting, sensor noise, shadows);
3. traffic: a head-to-head race on the reference track against two scripted
   bots (``follow@0.8``, ``lanes@1.0``);
4. heats (with ``heats`` > 0): head-to-head heats against the other shipped
   agents and `bot:follow@1.0` (`heats.py`): first places, at-fault
   collisions per lap, penalties and overtakes (attempted, completed) of every
   entrant;
5. overtake scenarios (with ``scenarios`` > 0 seeds): set-up starts behind or
   beside slower cars (`scenarios.py`), the share passed cleanly per scenario.

Per row: lap completion (laps finished / laps asked), whether the run was
clean (every lap finished, no off-track), best lap, off-tracks per lap driven,
collisions per lap driven (and collisions the agent caused). Summary per
agent: on held-out tracks the mean lap completion, the share of clean runs,
the mean best-lap ratio to the racing line and the share of runs within
1.25x of it; lap completion under the grid and nominal, the drop in points
under perturbation, and traffic figures.
"""
from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from ..atomic import AtomicOutput, write_text
from ..environment.race_env import MAX_CARS
from ..sim.tracks import list_tracks
from .heats import check_heats, left_out, run_heats, summarise_heats
from .nature import UNCERTAINTY_SET
from .scenarios import run_scenarios, summarise_scenarios
from .splits import HELD_OUT_TRACKS

GRID = [("none", None), ("mild", "mild"), ("strong", "strong")] + [
    (name, cfg) for name, cfg in UNCERTAINTY_SET if name not in ("nominal", "mild_everything")]
QUICK_GRID = [("none", None), ("mild", "mild"), ("action_noise", dict(UNCERTAINTY_SET)["action_noise"]),
              ("dark", dict(UNCERTAINTY_SET)["dark"])]
TRAFFIC_BOTS = ("follow@0.8", "lanes@1.0")
QUICK_COUNT = 3
REFERENCE_BOT = "bot:racingline"
GOOD_LAP_RATIO = 1.25  # a best lap within this many times the racing line's counts as racing pace


def race_agent(agent_path, track="reinvent_base", reverse=False, laps=2, seed=0, randomize=None, bots=(),
               race="time_trial", max_steps=None,
               step_budget=30.0) -> dict:
    """One race of an agent file (with optional randomisation and bots); the agent's result figures.

    Inference is allowed `step_budget` seconds a step (far more than a league's 1/15 s: a robustness
    report judges driving, not speed of inference).
    """
    from ..racing.runner import RaceConfig, make_controller, run_race

    controller = make_controller(str(agent_path), step_budget=step_budget)
    config = RaceConfig(track=track, reverse=reverse, race=race, laps=laps, seed=seed, max_steps=max_steps,
                        bots=tuple(bots), randomize=randomize)
    result = run_race([controller], config)
    car = next(c for c in result["cars"] if c["car"] == "car_0")
    driven = max(car["progress"] * laps / 100.0, 1e-9)
    return {"track": result["track"], "reverse": reverse, "seed": seed, "laps": car["laps"], "target": laps,
            "completion": car["laps"] / laps, "best_lap": car["best_lap"], "off_tracks": car["off_tracks"],
            "resets": car["resets"], "total_time": car["total_time"],
            "laps_driven": round(driven, 3), "off_tracks_per_lap": car["off_tracks"] / max(driven, 0.25),
            "collisions": car["collisions"], "collisions_caused": car["collisions_caused"],
            "collisions_per_lap": car["collisions"] / max(driven, 0.25),
            "position": car["position"], "status": car["status"], "reason": car["reason"],
            "clean": car["laps"] == laps and car["off_tracks"] == 0}


@functools.lru_cache(maxsize=None)
def reference_lap(track: str, reverse: bool = False, laps: int = 2):
    """Best lap of `bot:racingline` on the track and direction (nominal car, seed 0): the reference lap."""
    from ..racing.entrant import BotController
    from ..racing.runner import RaceConfig, run_race

    result = run_race([BotController(REFERENCE_BOT)], RaceConfig(track=track, reverse=reverse, laps=laps, seed=0))
    return result["cars"][0]["best_lap"]


def trained_tracks(agent_path) -> set:
    """The tracks an agent file (or a ``teacher:PATH``), and every file it started from or blends, trained on."""
    from ..racing.agentfile import parse_metadata, read_payload
    from ..racing.entrant import TEACHER_PREFIX, teacher_spec
    from ..racing.teacher_net import load_teacher

    try:
        if str(agent_path).startswith(TEACHER_PREFIX):
            training = load_teacher(teacher_spec(str(agent_path))[0]).training_notes
        else:
            training = parse_metadata(read_payload(agent_path), str(agent_path)).get("training")
    except Exception:
        return set()
    return {Path(str(t)).stem for stage in training_stages(training) for t in stage.get("tracks") or []}


def training_stages(training) -> list[dict]:
    """Every training record of an agent's lineage: its own, then those of the file it started from (`init`)
    and of the files it is a weight blend of (`blended`), and theirs in turn."""
    stages, pending = [], [training]
    while pending:
        stage = pending.pop(0)
        if not isinstance(stage, dict):
            continue
        stages.append(stage)
        blended = stage.get("blended")
        sources = [stage.get("init")] + (blended if isinstance(blended, list) else [])
        pending.extend(source.get("training") for source in sources if isinstance(source, dict))
    return stages


def held_out_tracks(seen: set, quick: bool = False) -> list[str]:
    """Tracks of the declared held-out split that an agent trained on `seen` never saw (`quick`: a few)."""
    tracks = [t for t in HELD_OUT_TRACKS if t not in seen and t in list_tracks()]
    return tracks[:QUICK_COUNT] if quick else tracks


def evaluate_agent(agent_path, tracks=None, grid=None, laps=2, seeds=1, reference=None, progress=None,
                   quick=False, directions="forward", randomize=None, heats=0, heat_tracks=None, field=None,
                   parts=("held-out", "perturbations", "traffic", "heats", "scenarios"), scenarios=0,
                   scenario_track="reinvent_base", first_heat=1) -> dict:
    """The report for one agent file (see the module docstring): the `parts` asked for, heats (seeds
    `first_heat` onwards) if `heats` > 0, overtake scenarios if `scenarios` (seeds per scenario) > 0."""
    seen = trained_tracks(agent_path)
    if tracks is None:
        tracks = held_out_tracks(seen, quick)
    tracks = tracks if "held-out" in parts else []
    grid = (GRID if grid is None else grid) if "perturbations" in parts else []
    traffic_seeds = seeds if "traffic" in parts else 0
    reference = reference or (sorted(seen)[0] if seen and sorted(seen)[0] in list_tracks() else "reinvent_base")
    reverses = (False, True) if directions == "both" else (True,) if directions == "reverse" else (False,)
    report = {"agent": str(agent_path), "trained_on": sorted(seen), "reference_track": reference, "laps": laps,
              "directions": directions, "randomize": randomize, "held_out": [], "perturbations": [], "traffic": [],
              "heats": [], "scenarios": []}
    say = progress or (lambda line: None)
    for track in tracks:
        for reverse in reverses:
            ref = reference_lap(track, reverse, laps)
            for seed in range(seeds):
                row = race_agent(agent_path, track, reverse=reverse, laps=laps, seed=seed, randomize=randomize)
                row["trained_on"] = Path(track).stem in seen
                row["reference_lap"] = ref
                row["lap_ratio"] = row["best_lap"] / ref if row["best_lap"] and ref else None
                report["held_out"].append(row)
                say(f"{'trained-on' if row['trained_on'] else 'held-out'} {track}{' reverse' if reverse else ''} "
                    f"seed {seed}: {row['laps']}/{laps} laps, {row['off_tracks']} off-tracks, best lap "
                    f"{_fmt(row['best_lap'])} (racing line {_fmt(ref)})")
    for name, cfg in grid:
        for seed in range(seeds):
            row = race_agent(agent_path, reference, laps=laps, seed=seed, randomize=cfg)
            row["perturbation"] = name
            report["perturbations"].append(row)
            say(f"{name} seed {seed}: {row['laps']}/{laps} laps, {row['off_tracks']} off-tracks")
    for seed in range(traffic_seeds):
        row = race_agent(agent_path, reference, laps=laps, seed=seed, bots=TRAFFIC_BOTS, race="head_to_head")
        report["traffic"].append(row)
        say(f"traffic seed {seed}: {row['laps']}/{laps} laps, position {row['position']}, "
            f"{row['collisions']} collisions")
    if heats > 0 and "heats" in parts:
        heat_tracks = heat_tracks or ["reinvent_base", *held_out_tracks(seen)[:1]]
        missing = left_out(agent_path) if field is None else []
        if missing:
            say(f"heats: no room in the field for {', '.join(missing)} (a race holds {MAX_CARS} cars)")
        report["heats"] = run_heats(agent_path, heat_tracks, range(first_heat, first_heat + heats), field=field,
                                     progress=say)
    if scenarios > 0 and "scenarios" in parts:
        report["scenarios"] = run_scenarios(agent_path, range(scenarios), scenario_track, progress=say)
    report["summary"] = summarise(report)
    return report


def _mean(values):
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def summarise(report: dict) -> dict:
    nominal = [r for r in report["perturbations"] if r["perturbation"] == "none"]
    perturbed = [r for r in report["perturbations"] if r["perturbation"] != "none"]
    held = [r for r in report["held_out"] if not r.get("trained_on")]
    summary = {
        "held_out_runs": len(held),
        "held_out_completion": _mean([r["completion"] for r in held]),
        "held_out_clean_share": _mean([float(r["clean"]) for r in held]),
        "held_out_lap_ratio": _mean([r.get("lap_ratio") for r in held]),
        "held_out_clean_within_1_25_share": _mean([float(r["clean"] and r.get("lap_ratio") is not None
                                                         and r["lap_ratio"] <= GOOD_LAP_RATIO) for r in held]),
        "held_out_tracks_completed": sorted({r["track"] for r in held if r["laps"] >= 1}),
        "held_out_best_lap": _mean([r["best_lap"] for r in held]),
        "held_out_off_tracks_per_lap": _mean([r["off_tracks_per_lap"] for r in held]),
        "nominal_completion": _mean([r["completion"] for r in nominal]),
        "perturbed_completion": _mean([r["completion"] for r in perturbed]),
        "perturbed_off_tracks_per_lap": _mean([r["off_tracks_per_lap"] for r in perturbed]),
        "nominal_off_tracks_per_lap": _mean([r["off_tracks_per_lap"] for r in nominal]),
        "traffic_completion": _mean([r["completion"] for r in report["traffic"]]),
        "traffic_collisions_per_lap": _mean([r["collisions_per_lap"] for r in report["traffic"]]),
        "traffic_collisions_caused_per_lap": _mean([r["collisions_caused"] / max(r["laps_driven"], 0.25)
                                                    for r in report["traffic"]]),
        "traffic_position": _mean([r["position"] for r in report["traffic"]]),
    }
    if report.get("heats"):
        summary["heats"] = summarise_heats(report["heats"])
    if report.get("scenarios"):
        summary["scenarios"] = summarise_scenarios(report["scenarios"])
    if summary["nominal_completion"] is not None and summary["perturbed_completion"] is not None:
        summary["completion_drop_points"] = 100.0 * (summary["nominal_completion"] - summary["perturbed_completion"])
    return summary


SUMMARY_LABELS = {  # the summary's keys (JSON) as the printed table names them
    "held_out_runs": "held-out runs", "held_out_completion": "held-out lap completion",
    "held_out_clean_share": "held-out clean share", "held_out_lap_ratio": "held-out best lap / racing line",
    "held_out_clean_within_1_25_share": "held-out clean and within 1.25x share",
    "held_out_tracks_completed": "held-out tracks with a lap", "held_out_best_lap": "held-out mean best lap (s)",
    "held_out_off_tracks_per_lap": "held-out off-tracks / lap", "nominal_completion": "nominal lap completion",
    "perturbed_completion": "perturbed lap completion", "perturbed_off_tracks_per_lap": "perturbed off-tracks / lap",
    "nominal_off_tracks_per_lap": "nominal off-tracks / lap", "traffic_completion": "traffic lap completion",
    "traffic_collisions_per_lap": "traffic collisions / lap",
    "traffic_collisions_caused_per_lap": "traffic collisions caused / lap", "traffic_position": "traffic position",
    "completion_drop_points": "completion drop under perturbations (points)"}


def _fmt(value, digits=2):
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def print_report(reports: list, console) -> None:
    from rich.table import Table

    for report in reports:
        reference = report["reference_track"] + (", trained on" if report["reference_track"] in report.get(
            "trained_on", ()) else "")
        table = Table(title=f"{Path(report['agent']).name}: held-out tracks, perturbations (on {reference}), "
                            f"traffic; {report['laps']} laps per race")
        for column in ("part", "track / perturbation", "laps", "lap completion", "best lap", "x racing line",
                       "off-tracks/lap", "collisions/lap", "status"):
            table.add_column(column)
        for part, rows in (("held-out", report["held_out"]), ("perturbed", report["perturbations"]),
                           ("traffic", report["traffic"])):
            for r in rows:
                label = r.get("perturbation", r["track"]) + (" reverse" if r["reverse"] else "")
                label += (f" s{r['seed']}" if r["seed"] else "") + (" (trained on)" if r.get("trained_on") else "")
                table.add_row(part, label, f"{r['laps']}/{r['target']}", f"{100 * r['completion']:.0f}%",
                              _fmt(r["best_lap"]), _fmt(r.get("lap_ratio")), _fmt(r["off_tracks_per_lap"]),
                              _fmt(r["collisions_per_lap"]),
                              r["status"] + (f" P{r['position']}" if part == "traffic" else ""))
        console.print(table)
    summary = Table(title="summary")
    summary.add_column("figure")
    for report in reports:
        summary.add_column(Path(report["agent"]).stem, justify="right")
    keys = [key for key in reports[0]["summary"] if key not in ("heats", "scenarios")]
    for key in keys:
        summary.add_row(SUMMARY_LABELS.get(key, key), *[_fmt(r["summary"].get(key)) if not isinstance(r["summary"].get(key), list)
                               else str(len(r["summary"][key])) for r in reports])
    console.print(summary)
    for report in reports:
        if report["summary"].get("heats"):
            print_heats(Path(report["agent"]).name, report["summary"]["heats"], console)
        if report["summary"].get("scenarios"):
            print_scenarios(Path(report["agent"]).name, report["summary"]["scenarios"], console)


def print_heats(agent_name: str, heats: dict, console) -> None:
    from rich.table import Table

    table = Table(title=f"{agent_name}: head-to-head heats (at-fault collisions per lap driven; overtakes: passes "
                        "for position on track, attempts from within a car length closing in)")
    for column in ("track", "entrant", "heats", "first", "mean pos", "laps", "at fault", "/lap", "at fault by kind",
                   "penalties", "overtakes", "overtaken", "attempted", "completed"):
        table.add_column(column, justify="left" if column in ("track", "entrant") else "right",
                         no_wrap=column in ("track", "entrant"))
    for track, entrants in heats.items():
        for name, f in entrants.items():
            table.add_row(track, name, str(f["heats"]), str(f["first"]), f"{f['mean_position']:.2f}",
                          f"{f['laps_driven']:.1f}", str(f["collisions_caused"]), f"{f['caused_per_lap']:.3f}",
                          (", ".join(f"{kind} {count}" for kind, count in f.get("caused_kinds", {}).items()) or "-")
                          + (f" ({f['caused_into_crash']} into a crash)" if f.get("caused_into_crash") else ""),
                          *[str(f.get(key, "-")) for key in ("penalties", "overtakes", "overtaken",
                                                             "overtakes_attempted", "overtakes_completed")])
    console.print(table)


def print_scenarios(agent_name: str, scenarios: dict, console) -> None:
    from rich.table import Table

    table = Table(title=f"{agent_name}: overtake scenarios (success: passed, still ahead when the time is up, no "
                        "at-fault contact)")
    for column in ("scenario", "runs", "passed", "passed cleanly", "success rate"):
        table.add_column(column)
    for name, f in scenarios.items():
        rate = "-" if f["success_rate"] is None else f"{100 * f['success_rate']:.0f}%"
        table.add_row(name, str(f["runs"]), str(f["passed"]), str(f["passed_cleanly"]), rate)
    console.print(table)


def _bar_panel(ax, series: list, title: str, ceiling: float) -> None:
    """Grouped bars of `series` ([(label, [(name, value or None), ...]), ...]) on `ax`. The y axis starts at 0
    and reaches at least `ceiling`, so counts that are all zero draw as zero, not as an empty panel; a panel
    with nothing to draw (a part not run) says so."""
    names = list(dict.fromkeys(name for _, bars in series for name, _ in bars))
    ax.set_title(title, fontsize=10)
    if not names:
        ax.text(0.5, 0.5, "not run", ha="center", va="center", transform=ax.transAxes, color="grey")
        ax.set_xticks([])
        ax.set_yticks([])
        return
    width = 0.8 / len(series)
    top = ceiling
    for k, (label, bars) in enumerate(series):
        values = dict(bars)
        heights = [values.get(name) or 0.0 for name in names]
        top = max(top, *heights)
        bars = ax.bar(np.arange(len(names)) + k * width, heights, width, label=label)
        ax.bar_label(bars, fmt="%.3g", fontsize=6)  # a zero reads as 0, not as a missing bar
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=60, ha="right", fontsize=7)
    ax.set_ylim(0, top * 1.1)
    ax.grid(alpha=0.3, axis="y")


def plot_report(reports: list, path) -> None:
    """Write `report_figure(reports)` as a PNG at `path`."""
    import matplotlib.pyplot as plt

    fig = report_figure(reports)
    with AtomicOutput(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def report_figure(reports: list):
    """The report as a matplotlib figure: lap completion on held-out tracks and under perturbations,
    off-tracks per lap under perturbations, and the traffic race (lap completion, collisions and collisions
    caused per lap)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def by(rows, key, value):
        names = list(dict.fromkeys(r[key] for r in rows))
        return [(name, _mean([value(r) for r in rows if r[key] == name])) for name in names]

    def traffic(rows):
        return [(figure, _mean([value(r) for r in rows])) for figure, value in (
            ("lap completion", lambda r: r["completion"]), ("collisions/lap", lambda r: r["collisions_per_lap"]),
            ("caused/lap", lambda r: r["collisions_caused"] / max(r["laps_driven"], 0.25)))] if rows else []

    fig, axes = plt.subplots(1, 4, figsize=(19, 4.4))
    labels = [Path(report["agent"]).stem for report in reports]
    _bar_panel(axes[0], [(label, by(r["held_out"], "track", lambda x: 100 * x["completion"]))
                         for label, r in zip(labels, reports)], "lap completion on held-out tracks (%)", 100)
    _bar_panel(axes[1], [(label, by(r["perturbations"], "perturbation", lambda x: 100 * x["completion"]))
                         for label, r in zip(labels, reports)], "lap completion under perturbations (%)", 100)
    _bar_panel(axes[2], [(label, by(r["perturbations"], "perturbation", lambda x: x["off_tracks_per_lap"]))
                         for label, r in zip(labels, reports)], "off-tracks per lap under perturbations", 1.0)
    _bar_panel(axes[3], [(label, traffic(r["traffic"])) for label, r in zip(labels, reports)],
               "traffic race (completion 0-1; per lap driven)", 1.0)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7)
    fig.tight_layout()
    return fig


def _names(text):
    """A comma-separated command-line list (None stays None)."""
    return [t.strip() for t in text.split(",") if t.strip()] if text else None


def check_agent_files(agents) -> None:
    """Load every agent file to evaluate (teachers are checked as the arguments are read): a file that cannot
    race is an `AgentFileError` naming it and its fault, before any race (a race would score it as a forfeit)."""
    from ..racing.agentfile import load_agent
    from ..racing.entrant import TEACHER_PREFIX

    for agent in agents:
        if not str(agent).startswith(TEACHER_PREFIX):
            load_agent(agent, step_budget=None)


def run_evaluation(args) -> int:
    """The `multirace evaluate` command."""
    from rich.console import Console

    console = Console(width=160)
    tracks = _names(args.tracks)
    grid = QUICK_GRID if args.quick else None
    parts = _names(args.parts)
    if args.heats and "heats" in parts:
        check_heats(_names(args.heat_tracks), _names(args.field))
    check_agent_files(args.agents)
    reports = []
    for agent in args.agents:
        reports.append(evaluate_agent(agent, tracks=tracks, grid=grid, laps=args.laps, seeds=args.seeds,
                                      quick=args.quick, directions=args.directions, randomize=args.randomize,
                                      heats=args.heats, first_heat=args.first_heat,
                                      heat_tracks=_names(args.heat_tracks),
                                      field=_names(args.field), parts=parts, scenarios=args.scenarios,
                                      scenario_track=args.scenario_track,
                                      progress=lambda line: console.print(f"[dim]{line}[/dim]")))
    print_report(reports, console)
    png = Path(args.png) if args.png else (Path(args.json).with_suffix(".png") if args.json
                                           else Path.cwd() / (Path(args.agents[0]).stem + ".eval.png"))
    if args.json:  # the report first: a plot that fails must not lose it
        write_text(args.json, json.dumps(reports if len(reports) > 1 else reports[0], indent=1))
    plot_report(reports, png)
    console.print(f"wrote {png}")
    return 0
