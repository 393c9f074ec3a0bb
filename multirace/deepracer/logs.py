"""DeepRacer's log files, as DeepRacer-for-Cloud writes them, so its log-analysis tools read ours.

A training folder (what deepracer-utils' ``DeepRacerLog(folder)`` reads as a
DeepRacer-for-Cloud model, single worker)::

    FOLDER/model/model_metadata.json          the agent's action space, sensor, network
    FOLDER/ip/hyperparameters.json            DeepRacer's hyperparameter names
    FOLDER/training-simtrace/N-iteration.csv  one sim-trace per training iteration
    FOLDER/metrics/TrainingMetrics.json       one entry per episode (reward, progress, status)

`TrainingLog` writes it from a training loop (see its docstring). Evaluation
metrics (DeepRacer's ``metrics/evaluation/evaluation-*.json``: one entry per
trial, i.e. per lap) come from sim-trace rows (`evaluation_metrics`), or from a
race as it runs (`EvaluationMetricsRecorder`).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from ..atomic import write_text
from ..environment.actions import ActionSpace
from ..recording.simtrace import SimTraceStep, SimTraceWriter, episode_status, read_simtrace, simtrace_row

STATUS_LABELS = {  # sim-trace episode_status -> the label in DeepRacer's metrics files
    "prepare": "Prepare", "in_progress": "In progress", "off_track": "Off track", "crashed": "Crashed",
    "reversed": "Reversed", "immobilized": "Immobilized", "lap_complete": "Lap complete", "time_up": "Time up",
    "pause": "Pause", "park": "Park",
}
DEFAULT_HYPERPARAMETERS = {  # DeepRacer-for-Cloud's defaults (defaults/hyperparameters.json)
    "batch_size": 64, "beta_entropy": 0.01, "discount_factor": 0.99, "e_greedy_value": 0.05,
    "epsilon_steps": 10000, "exploration_type": "categorical", "loss_type": "huber", "lr": 0.0003,
    "num_episodes_between_training": 20, "num_epochs": 5, "stack_size": 1, "term_cond_avg_score": 350.0,
    "term_cond_max_episodes": 1000, "sac_alpha": 0.2,
}


def _write_json(path: Path, data) -> Path:
    return write_text(path, json.dumps(data, indent=4))


def evaluation_metrics(rows: list[dict], episode: int = 0) -> dict:
    """DeepRacer's evaluation metrics (``{"metrics": [trial, ...]}``) of one car's sim-trace rows.

    Every lap is a trial; a last, unfinished lap is a trial too, ending with the run's last status.
    Times are simulated milliseconds from the start.
    """
    rows = [r for r in rows if int(r["episode"]) == episode]
    trials, counts, start = [], None, None
    for k, row in enumerate(rows):
        if counts is None:
            counts = {"off_track": 0, "crashed": 0, "reversed": 0, "immobilized": 0}
            start = float(row["tstamp"]) - 1.0 / 15 if not trials else float(rows[k - 1]["tstamp"])
        status = row["episode_status"]
        if status in counts:
            counts[status] += 1
        last = k == len(rows) - 1
        if status == "lap_complete" or last:
            end = float(row["tstamp"])
            trials.append({
                "trial": len(trials) + 1,
                "completion_percentage": 100 if status == "lap_complete" else int(float(row["progress"])),
                "episode_status": STATUS_LABELS.get(status, "In progress"),
                "start_time": int(round(start * 1000)),
                "metric_time": int(round(end * 1000)),
                "elapsed_time_in_milliseconds": int(round((end - start) * 1000)),
                "off_track_count": counts["off_track"],
                "crash_count": counts["crashed"],
                "reversed_count": counts["reversed"],
                "immobilized_count": counts["immobilized"],
                "reset_count": sum(counts.values()),
            })
            counts = None
    return {"metrics": trials}


def write_evaluation_metrics(path, simtrace, episode: int = 0) -> Path:
    """Write the evaluation metrics JSON of one car (`episode`) of a sim-trace (a CSV path or its rows)."""
    rows = read_simtrace(simtrace) if isinstance(simtrace, (str, Path)) else simtrace
    return _write_json(Path(path), evaluation_metrics(rows, episode))


class EvaluationMetricsRecorder:
    """Race recorder writing DeepRacer's evaluation metrics JSON of one car (default car_0) at the end."""

    def __init__(self, path, car: int = 0):
        self.path, self.car = Path(path), int(car)
        self.rows: list[dict] = []

    def start(self, env) -> None:
        self.rows = []
        self._ended = False

    def step(self, env, observations, rewards, infos) -> None:
        agent = env.possible_agents[self.car]
        if self._ended or agent not in infos:
            return
        values = simtrace_row(infos[agent], episode=0, reward=0.0)
        self.rows.append({"episode": 0, "progress": values[11], "tstamp": values[14], "episode_status": values[15]})
        self._ended = not env.races[self.car].racing

    def finish(self, env, result) -> None:
        write_evaluation_metrics(self.path, self.rows)


