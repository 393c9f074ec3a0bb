"""Learning by cheating, both stages in one run (`multirace train --set privileged=true`).

1. `teacher.train_teacher`: PPO of a state policy on the privileged state, from the run's reward, for
   the first ``1 - distill_share`` of the budget (the best-evaluated teacher is kept);
2. DAgger of the camera policy (the student, a CNN that sees only what its agent file's sensors give
   it) with the teacher as its expert (`distill_student`): the envs run in worker processes as in PPO,
   every image a car meets is labelled there with the teacher's command for that car, the cars are
   driven by the teacher with probability beta (1, then halved every iteration) and by the student
   otherwise, and the student is trained on the aggregated labels.

Both stages learn from the reward through the teacher: no scripted driver labels anything. Writes
`out` (the camera agent file), `out.teacher.pt` (the teacher), `out.png` (the student's learning
curve) and `out.train.json` (both stages' figures, evaluations and wall times, and the racing line's
reference lap for scale).
"""
from __future__ import annotations

import concurrent.futures
import copy
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from ..environment.actions import load_action_space
from ..racing.blend import blend_weights
from ..racing.nets import build_net
from .config import TrainConfig
from .experts import TEACHER_PREFIX, make_expert
from .imitate import Dataset, fit_labels, greedy_actions, imitation_loss
from .ppo import decayed, init_continuous_head, input_pooling, make_vector_env, observation_shapes
from .rollout import Rollout, expert_actions, finished_episodes
from .run import TrainingRun
from .teacher import train_teacher
from ..racing.teacher_net import load_teacher
from .warmstart import init_lineage, init_settings, load_init_agent
from .threads import update_threads


def student_config(config: TrainConfig, teacher_path, seconds: float, init=None) -> TrainConfig:
    """The camera student's settings: the run's own, with the teacher as the labelling expert and the rest of
    the budget; with `init` (an agent file), that file's network, camera image, action space and sensors."""
    student = dataclasses.replace(config, privileged=False, network=config.student_network, minutes=seconds / 60.0,
                                  expert=f"{TEACHER_PREFIX}{teacher_path}" + (
                                      f"@{config.distill_speed_scale:g}" if config.distill_speed_scale != 1.0 else ""),
                                  expert_coef=1.0)
    if init:
        settings = init_settings(init)
        if load_action_space(settings["action_space"]).discrete:
            raise ValueError(f"--init {init}: a discrete-action agent; a teacher's student needs a continuous "
                             "action space")
        student = dataclasses.replace(student, **{**settings, "camera": tuple(settings["camera"])})
    return student


