"""Learning by cheating, both stages in one run (`multirace train --set privileged=true`).

1. `teacher.train_teacher`: PPO of a state policy on the privileged state, from the run's reward, for
   the first ``1 - distill_share`` of the budget (the best-evaluated teacher is kept);
2. `imitate.run_dagger` with that teacher as the expert: the camera policy (the student, a CNN that
   sees only what the agent file's sensors give it) drives, and every image it meets is labelled with
   the teacher's command there, for the rest of the budget.

Both stages learn from the reward through the teacher: no scripted driver labels anything. Writes
`out` (the camera agent file), `out.teacher.pt` (the teacher) and `out.train.json` (both stages'
figures, evaluations and wall times, and the racing line's reference lap for scale).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from .config import TrainConfig
from .imitate import ImitationConfig, run_dagger
from .run import evaluate_time_trial
from .teacher import train_teacher


def student_config(config: TrainConfig, out, teacher_path, minutes: float, command: str | None) -> ImitationConfig:
    """The DAgger settings of the camera student: the run's tracks, directions, action space and sensors."""
    if config.reverse == "yes":
        raise ValueError("--reverse yes: the privileged run trains a direction set of 'no' or 'both'")
    return ImitationConfig(out=str(out), tracks=tuple(config.tracks), both_directions=config.reverse == "both",
                           minutes=minutes, seed=config.seed, network=config.student_network,
                           action_space=config.action_space, teacher=str(teacher_path), randomize=config.randomize,
                           procedural_tracks=config.procedural_tracks, camera=tuple(config.camera),
                           sensor=tuple(config.sensors().names), progress=config.progress, command=command)


def train_privileged(config: TrainConfig, out, command: str | None = None, log=print) -> dict:
    """Run both stages within `config.minutes`; returns the summary written to `out.train.json`."""
    from .evaluate import reference_lap

    started = time.perf_counter()
    out = Path(out)
    teacher_path = out.with_name(out.stem + ".teacher.pt")
    budget = 60.0 * float(config.minutes)
    teacher = train_teacher(config, teacher_path, budget * (1.0 - config.distill_share), log=log)
    log(f"wrote {teacher_path}: {teacher['agent_steps']} agent-steps in {teacher['wall_seconds']} s (sampling "
        f"{teacher['sample_seconds']:.0f} s, updates {teacher['update_seconds']:.0f} s)")
    remaining = max(30.0, budget - (time.perf_counter() - started))
    student = run_dagger(student_config(config, out, teacher_path, remaining / 60.0, command))
    track = config.eval_track or str(config.tracks[0])
    car = evaluate_time_trial(out, track, config.eval_laps)
    reference = reference_lap(track)
    student_eval = {key: car[key] for key in ("laps", "resets", "total_time", "best_lap", "status")}
    summary = {"out": str(out), "teacher_file": str(teacher_path), "track": track, "racing_line_lap": reference,
               "wall_seconds": round(time.perf_counter() - started, 1),
               "teacher": {**{k: v for k, v in teacher.items()}, "ratio": _ratio(teacher["selected"], reference)},
               "student": {**{k: v for k, v in student.items() if k != "history"}, "evaluation": student_eval,
                           "ratio": _ratio(student_eval, reference)},
               "config": config.to_dict()}
    out.with_suffix(".train.json").write_text(json.dumps(summary, indent=1))
    return summary


def _ratio(evaluation: dict, reference) -> float | None:
    """Best lap over the racing line's, for a run with every lap and no off-track (else None)."""
    if not evaluation.get("best_lap") or not reference or evaluation.get("resets"):
        return None
    return round(evaluation["best_lap"] / reference, 3)
