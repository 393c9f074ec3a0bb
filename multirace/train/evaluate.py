"""`multirace evaluate`: a robustness report of agent files.

Three parts, each a list of rows (one race per row and seed):

1. held-out tracks: a time trial on every bundled track the agent did not
   train on (its metadata's training notes), forwards; `--quick` takes the
   first three of the declared split `HELD_OUT_TRACKS` that the agent did not
   train on. Tracks named with `--tracks` that the agent trained on are
   raced but labelled as such and left out of the held-out figures;
2. perturbation grid: a time trial on the reference track (the first training
   track, else reinvent_base) under each element of the grid: no
   perturbation, the "mild" and "strong" randomisation presets, and the nature
   adversary's uncertainty set (action noise, grip, motor, steering bias,
   camera pose, lighting, sensor noise, shadows);
3. traffic: a head-to-head race on the reference track against two scripted
   bots (``follow@0.8``, ``lanes@1.0``).

Per row: lap completion (laps finished / laps asked), best lap, off-tracks
per lap driven, collisions per lap driven (and collisions the agent caused).
Summary per agent: mean lap completion on held-out tracks, under the grid and
nominal, the drop in points under perturbation, and traffic figures.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..sim.tracks import list_tracks
from .nature import UNCERTAINTY_SET

GRID = [("none", None), ("mild", "mild"), ("strong", "strong")] + [
    (name, cfg) for name, cfg in UNCERTAINTY_SET if name not in ("nominal", "mild_everything")]
QUICK_GRID = [("none", None), ("mild", "mild"), ("action_noise", dict(UNCERTAINTY_SET)["action_noise"]),
              ("dark", dict(UNCERTAINTY_SET)["dark"])]
TRAFFIC_BOTS = ("follow@0.8", "lanes@1.0")
# The project's declared held-out split: real DeepRacer tracks that none of its training recipes use.
HELD_OUT_TRACKS = ("2022_april_open", "Canada_Training", "July_2020", "Mexico_track", "arctic_pro", "Aragon",
                   "2022_september_pro", "Virtual_May19_Train_track")
QUICK_COUNT = 3


def race_agent(agent_path, track="reinvent_base", reverse=False, laps=2, seed=0, randomize=None, bots=(),
               race="time_trial", max_steps=None,
               step_budget=30.0) -> dict:
    """One race of an agent file (with optional randomisation and bots); the agent's result figures.

    Inference is allowed `step_budget` seconds a step (far more than a league's 1/15 s: a robustness
    report judges driving, not speed of inference).
    """
    from ..racing.agentfile import AgentController
    from ..racing.runner import RaceConfig, run_race

    controller = AgentController(agent_path, step_budget=step_budget)
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
            "position": car["position"], "status": car["status"], "reason": car["reason"]}


def trained_tracks(agent_path) -> set:
    from ..racing.agentfile import parse_metadata, read_payload

    try:
        meta = parse_metadata(read_payload(agent_path), str(agent_path))
    except Exception:
        return set()
    return {Path(t).stem for t in (meta.get("training") or {}).get("tracks", [])}


def held_out_tracks(seen: set, quick: bool = False) -> list[str]:
    """Bundled tracks an agent that trained on `seen` never saw (`quick`: a few of the declared split)."""
    if quick:
        return [t for t in HELD_OUT_TRACKS if t not in seen][:QUICK_COUNT]
    return [t for t in list_tracks() if t not in seen]


def evaluate_agent(agent_path, tracks=None, grid=None, laps=2, seeds=1, reference=None, progress=None,
                   quick=False) -> dict:
    """The full report for one agent file (see the module docstring)."""
    seen = trained_tracks(agent_path)
    if tracks is None:
        tracks = held_out_tracks(seen, quick)
    reference = reference or (sorted(seen)[0] if seen and sorted(seen)[0] in list_tracks() else "reinvent_base")
    grid = GRID if grid is None else grid
    report = {"agent": str(agent_path), "trained_on": sorted(seen), "reference_track": reference, "laps": laps,
              "held_out": [], "perturbations": [], "traffic": []}
    say = progress or (lambda line: None)
    for track in tracks:
        for seed in range(seeds):
            row = race_agent(agent_path, track, laps=laps, seed=seed)
            row["trained_on"] = Path(track).stem in seen
            report["held_out"].append(row)
            say(f"{'trained-on' if row['trained_on'] else 'held-out'} {track} seed {seed}: "
                f"{row['laps']}/{laps} laps, {row['off_tracks']} off-tracks")
    for name, cfg in grid:
        for seed in range(seeds):
            row = race_agent(agent_path, reference, laps=laps, seed=seed, randomize=cfg)
            row["perturbation"] = name
            report["perturbations"].append(row)
            say(f"{name} seed {seed}: {row['laps']}/{laps} laps, {row['off_tracks']} off-tracks")
    for seed in range(seeds):
        row = race_agent(agent_path, reference, laps=laps, seed=seed, bots=TRAFFIC_BOTS, race="head_to_head")
        report["traffic"].append(row)
        say(f"traffic seed {seed}: {row['laps']}/{laps} laps, position {row['position']}, "
            f"{row['collisions']} collisions")
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
        "held_out_completion": _mean([r["completion"] for r in held]),
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
    if summary["nominal_completion"] is not None and summary["perturbed_completion"] is not None:
        summary["completion_drop_points"] = 100.0 * (summary["nominal_completion"] - summary["perturbed_completion"])
    return summary


def _fmt(value, digits=2):
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def print_report(reports: list, console) -> None:
    from rich.table import Table

    for report in reports:
        table = Table(title=f"{Path(report['agent']).name}: held-out tracks, perturbations (on "
                            f"{report['reference_track']}), traffic; {report['laps']} laps per race")
        for column in ("part", "track / perturbation", "laps", "lap completion", "best lap", "off-tracks/lap",
                       "collisions/lap", "status"):
            table.add_column(column)
        for part, rows in (("held-out", report["held_out"]), ("perturbed", report["perturbations"]),
                           ("traffic", report["traffic"])):
            for r in rows:
                label = r.get("perturbation", r["track"]) + (f" s{r['seed']}" if r["seed"] else "")
                label += " (trained on)" if r.get("trained_on") else ""
                table.add_row(part, label, f"{r['laps']}/{r['target']}", f"{100 * r['completion']:.0f}%",
                              _fmt(r["best_lap"]), _fmt(r["off_tracks_per_lap"]), _fmt(r["collisions_per_lap"]),
                              r["status"] + (f" P{r['position']}" if part == "traffic" else ""))
        console.print(table)
    summary = Table(title="summary")
    summary.add_column("figure")
    for report in reports:
        summary.add_column(Path(report["agent"]).stem, justify="right")
    keys = list(reports[0]["summary"])
    for key in keys:
        summary.add_row(key, *[_fmt(r["summary"].get(key)) if not isinstance(r["summary"].get(key), list)
                               else str(len(r["summary"][key])) for r in reports])
    console.print(summary)


def plot_report(reports: list, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    width = 0.8 / len(reports)
    for k, report in enumerate(reports):
        label = Path(report["agent"]).stem
        for ax, rows, key in ((axes[0], report["held_out"], "track"),
                              (axes[1], report["perturbations"], "perturbation")):
            names = list(dict.fromkeys(r[key] for r in rows))
            values = [_mean([r["completion"] for r in rows if r[key] == n]) for n in names]
            ax.bar(np.arange(len(names)) + k * width, [100 * v for v in values], width, label=label)
            ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=60, ha="right", fontsize=7)
        names = list(dict.fromkeys(r["perturbation"] for r in report["perturbations"]))
        values = [_mean([r["off_tracks_per_lap"] for r in report["perturbations"] if r["perturbation"] == n])
                  for n in names]
        axes[2].bar(np.arange(len(names)) + k * width, values, width, label=label)
        axes[2].set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=60, ha="right", fontsize=7)
    axes[0].set_title("lap completion on held-out tracks (%)")
    axes[1].set_title("lap completion under perturbations (%)")
    axes[2].set_title("off-tracks per lap under perturbations")
    for ax in axes:
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_evaluation(args) -> int:
    """The `multirace evaluate` command."""
    from rich.console import Console

    console = Console(width=140)
    tracks = [t.strip() for t in args.tracks.split(",")] if args.tracks else None
    grid = QUICK_GRID if args.quick else None
    reports = []
    for agent in args.agents:
        if not Path(agent).exists():
            raise FileNotFoundError(f"{agent}: no such agent file")
        reports.append(evaluate_agent(agent, tracks=tracks, grid=grid, laps=args.laps, seeds=args.seeds,
                                      quick=args.quick, progress=lambda line: console.print(f"[dim]{line}[/dim]")))
    print_report(reports, console)
    png = Path(args.png) if args.png else (Path(args.json).with_suffix(".png") if args.json
                                           else Path.cwd() / (Path(args.agents[0]).stem + ".eval.png"))
    plot_report(reports, png)
    console.print(f"wrote {png}")
    if args.json:
        Path(args.json).write_text(json.dumps(reports if len(reports) > 1 else reports[0], indent=1))
    return 0