def distill_student(config: TrainConfig, out, command: str | None = None, log=print, init=None) -> dict:
    """DAgger of a camera net from `config.expert` (a teacher) in the vectorised envs, starting from the agent
    file `init` if given (else from scratch); writes the agent file (the best-evaluated student) and its curve
    and history like a PPO run; returns the run's summary."""
    if config.init_blend < 1 and not init:
        raise ValueError("--set init_blend: needs --init (the agent whose weights the student is blended with)")
    run = TrainingRun(config, out, command, log)
    run.method, run.notes = "dagger", {"expert": config.expert.replace(TEACHER_PREFIX, "teacher:"),
                                       "stage": "student of an RL teacher (learning by cheating)"}
    if config.distill_free_teacher:
        run.notes["free_road_expert"] = f"teacher:{config.distill_free_teacher}"
    if config.distill_ahead_speed is not None:
        run.notes["expert_ahead_speed"] = config.distill_ahead_speed  # m/s: the cars ahead as the teacher took them
        if config.distill_ahead_seen:
            run.notes["expert_ahead_seen"] = True  # ... only those the student's camera showed
    if init:
        run.lineage = init_lineage(init)
    if config.init_blend < 1:
        run.notes["init_blend"] = config.init_blend  # the share of the trained weights; the rest: the init agent's
    torch.set_num_threads(int(config.threads))
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    space = load_action_space(config.action_space)
    pool = input_pooling(config)  # the workers pool the images as the net's first layer would
    vec = make_vector_env(config, pool=pool)
    E, A, T = config.num_envs, config.cars_per_env, config.rollout_steps
    fitter = None  # the student's fit, once the net is built
    try:
        obs, infos = vec.reset(seeds=[config.seed * 100_000 + e for e in range(E)])
        obs_shape, image_shape, vectors = observation_shapes(obs, pool)
        obs_dtype = np.int16 if pool > 1 else np.uint8
        net = build_net(config.network, image_shape, space, vector_inputs=vectors)
        if init:
            load_init_agent(init, net)
        elif not space.discrete:
            init_continuous_head(net, space)
        optimiser = torch.optim.Adam(net.parameters(), lr=config.distill_lr)
        blend = config.init_blend < 1  # the student evaluated, kept and written mixes in the init agent's weights
        start = {key: value.clone() for key, value in net.state_dict().items()} if blend else None
        shipped = copy.deepcopy(net) if blend else net
        loss_fn = imitation_loss(space)
        label_shape, label_dtype = ((), np.int64) if space.discrete else ((2,), np.float32)
        data = Dataset(config.distill_samples, obs_shape, label_shape, label_dtype, rng, vectors, obs_dtype,
                       weight=steering_weight(space, config.distill_balance), weighted=config.distill_traffic > 0)
        view = Rollout(1, E * A, obs_shape, vectors, space, obs_dtype)  # only its net_input(): (E, A, ...) -> (N, ...)
        labels = expert_actions(infos, space.discrete).numpy()
        factors = traffic_factors(infos, config)
        fitter = StudentFit(net, optimiser, loss_fn, data, config, pool > 1)
        while run.keep_going(0):
            t0 = time.perf_counter()
            beta = 0.5 ** run.iteration
            rate = decayed(config.distill_lr, run.fraction()) if config.distill_anneal_lr else config.distill_lr
            fitter.begin(rate)  # with distill_overlap: on its thread, beside this rollout
            driver = fitter.driver
            driver.eval()
            episodes = []
            for _ in range(T):
                x = view.net_input(obs)
                known = labels >= 0 if space.discrete else ~np.isnan(labels).any(-1)
                for k in np.flatnonzero(known):
                    fitter.add({key: x[key][k] for key in x} if vectors else x[k], labels[k], factors[k])
                with torch.no_grad():
                    mine = np.asarray(greedy_actions(space, driver(x, pooled=pool > 1)))
                teacher_drives = (rng.random(E * A) < beta) & known
                actions = np.where(teacher_drives.reshape(-1, *([1] * (mine.ndim - 1))), labels, mine)
                obs, _, _, _, infos = vec.step(actions.reshape(E, A, *actions.shape[1:]))
                labels = expert_actions(infos, space.discrete).numpy()
                factors = traffic_factors(infos, config)
                episodes += finished_episodes(infos, np.ones((E, A), bool))
            run.agent_steps += T * E * A
            run.sample_time += time.perf_counter() - t0
            t1 = time.perf_counter()
            loss = fitter.finish(rate)
            if blend:
                blend_weights(shipped, start, net, config.init_blend)
            run.update_time += time.perf_counter() - t1
            run.iteration += 1
            run.record(episodes, {"expert_loss": round(loss, 4), "beta": round(beta, 4), "lr": rate}, 0.0, T * E * A,
                       time.perf_counter() - t0, {})
            if run.checkpoint_and_evaluate(shipped, optimiser, None, space, image_shape):
                break
    finally:
        run.stop_progress()
        vec.close()
        if fitter is not None:
            fitter.close()
    return run.finish(shipped, optimiser, None, space, image_shape)



def traffic_factors(infos, config: TrainConfig) -> np.ndarray:
    """Per car (flat, as the labels): 1 + `distill_traffic` where a car or box was less than
    `distill_traffic_gap` metres ahead of it (the situations whose labels the fit should draw more), else 1."""
    gaps = np.array([info.get("gap_ahead", np.inf) for env_infos in infos for info in env_infos])
    return np.where(gaps < config.distill_traffic_gap, 1.0 + config.distill_traffic, 1.0)


