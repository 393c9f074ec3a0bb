"""The bookkeeping of a training run, beside the PPO loop: clock and budget, resume and checkpoints,
periodic evaluations and the best policy so far, the history and progress bar, and the outputs.

A run writes `out` (the agent file), `out.png` (learning curve), `out.train.json` (history, evaluations)
and `out.ckpt/` (a resumable checkpoint and agent snapshots: latest, first_success, first_clean, final),
and with `deepracer_log` `out.deepracer/`, a DeepRacer-for-Cloud training folder (`DeepRacerFolder`).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from ..atomic import AtomicOutput, write_text
from ..deepracer.logs import TrainingLog
from ..racing.agentfile import make_metadata, net_sensors, save_agent
from .config import TrainConfig


class TrainingRun:
    """Everything about a run that is not learning: see the module docstring."""

    def __init__(self, config: TrainConfig, out, command: str | None = None, log=print):
        self.started = time.perf_counter()
        self.config, self.command, self.log = config, command, log
        self.out = Path(out)
        self.ckpt_dir = self.out.with_name(self.out.stem + ".ckpt")  # made at the first checkpoint or snapshot
        self.budget = 60.0 * float(config.minutes)
        self.agent_steps, self.iteration, self.spent = 0, 0, 0.0
        self.history: list = []
        self.evals: list = []
        self.lineage: dict | None = None  # what the policy started from (`warmstart.init_lineage`), if anything
        self.method = "ppo"  # how the weights learn, as the agent file's training notes name it
        self.notes: dict = {}  # more training notes for every agent file the run writes (e.g. the teacher)
        self.first_success = self.first_clean = None  # elapsed seconds at the first evaluation finishing every lap
        self.best = None  # (score, weights, evaluation) of the best evaluated policy so far
        self.sample_time = self.update_time = 0.0
        self.last_ckpt = self.last_eval = time.perf_counter()
        self.resumed = False
        self.progress = None
        if config.progress:
            from tqdm import tqdm

            self.progress = tqdm(total=int(self.budget), unit="s", desc="ppo", dynamic_ncols=True,
                                 bar_format="{desc} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} s {postfix}")

    # ------------------------------------------------------------ clock
    def elapsed(self) -> float:
        """Seconds of this process's part of the run."""
        return time.perf_counter() - self.started

    def fraction(self) -> float:
        """How much of the budget (time, or iterations if `max_iterations` ends the run first) is spent, 0-1."""
        spent = self.elapsed() / self.budget
        if self.config.max_iterations > 0:
            spent = max(spent, self.iteration / self.config.max_iterations)
        return min(1.0, spent)

    def keep_going(self, start_iteration: int) -> bool:
        """Another iteration? At least one per run, then until the time budget or `max_iterations` is spent."""
        if self.config.max_iterations > 0 and self.iteration >= self.config.max_iterations:
            return False
        return self.iteration == start_iteration or self.elapsed() < self.budget

    # ------------------------------------------------------- resume, checkpoints
    def load_checkpoint(self, path) -> dict | None:
        """A checkpoint to resume from (its network, action space, camera and sensor settings win)."""
        if not path:
            return None
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
        saved = json.loads(checkpoint["config"])
        for key in ("network", "action_space", "camera", "sensor", "lidar"):
            value = saved.get(key, getattr(self.config, key))  # older checkpoints lack "sensor" (and "lidar")
            setattr(self.config, key, tuple(value) if key == "camera" else value)
        return checkpoint

    def restore(self, checkpoint: dict | None, net, optimiser, reward_scale) -> None:
        """Continue a checkpoint's learning and history."""
        if checkpoint is None:
            return
        self.resumed = True
        net.load_state_dict(checkpoint["net"])
        optimiser.load_state_dict(checkpoint["optimiser"])
        self.agent_steps, self.iteration = int(checkpoint["agent_steps"]), int(checkpoint["iteration"])
        self.history, self.evals = json.loads(checkpoint["history"]), json.loads(checkpoint["evals"])
        self.spent = float(checkpoint["elapsed"])
        saved_scale = json.loads(checkpoint.get("reward_scale", "null"))
        if reward_scale is not None and saved_scale:
            reward_scale.load(saved_scale)
        for e in self.evals:
            if e["laps"] >= e["target"] and self.first_success is None:
                self.first_success = e["elapsed"]
            if e["laps"] >= e["target"] and e["resets"] == 0 and self.first_clean is None:
                self.first_clean = e["elapsed"]

    def save_checkpoint(self, net, optimiser, reward_scale) -> None:
        """Write the resumable checkpoint (atomically)."""
        with AtomicOutput(self.ckpt_dir / "checkpoint.pt") as tmp:
            torch.save({"net": net.state_dict(), "optimiser": optimiser.state_dict(),
                        "agent_steps": self.agent_steps,
                        "reward_scale": json.dumps(reward_scale.state() if reward_scale is not None else None),
                        "iteration": self.iteration, "history": json.dumps(self.history),
                        "evals": json.dumps(self.evals), "elapsed": self.spent + self.elapsed(),
                        "config": json.dumps(self.config.to_dict())}, tmp)

    def snapshot_agent(self, path, net, space, image_shape, note=None) -> Path:
        """An agent file of the current weights, with the run's training notes."""
        config = self.config
        training = {"method": self.method, "agent_steps": self.agent_steps, "iterations": self.iteration,
                    "tracks": [str(t) for t in config.tracks], "reverse": config.reverse, "seed": config.seed,
                    "wall_seconds": round(self.spent + self.elapsed(), 1), "reward": str(config.reward),
                    "robust": bool(config.robust)}
        if self.command:
            training["command"] = self.command
        if self.lineage:
            training["init"] = self.lineage
        training.update(self.notes)
        if note:
            training.update(note)
        net.eval()
        return save_agent_file(path, net, space, config, image_shape, training)

    def deepracer_folder(self, net, space, image_shape) -> DeepRacerFolder | None:
        """`out.deepracer/`, the run's DeepRacer-for-Cloud training folder (None without `deepracer_log`)."""
        if not self.config.deepracer_log:
            return None
        metadata = make_metadata(space, net.network, self.out.stem, image_shape, training_algorithm="clipped_ppo",
                                 sensor=net_sensors(net, self.config.sensors().camera).names)
        return DeepRacerFolder(self.out.with_name(self.out.stem + ".deepracer"), metadata, self.config)

    # ------------------------------------------------------------ history
    def record(self, episodes: list, stats: dict, env_reward: float, samples: int, iteration_seconds: float,
               extra: dict) -> dict:
        """One history row from the iteration's finished learner episodes and update statistics."""
        mine = [ep for ep in episodes if ep["learner"]]
        last = self.history[-1] if self.history else {}
        row = {"iteration": self.iteration, "agent_steps": self.agent_steps,
               "elapsed": round(self.spent + self.elapsed(), 1), "episodes": len(mine),
               "return": float(np.mean([ep["return"] for ep in mine])) if mine else last.get("return", 0.0),
               "laps_per_episode": (float(np.mean([ep["laps"] for ep in mine])) if mine
                                    else last.get("laps_per_episode", 0.0)),
               "lap_completion": (float(np.mean([ep["laps"] >= 1.0 for ep in mine])) if mine
                                  else last.get("lap_completion", 0.0)),
               "caused_per_lap": (float(sum(ep["caused"] for ep in mine) / max(sum(ep["laps"] for ep in mine), 0.25))
                                  if mine else 0.0),
               "mean_reward": env_reward, **stats,
               "steps_per_s": (round(self.agent_steps / max(self.spent + self.elapsed(), 1e-9), 1) if not self.spent
                               else round(samples / max(iteration_seconds, 1e-9), 1)), **extra}
        self.history.append(row)
        if self.progress is not None:
            self.progress.n = min(int(self.elapsed()), self.progress.total)
            last_eval = self.evals[-1] if self.evals else None
            training = (f"ret {row['return']:.1f} laps/ep {row['laps_per_episode']:.2f} episodes with a lap "
                        f"{100 * row['lap_completion']:.0f}%" if any(h["episodes"] for h in self.history)
                        else "no episode ended yet")
            self.progress.set_postfix_str(  # training episodes (exploring) beside the greedy evaluation
                f"it {self.iteration} {row['steps_per_s']:.0f} steps/s | training: {training}"
                + (f" | eval {last_eval['laps']}/{last_eval['target']} laps, {last_eval['resets']} resets"
                   if last_eval else ""))
            self.progress.refresh()
        return row

    # ------------------------------------------------------------ evaluations
    def checkpoint_and_evaluate(self, net, optimiser, reward_scale, space, image_shape) -> bool:
        """Checkpoint and evaluate when due; True when the run should stop (`stop_on_success`)."""
        config = self.config
        if time.perf_counter() - self.last_ckpt >= config.checkpoint_every:
            self.save_checkpoint(net, optimiser, reward_scale)
            self.last_ckpt = time.perf_counter()
        if not config.eval_every or time.perf_counter() - self.last_eval < config.eval_every:
            return False
        latest = self.snapshot_agent(self.ckpt_dir / "latest.pt", net, space, image_shape)
        car = evaluate_agent(latest, config)
        self.evals.append({"iteration": self.iteration, "agent_steps": self.agent_steps,
                           "elapsed": round(self.spent + self.elapsed(), 1), **car})
        score = eval_score(self.evals[-1])
        if self.best is None or score > self.best[0]:
            self.best = (score, {k: v.detach().clone() for k, v in net.state_dict().items()}, self.evals[-1])
        if car["laps"] >= car["target"] and self.first_success is None:
            self.first_success = self.evals[-1]["elapsed"]
            self.snapshot_agent(self.ckpt_dir / "first_success.pt", net, space, image_shape)
        if car["laps"] >= car["target"] and car["resets"] == 0 and self.first_clean is None:
            self.first_clean = self.evals[-1]["elapsed"]
            self.snapshot_agent(self.ckpt_dir / "first_clean.pt", net, space, image_shape)
        if self.log and not self.progress:
            self.log(f"eval: {car['laps']}/{car['target']} laps, {car['resets']} resets")
        self.last_eval = time.perf_counter()
        return bool(config.stop_on_success and self.first_clean is not None)

    # ------------------------------------------------------------ outputs
    def stop_progress(self) -> None:
        """Close the progress bar."""
        if self.progress is not None:
            self.progress.close()
            self.progress = None

    def finish(self, net, optimiser, reward_scale, space, image_shape) -> dict:
        """Write the agent file (the best evaluated policy, if it beats the final weights), the checkpoint,
        the learning curve and the history; return the run's summary."""
        config, wall = self.config, self.spent + self.elapsed()
        history = self.history
        summary = {"out": str(self.out), "iterations": self.iteration, "agent_steps": self.agent_steps,
                   "wall_seconds": round(wall, 1), "steps_per_s": round(self.agent_steps / max(wall, 1e-9), 1),
                   "sample_seconds": round(self.sample_time, 1), "update_seconds": round(self.update_time, 1),
                   "first_success_seconds": self.first_success, "first_clean_seconds": self.first_clean,
                   "final_return": history[-1]["return"] if history else None,
                   "final_laps_per_episode": history[-1]["laps_per_episode"] if history else None}
        self.save_checkpoint(net, optimiser, reward_scale)
        note = {"first_success_seconds": self.first_success, "first_clean_seconds": self.first_clean}
        if self.best is not None and config.keep_best:
            # the final weights get one last evaluation; the best evaluated policy is what we ship
            final = self.snapshot_agent(self.ckpt_dir / "final.pt", net, space, image_shape)
            final_eval = {**evaluate_agent(final, config), "iteration": self.iteration, "final": True}
            if self.best[0] > eval_score(final_eval):
                net.load_state_dict(self.best[1])
                note["selected"] = f"best evaluation (iteration {self.best[2]['iteration']})"
                summary["selected_eval"] = self.best[2]
            else:
                note["selected"] = "final weights"
                summary["selected_eval"] = final_eval
        self.snapshot_agent(self.out, net, space, image_shape, note)
        plot_history(history, self.evals, self.out.with_suffix(".png"))
        write_text(self.out.with_suffix(".train.json"), json.dumps(
            {"summary": summary, "config": config.to_dict(), "history": history, "evals": self.evals}, indent=1))
        summary["evals"] = self.evals
        summary["history"] = history
        return summary