class TrainingLog:
    """A DeepRacer-for-Cloud style training folder, written as training runs (see the module docstring).

    A training loop calls::

        log = TrainingLog(folder, model_metadata, hyperparameters)
        log.start_iteration(0)
        log.write_step(info, reward=r, episode=e, action=a)   # every car with an info, every step
        ...                                                    # (episode: a number unique in the run)
        log.start_iteration(1) ...
        log.close()

    `action` is what the policy gave the env (a discrete index, or [steer, speed]); the row holds
    the commanded steer and throttle, and the index for a discrete space. When a car's episode ends
    (`done`, default: the info's status is not racing) its TrainingMetrics entry is added; the metrics
    file is written at every new iteration and at `close`.
    """

    def __init__(self, folder, metadata: dict, hyperparameters: dict | None = None):
        self.folder = Path(folder)
        self.space = ActionSpace(metadata, "model_metadata")
        _write_json(self.folder / "model" / "model_metadata.json", metadata)
        _write_json(self.folder / "ip" / "hyperparameters.json", {**DEFAULT_HYPERPARAMETERS, **(hyperparameters or {})})
        self.metrics: list[dict] = []
        self.writer: SimTraceWriter | None = None
        self.iteration = None
        self._episodes: dict = {}  # episode -> [reward sum, first tstamp, wall clock start ms]
        self._trials = 0

    def start_iteration(self, iteration: int) -> None:
        """Begin `training-simtrace/{iteration}-iteration.csv` (closing the previous one, whose ended episodes
        go into the metrics file: rewriting it at every episode's end would cost a run quadratic time)."""
        if self.writer is not None:
            self.writer.close()
            self.write_metrics()
        self.iteration = int(iteration)
        self._trials = 0
        self.writer = SimTraceWriter(self.folder / "training-simtrace" / f"{self.iteration}-iteration.csv")

    def write_step(self, info: dict, *, reward: float, episode: int, action, done: bool | None = None) -> None:
        """Log one step of one car (see the class docstring)."""
        self._check_started()
        command = self.space.command(action)
        index = int(action) if self.space.discrete else None
        if done is None:
            done = info.get("status", "racing") != "racing"
        self.writer.write_step(info, reward=reward, episode=episode, action=index, done=done, command=command)
        self._count(episode, float(info["sim_time"]), reward)
        if done:
            self._episode_ended(episode, float(info["sim_time"]), episode_status(info), float(info["progress"]))

    def write_text(self, step: SimTraceStep, *, reward: float, episode: int, done: bool) -> None:
        """Log one step of one car whose row was formatted where it ran (`recording.simtrace.CarSimTrace`): the
        same file as `write_step` gives, with less work here."""
        self._check_started()
        self.writer.write_text(episode, step.text)
        self._count(episode, step.sim_time, reward)
        if done:
            self._episode_ended(episode, step.sim_time, step.status, step.progress)

    def _check_started(self) -> None:
        if self.writer is None:
            raise RuntimeError("TrainingLog.write_step before start_iteration")

    def _count(self, episode: int, sim_time: float, reward: float) -> None:
        """Add a step's reward to its episode (started at this step's time if it is the episode's first)."""
        state = self._episodes.setdefault(episode, [0.0, sim_time - 1.0 / 15, time.time() * 1000])
        state[0] += float(reward)

    def _episode_ended(self, episode: int, sim_time: float, status: str, progress: float) -> None:
        total, first, wall = self._episodes.pop(episode)
        self._trials += 1
        elapsed = int(round((sim_time - first) * 1000))
        self.metrics.append({
            "reward_score": int(round(total)),
            "metric_time": int(round(wall)) + elapsed,
            "start_time": int(round(wall)),
            "elapsed_time_in_milliseconds": elapsed,
            "episode": len(self.metrics) + 1,
            "trial": self._trials,
            "phase": "training",
            "completion_percentage": 100 if status == "lap_complete" else int(progress),
            "episode_status": STATUS_LABELS.get(status, "In progress"),
        })

    def write_metrics(self) -> Path:
        """(Re)write metrics/TrainingMetrics.json with the episodes ended so far."""
        return _write_json(self.folder / "metrics" / "TrainingMetrics.json",
                           {"metrics": self.metrics, "version": "2", "best_model_metric": "progress"})

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.write_metrics()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