def steering_weight(space, balance: float):
    """Label -> 1 + `balance` x |its steering| / the space's widest steering: the student's fit then draws the
    rare hard-turn labels (hairpins) more often than the many straight ones; None (uniform draws) at 0."""
    if not balance:
        return None
    if space.discrete:
        steering = np.abs([steer for steer, _ in space.actions])
        per_action = 1.0 + balance * steering / max(steering.max(), 1e-9)
        return lambda label: per_action[int(label)]
    widest = max(abs(space.low[0]), abs(space.high[0]), 1e-9)
    return lambda label: 1.0 + balance * abs(float(label[0])) / widest


class StudentFit:
    """The student's fit on the aggregated labels after each rollout: at once (the workers wait), or with
    `distill_overlap` on a thread while the next rollout is gathered, driven by `driver`, a copy of the
    student that takes the new weights when the fit ends. The labels of a rollout join the dataset when its
    fit ends, so the fit reads a dataset nothing writes to."""

    def __init__(self, net, optimiser, loss_fn, data: Dataset, config: TrainConfig, pooled: bool):
        self.net, self.optimiser, self.loss_fn, self.data = net, optimiser, loss_fn, data
        self.steps, self.batch, self.pooled = config.distill_steps, config.distill_batch, pooled
        self.threads, self.update_threads = int(config.threads), config.update_threads
        self.overlap = bool(config.distill_overlap)
        self.driver = copy.deepcopy(net) if self.overlap else net
        self.pool = concurrent.futures.ThreadPoolExecutor(1) if self.overlap else None
        self.pending: list = []  # with overlap: (input, label) pairs of this rollout, added when the fit ends
        self.running = None  # with overlap: the fit on the thread (None before the first labels)

    def begin(self, rate: float) -> None:
        """With overlap: start the fit on the labels gathered so far (the rollout's labels go to `pending`)."""
        if self.overlap and self.data.size:
            self._set_rate(rate)
            torch.set_num_threads(1)  # one for the fit, the other core for the learner's sampling and the workers
            self.running = self.pool.submit(self._fit)

    def add(self, observation, label, factor: float = 1.0) -> None:
        """A labelled input of the rollout being gathered (`factor`: its draw weight's factor)."""
        if self.overlap:
            self.pending.append(({key: value.clone() for key, value in observation.items()}
                                 if isinstance(observation, dict) else observation.clone(), np.array(label), factor))
        else:
            self.data.add(observation, label, factor)

    def finish(self, rate: float) -> float:
        """The fit's mean loss: the overlapped one's (then the rollout's labels join the dataset and the driver
        takes the new weights), or a fit now on every label so far."""
        if not self.overlap:
            self._set_rate(rate)
            torch.set_num_threads(update_threads(self.update_threads))
            loss = self._fit()
            torch.set_num_threads(self.threads)
            return loss
        loss = self.running.result() if self.running is not None else None
        for observation, label, factor in self.pending:
            self.data.add(observation, label, factor)
        self.pending.clear()
        if self.running is None:  # the first rollout: nothing was fitted beside it, so fit now
            self._set_rate(rate)
            loss = self._fit()
        self.running = None
        self.driver.load_state_dict(self.net.state_dict())
        return loss

    def close(self) -> None:
        """Let the fit thread go (a fit still running ends on its own)."""
        if self.pool is not None:
            self.pool.shutdown(wait=False)

    def _set_rate(self, rate: float) -> None:
        for group in self.optimiser.param_groups:
            group["lr"] = rate

    def _fit(self) -> float:
        return fit_labels(self.net, self.optimiser, self.loss_fn, self.data, self.steps, self.batch,
                          pooled=self.pooled)