def deepracer_hyperparameters(config: TrainConfig) -> dict:
    """The config's PPO settings under DeepRacer's hyperparameter names (the rest keep DeepRacer's defaults)."""
    return {"batch_size": config.minibatch_size, "num_epochs": config.epochs, "lr": config.lr,
            "discount_factor": config.gamma, "beta_entropy": config.ent_coef, "loss_type": "mean squared error"}


class DeepRacerFolder:
    """The DeepRacer-for-Cloud training folder of a PPO run (`deepracer.logs.TrainingLog`): one sim-trace
    row per learning car per step, one file per PPO iteration, episode numbers unique in the run."""

    def __init__(self, folder, metadata: dict, config: TrainConfig):
        self.log = TrainingLog(folder, metadata, deepracer_hyperparameters(config))
        cars = config.num_envs * config.cars_per_env
        self.episodes = np.arange(cars).reshape(config.num_envs, config.cars_per_env)  # each car's episode now
        self.next_episode = cars

    def start_iteration(self, iteration: int) -> None:
        self.log.start_iteration(iteration)

    def write_step(self, infos, rewards, learner_mask) -> None:
        """One step of every env: a row per learning car (`infos` from `TrainEnv` with `deepracer_log`, whose
        workers format the rows)."""
        for e, env_infos in enumerate(infos):
            for a, info in enumerate(env_infos):
                if learner_mask[e, a]:
                    self.log.write_text(info["deepracer"], reward=float(rewards[e, a]),
                                        episode=int(self.episodes[e, a]), done=bool(info["train_done"]))
                if info["train_done"]:
                    self.episodes[e, a], self.next_episode = self.next_episode, self.next_episode + 1

    def close(self) -> None:
        self.log.close()


def evaluation_runs(config: TrainConfig) -> list[tuple[str, bool]]:
    """The (track, reverse) runs of each evaluation: the evaluation track forward, then every `eval_tracks`
    entry in each of the run's directions."""
    first = (config.eval_track or str(config.tracks[0]), False)
    return [first] + [(str(t), r) for t in config.eval_tracks for r in config.directions() if (str(t), r) != first]


def combined_evaluation(rows: list[dict], laps: int) -> dict:
    """One evaluation row from the rows of `evaluation_runs`: laps, off-tracks and time summed (so the best
    policy is the one that completes and stays on the road most), the best lap and status of the first."""
    times = [r["total_time"] for r in rows]
    return {"laps": sum(r["laps"] for r in rows), "target": laps * len(rows),
            "resets": sum(r["resets"] for r in rows),
            "total_time": None if None in times else round(sum(times), 3), "best_lap": rows[0]["best_lap"],
            "status": rows[0]["status"], "reason": rows[0].get("reason"), "runs": len(rows)}


def evaluate_agent(agent_path, config: TrainConfig) -> dict:
    """The combined evaluation row of an agent file over `evaluation_runs` (time trials, or races against
    `eval_bots`)."""
    return combined_evaluation([evaluate_time_trial(agent_path, track, config.eval_laps, reverse=reverse,
                                                    bots=config.eval_bots, randomize=config.eval_randomize)
                                for track, reverse in evaluation_runs(config)], config.eval_laps)