def train_privileged(config: TrainConfig, out, command: str | None = None, log=print, init=None,
                     teacher_file=None) -> dict:
    """Run both stages within `config.minutes`; returns the summary written to `out.train.json`.

    `init`: the camera student starts from this agent file (e.g. an imitation racer) instead of from
    scratch. `teacher_file`: a teacher trained before (`FILE.teacher.pt` of an earlier run): the first stage
    is skipped and the whole budget goes to the student."""
    from .evaluate import reference_lap

    started = time.perf_counter()
    out = Path(out)
    budget = 60.0 * float(config.minutes)
    if config.distill_free_teacher:  # refused before the teacher's stage, not in the student's workers
        try:
            make_expert(f"{TEACHER_PREFIX}{config.distill_free_teacher}", 1.0)
        except ValueError as exc:
            raise ValueError(f"--set distill_free_teacher: {exc}") from None
    if teacher_file:
        teacher_path = Path(teacher_file)
        teacher = earlier_teacher(teacher_path)
    else:
        teacher_path = out.with_name(out.stem + ".teacher.pt")
        teacher = train_teacher(config, teacher_path, budget * (1.0 - config.distill_share), log=log)
        log(f"wrote {teacher_path}: {teacher['agent_steps']} agent-steps in {teacher['wall_seconds']} s (sampling "
            f"{teacher['sample_seconds']:.0f} s, updates {teacher['update_seconds']:.0f} s)")
    remaining = max(30.0, budget - (time.perf_counter() - started))
    student = distill_student(student_config(config, teacher_path, remaining, init), out, command=command,
                              log=log, init=init)
    track = config.eval_track or str(config.tracks[0])
    reference = reference_lap(track)
    record = json.loads(out.with_suffix(".train.json").read_text())
    record["teacher"] = {**teacher, "file": str(teacher_path), "ratio": ratio(teacher["selected"], reference),
                         "milestones": milestones(teacher["evals"], reference)}
    record["summary"]["milestones"] = milestones(record["evals"], reference, offset=teacher["wall_seconds"])
    record["racing_line_lap"] = reference
    record["summary"]["wall_seconds_both_stages"] = round(time.perf_counter() - started, 1)
    out.with_suffix(".train.json").write_text(json.dumps(record, indent=1))
    selected = student.get("selected_eval") or {}
    return {"out": str(out), "teacher_file": str(teacher_path), "track": track, "racing_line_lap": reference,
            "wall_seconds": record["summary"]["wall_seconds_both_stages"], "teacher": record["teacher"],
            "student": {**{k: v for k, v in student.items() if k not in ("history", "evals")},
                        "evaluation": selected, "ratio": ratio(selected, reference),
                        "milestones": record["summary"]["milestones"]}}


def earlier_teacher(path: Path) -> dict:
    """The figures of a teacher an earlier run trained, read from its file: this run spends no time on it
    (its own training wall time stays as `trained_seconds`; its evaluations are not in the file)."""
    load_teacher(path)  # a ValueError naming the file if it is not a teacher
    training = dict(torch.load(path, map_location="cpu", weights_only=True).get("training") or {})
    return {**training, "trained_seconds": training.get("wall_seconds"), "wall_seconds": 0.0, "agent_steps": 0,
            "evals": [], "reused": str(path)}


def ratio(evaluation: dict, reference) -> float | None:
    """Best lap over the racing line's, for a run with every lap and no off-track (else None)."""
    if not evaluation.get("best_lap") or not reference or evaluation.get("resets"):
        return None
    return round(evaluation["best_lap"] / reference, 3)


def milestones(evals: list, reference, offset: float = 0.0) -> dict:
    """Seconds from the run's start (`offset` + an evaluation's elapsed) and agent-steps to the first clean
    evaluation (every lap, no off-track), and to the first clean one within 1.25x and 1.15x of `reference`."""
    found = {}
    for name, bound in (("clean", None), ("within_1.25x", 1.25), ("within_1.15x", 1.15)):
        for e in evals:
            r = ratio(e, reference)
            if e["laps"] >= e.get("target", 0) and r is not None and (bound is None or r <= bound):
                found[name] = {"seconds": round(offset + e["elapsed"], 1), "agent_steps": e["agent_steps"]}
                break
    return found