def evaluate_time_trial(agent_path, track: str, laps: int = 3, seed: int = 0, reverse: bool = False,
                        bots=(), randomize=None) -> dict:
    """Race the agent file alone (as `multirace race FILE --format time_trial`, in the world `randomize`
    perturbs, see environment.randomize); its result row.

    With `bots`: a head-to-head race against them instead, in which each collision the agent caused
    counts like an off-track reset in the row's "resets" (so the best-policy choice avoids both).
    A generous step budget: the evaluation measures driving, not how busy the machine is.
    """
    from ..racing.agentfile import AgentController
    from ..racing.runner import RaceConfig, run_race

    if bots:
        from .evaluate import race_agent
        from .rivals import race_opponents

        row = race_agent(agent_path, track, reverse=reverse, laps=laps, seed=seed, bots=race_opponents(bots),
                         race="head_to_head", step_budget=5.0, randomize=randomize)
        return {**row, "resets": row["resets"] + row["collisions_caused"]}
    result = run_race([AgentController(agent_path, step_budget=5.0)],
                      RaceConfig(track=track, reverse=reverse, race="time_trial", laps=laps, seed=seed,
                                 randomize=randomize))
    return result["cars"][0]


def save_agent_file(path, net, space, config: TrainConfig, image_shape, training: dict) -> Path:
    """The agent file of a PPO net (its value head is not saved)."""
    name = Path(path).stem
    metadata = make_metadata(space, net.network, name, image_shape, training_algorithm="clipped_ppo",
                             sensor=net_sensors(net, config.sensors().camera).names, training=training)
    return save_agent(path, net, metadata)


def plot_history(history: list, evals: list, path) -> None:
    """Learning curve: episode return and laps per episode against agent-steps, evaluations marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    steps = [h["agent_steps"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    axes[0].plot(steps, [h["return"] for h in history], color="tab:blue")
    axes[0].set_ylabel("mean episode return")
    axes[1].plot(steps, [h["laps_per_episode"] for h in history], color="tab:green", label="laps per episode")
    for e in evals:  # evaluations: green = every lap with no off-track, orange = every lap, grey = not
        finished = e["laps"] >= e["target"]
        colour = ("tab:green" if not e["resets"] else "tab:orange") if finished else "0.75"
        axes[1].axvline(e["agent_steps"], color=colour, lw=1.0)
    axes[1].set_ylabel("laps per training episode")
    axes[1].set_title("evaluations: green clean 3/3, orange 3/3 with off-tracks, grey not", fontsize=8)
    for ax in axes:
        ax.set_xlabel("agent-steps")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with AtomicOutput(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def eval_score(e: dict) -> tuple:
    """Order of evaluations: more laps, then fewer off-tracks, then faster."""
    return (e["laps"], -e["resets"], -(e["total_time"] or 1e9))
