"""DAgger imitation of a scripted driver, from the camera: a first real agent in minutes on a CPU.

The expert is a scripted bot (`environment.bots`): by default the ``pass``
driver (`bots.passing_line` steering by `bots.PurePursuit`), which keeps the
centre line and goes wide round slower cars when there are any
(``traffic``); ``expert="racingline@0.9"`` makes it the racing-line driver at
0.9 of its speed profile, the teacher of fast racers. Either reads the car's
true pose, the track and the other cars (privileged state). The learner is a camera CNN
(`nets.py`) that sees only the front camera image. DAgger (Ross et al., 2011)
lets the learner drive so it visits its own mistakes, and asks the expert what
it should have done there:

1. roll out every env (several tracks, both directions, one car each) with the
   mixed policy "expert with probability beta, else the learner" (beta = 1 on
   the first iteration, then ``beta_decay ** i``);
2. label every visited camera image with the expert's command, mapped to the
   nearest action of the agent's action space (`ActionSpace.nearest`);
3. aggregate into one dataset (capped: beyond ``max_samples`` new samples
   replace random old ones) and train the CNN with cross-entropy (discrete) or
   a Gaussian negative log-likelihood (continuous);
4. repeat until the time budget is spent, then write an agent file.

Cars race a time trial with unlimited resets, so a learner that leaves the
track is put back by the rules (with the usual penalty) and DAgger goes on;
the env adds DeepRacer's steering and speed noise to every command. With
``traffic`` (bot specs such as ``follow@1.0``), every env also has those
bots, started at random gaps ahead of the learner each episode, so the
dataset holds passes: the learner sees the cars in its camera and the
expert's labels steer round them. ``sensor`` is DeepRacer's sensor list the
learner reads (``STEREO_CAMERAS``, ``SECTOR_LIDAR``...; see `sensors.suite`).
With ``lidar`` (its shorthand) the learner also reads
DeepRacer's LIDAR (`lidar`), which sees the cars alongside and right ahead
that the camera cannot. ``randomize`` (a preset name or dict, as the env's)
randomises perception and dynamics per episode, and ``procedural_tracks`` adds
seeded generated tracks (`sim.trackgen`) to the named ones. ``init`` starts the
learner from an agent file (a camera agent can start a LIDAR learner: its
LIDAR inputs start at zero weight), so a second stage can add traffic.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..environment.actions import load_action_space
from ..racing.agentfile import make_metadata, save_agent
from ..environment.bots import Bot, parse_bot
from ..environment.drivers import Driver
from ..environment.race_env import parallel_env
from ..environment.rewards import NO_REWARD
from ..racing.nets import DEFAULT_NETWORK, build_net
from ..sensors.camera import image_shape_of
from .experts import TEACHER_PREFIX, expert_command
from .experts import make_expert as make_driver
from .threads import default_threads
from .warmstart import init_lineage, init_settings, load_init_agent

DEFAULT_TRACKS = ("reinvent_base", "reInvent2019_track", "Oval_track", "Bowtie_track")


@dataclasses.dataclass
class ImitationConfig:
    """What to train and for how long (see the module docstring)."""

    out: str = "agent.pt"
    tracks: tuple = DEFAULT_TRACKS
    both_directions: bool = True  # each track forwards and in reverse
    minutes: float = 4.0  # wall-clock budget (rollouts + training), the file is written after it
    seed: int = 0
    network: str = DEFAULT_NETWORK
    action_space: object = None  # model_metadata path/dict; None = the 10 default actions (with init: its own)
    expert_speed: float = 1.0  # m/s the default `pass` expert drives (and so labels)
    expert: str | None = None  # a bot spec such as "racingline@0.9"; None = pass@expert_speed
    teacher: str | None = None  # a teacher file (`teacher.py`, an RL state policy): the expert drives as it does
    randomize: object = None  # the env's domain randomisation (None, "mild", "strong" or a dict), per episode
    procedural_tracks: int = 0  # seeded generated tracks added to `tracks` (each in both directions if asked)
    init: str | None = None  # start from this agent file's weights (its network, image size and action space)
    traffic: tuple = ()  # bots in the envs (e.g. ("follow@1.0", "lanes@1.0")), started ahead of the learner
    traffic_share: float = 1.0  # share of the envs that hold the traffic (the others: the car alone on the track)
    name: str | None = None  # agent name in the metadata (default: the file stem)
    camera: tuple = (120, 160)
    sensor: tuple = ("FRONT_FACING_CAMERA",)  # DeepRacer's sensor list the learner reads, e.g. ("STEREO_CAMERAS",)
    lidar: bool = False  # the learner also reads the 64-beam LIDAR (sensor FRONT_FACING_CAMERA + LIDAR)
    episode_steps: int = 900  # steps before an env is reset to the start grid (60 s at 15 Hz)
    rollout_steps: int = 1600  # samples gathered per DAgger iteration, over all envs
    train_steps: int = 250  # gradient steps per iteration
    batch_size: int = 64
    lr: float = 1e-3
    beta_decay: float = 0.5
    max_samples: int = 40000
    threads: int | None = None  # torch threads; None = all cores if the machine is idle, else 1
    progress: bool = True
    command: str | None = None  # the command line that ran this, recorded in the metadata


class Dataset:
    """Aggregated (observation, label) pairs with a size cap (random replacement when full).

    An observation is an image, or with `vector_inputs` ({key: size}: the sensors beside the camera) the
    env's {"camera", key, ...} dict. With `weight` (label -> a weight > 0) and/or `weighted` (each `add` gives
    its sample's own factor), batches draw each sample in proportion to its weight; without, uniformly.
    """

    def __init__(self, capacity: int, obs_shape, label_shape, label_dtype, rng: np.random.Generator,
                 vector_inputs: dict | None = None, obs_dtype=np.uint8, weight=None, weighted: bool = False):
        self.images = np.zeros((capacity, *obs_shape), obs_dtype)  # uint8 images, or int16 pooled ones
        self.vectors = {key: np.zeros((capacity, size), np.float32) for key, size in (vector_inputs or {}).items()}
        self.labels = np.zeros((capacity, *label_shape), label_dtype)
        self.size, self.capacity, self.seen, self.rng = 0, capacity, 0, rng
        self.weight = weight
        self.weighted = bool(weight) or weighted
        self.weights = np.zeros(capacity) if self.weighted else None

    def add(self, observation, label, factor: float = 1.0) -> None:
        """Keep a labelled observation (`factor`: its draw weight's factor, with `weighted`)."""
        if self.size < self.capacity:
            k = self.size
            self.size += 1
        else:
            k = int(self.rng.integers(self.capacity))
        self.images[k] = observation["camera"] if self.vectors else observation
        for key, values in self.vectors.items():
            values[k] = observation[key]
        self.labels[k] = label
        if self.weighted:
            self.weights[k] = (self.weight(label) if self.weight else 1.0) * factor
        self.seen += 1

    def batch(self, n: int):
        """(net input, labels) of `n` random samples."""
        if self.weighted:
            cumulative = np.cumsum(self.weights[:self.size])
            idx = np.minimum(np.searchsorted(cumulative, self.rng.random(n) * cumulative[-1], side="right"),
                             self.size - 1)
        else:
            idx = self.rng.integers(self.size, size=n)
        images = torch.from_numpy(self.images[idx])
        if not self.vectors:
            return images, torch.from_numpy(self.labels[idx])
        inputs = {"camera": images, **{key: torch.from_numpy(values[idx]) for key, values in self.vectors.items()}}
        return inputs, torch.from_numpy(self.labels[idx])


def stack_observations(observations: list):
    """One net input from per-car observations (images, or {"camera", key, ...} dicts)."""
    if isinstance(observations[0], dict):
        return {key: torch.from_numpy(np.stack([o[key] for o in observations])) for key in observations[0]}
    return torch.from_numpy(np.stack(observations))


def imitation_loss(space):
    """Loss(outputs, labels) for the action space: cross-entropy, or Gaussian NLL on scaled commands."""
    if space.discrete:
        ce = nn.CrossEntropyLoss()
        return lambda out, labels: ce(out, labels)
    low = torch.tensor(space.low, dtype=torch.float32)
    scale = torch.clamp((torch.tensor(space.high, dtype=torch.float32) - low) / 2, min=1e-3)

    def nll(out, labels):
        z = (labels - out[:, :2]) / scale
        log_std = torch.clamp(out[:, 2:] - torch.log(scale), -5.0, 2.0)
        return (log_std + 0.5 * z ** 2 * torch.exp(-2 * log_std)).sum(dim=1).mean()

    return nll


def fit_labels(net, optimiser, loss_fn, data: Dataset, steps: int, batch: int, stop=lambda: False,
               pooled: bool = False) -> float:
    """Up to `steps` gradient steps on random batches of the aggregated labels (after the first, `stop()` may end
    them early; `pooled`: the images are pooled, `nets.pool_image`); the mean loss."""
    net.train()
    losses = []
    for step in range(steps):
        if step and stop():
            break
        inputs, labels = data.batch(batch)
        loss = loss_fn(net(inputs, pooled=pooled), labels)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    return float(np.mean(losses))


def greedy_actions(space, out: torch.Tensor):
    """The learner's actions for a batch of outputs."""
    if space.discrete:
        return out.argmax(dim=1).tolist()
    return [row[:2].numpy() for row in out]


def with_traffic(k: int, share: float) -> bool:
    """Does env k hold the traffic, when `share` of the envs do? (A golden-ratio sequence spreads them over the
    runs, so neither direction nor any stretch of the track list is left out.)"""
    return (k * 0.6180339887498949) % 1.0 < share


def imitation_runs(config: ImitationConfig) -> list:
    """(track, reverse) pairs to drive: the named tracks and `procedural_tracks` generated ones, x directions."""
    from ..sim.trackgen import generate_track

    directions = (False, True) if config.both_directions else (False,)
    runs = [(t, r) for t in config.tracks for r in directions]
    for k in range(int(config.procedural_tracks)):
        runs += [(generate_track(seed=20_000 + 1000 * config.seed + k, reverse=r), r) for r in directions]
    if not runs:
        raise ValueError("tracks: need at least one track")
    return runs


def check_init_action_space(init_space, space, init_path) -> None:
    """Refuse an action space that an --init net's outputs do not fit: a continuous net's outputs are commands in
    degrees and m/s, so any continuous range fits it; a discrete net needs the same number of actions."""
    if init_space.discrete != space.discrete or (space.discrete and len(space.actions) != len(init_space.actions)):
        size = f"{len(init_space.actions)} actions" if init_space.discrete else "steering and speed"
        raise ValueError(f"--action-space: does not fit the net of --init {init_path} ({init_space.kind}, {size})")


def make_expert(config: ImitationConfig, space) -> Driver:
    """The driver whose commands label the images: a teacher file's state policy, or a scripted bot."""
    expert = make_driver(TEACHER_PREFIX + config.teacher if config.teacher else config.expert, config.expert_speed)
    if isinstance(expert, Bot) and expert.number_is_speed and not space.discrete \
            and not space.low[1] <= expert.speed <= space.high[1]:
        raise ValueError(f"expert speed {expert.speed} is outside the action space's speed range")
    return expert


def with_init_settings(config: ImitationConfig) -> ImitationConfig:
    """The config with the init file's network, image size, action space and sensors (the learner is that
    net); a new action space is accepted only where the init net's outputs still fit it."""
    if not config.init:
        return config
    settings = init_settings(config.init)
    action_space = settings["action_space"]
    if config.action_space is not None:
        action_space = config.action_space
        check_init_action_space(load_action_space(settings["action_space"]),
                                load_action_space(action_space), config.init)
    return dataclasses.replace(config, network=settings["network"], action_space=action_space,
                               camera=settings["camera"], sensor=settings.get("sensor", config.sensor))


class DaggerEnvs:
    """The DAgger runs' envs (one learner car each, traffic where the run has it) and their observations."""

    def __init__(self, config: ImitationConfig, space, rng):
        self.config, self.rng = config, rng
        self.bots = tuple(parse_bot(b).name for b in config.traffic)  # a clear error on a bad spec, first
        self.envs = [parallel_env(track=t, reverse=r, num_cars=1, race="time_trial", laps=1000,
                                  action_space=space, camera=tuple(config.camera), sensor=config.sensor,
                                  lidar=config.lidar, max_steps=config.episode_steps,
                                  bots=self.bots if with_traffic(k, config.traffic_share) else (),
                                  randomize=config.randomize, reward_function=NO_REWARD)  # DAgger reads no reward
                     for k, (t, r) in enumerate(imitation_runs(config))]
        self.episodes = [0] * len(self.envs)
        self.observations = [self.reset(k) for k in range(len(self.envs))]

    def reset(self, k: int):
        """Reset env k; traffic starts at random gaps ahead (up to half a lap), so passes come early."""
        env = self.envs[k]
        obs, _ = env.reset(seed=self.config.seed * 1000 + k + 100 * self.episodes[k])
        if env.bots:
            half = env.track.length / 2
            obs = env.move_cars({1 + b: (self.rng.uniform(1.5, half), 0.0) for b in range(len(self.bots))})
        return obs["car_0"]

    def step_all(self, learner_actions, expert, space, beta: float, data: Dataset) -> tuple[int, int]:
        """One step of every env under the mixed policy, every image labelled by the expert; returns the
        steps the learner drove and the resets it caused."""
        learner_steps = learner_resets = 0
        for k, env in enumerate(self.envs):
            label = space.nearest(*expert_command(expert, env))
            data.add(self.observations[k], label)
            use_learner = self.rng.random() >= beta
            resets_before = env.races[0].resets
            obs, _, terms, truncs, _ = env.step({"car_0": learner_actions[k] if use_learner else label})
            if use_learner:
                learner_steps += 1
                learner_resets += env.races[0].resets - resets_before
            if terms["car_0"] or truncs["car_0"]:
                self.episodes[k] += 1
                self.observations[k] = self.reset(k)
            else:
                self.observations[k] = obs["car_0"]
        return learner_steps, learner_resets

    def close(self):
        for env in self.envs:
            env.close()


def _progress_bar(config: ImitationConfig, budget: float):
    if not config.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=int(budget), unit="s", desc="dagger",
                bar_format="{desc} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} s {postfix}")


def _show_progress(progress, elapsed: float, row: dict) -> None:
    if progress is None:
        return
    off_rate = row["learner_resets_per_1000_steps"]
    progress.n = min(int(elapsed), progress.total)
    progress.set_postfix_str(f"iter {row['iteration'] + 1} beta {row['beta']:.2f} samples {row['samples']} "
                             f"loss {row['loss']:.3f} learner resets/1k steps "
                             + (f"{off_rate:.1f}" if off_rate is not None else "- (expert drove)"))
    progress.refresh()


def run_dagger(config: ImitationConfig) -> dict:
    """Train a camera agent by DAgger and write it to `config.out`; returns a summary dict."""
    started = time.perf_counter()
    budget = max(1.0, 60.0 * float(config.minutes))
    config = with_init_settings(config)
    torch.set_num_threads(int(config.threads or default_threads()))
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    space = load_action_space(config.action_space)
    expert = make_expert(config, space)
    runs = DaggerEnvs(config, space, rng)
    observation_space, sensors = runs.envs[0].observation_space("car_0"), runs.envs[0].sensors
    obs_shape = observation_space["camera"].shape if sensors.vectors else observation_space.shape
    image_shape = image_shape_of(obs_shape)  # (H, W, C), as the net and its metadata record it
    net = build_net(config.network, image_shape, space, vector_inputs=sensors.vector_inputs)
    if config.init:
        load_init_agent(config.init, net)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr)
    loss_fn = imitation_loss(space)
    label_shape, label_dtype = ((), np.int64) if space.discrete else ((2,), np.float32)
    data = Dataset(config.max_samples, obs_shape, label_shape, label_dtype, rng, sensors.vector_inputs)
    out_of_time = lambda: time.perf_counter() - started >= budget  # noqa: E731
    progress = _progress_bar(config, budget)
    history = []
    iteration, loss_value = 0, float("nan")
    try:
        while True:
            beta = config.beta_decay ** iteration
            learner_steps = learner_resets = 0
            net.eval()
            for step in range(max(1, math.ceil(config.rollout_steps / len(runs.envs)))):
                if step and out_of_time():
                    break  # out of time: train on what we have and finish
                with torch.no_grad():
                    learner = greedy_actions(space, net(stack_observations(runs.observations)))
                steps, resets = runs.step_all(learner, expert, space, beta, data)
                learner_steps, learner_resets = learner_steps + steps, learner_resets + resets
            loss_value = fit_labels(net, optimiser, loss_fn, data, config.train_steps, config.batch_size,
                                    stop=out_of_time)
            off_rate = round(1000.0 * learner_resets / learner_steps, 2) if learner_steps else None  # None: the
            history.append({"iteration": iteration, "beta": round(beta, 4), "samples": data.seen,  # expert drove
                            "loss": round(loss_value, 4), "learner_steps": learner_steps,
                            "learner_resets_per_1000_steps": off_rate})
            iteration += 1
            _show_progress(progress, time.perf_counter() - started, history[-1])
            if out_of_time():
                break
    finally:
        if progress is not None:
            progress.close()
        runs.close()
    training = _training_record(config, expert, runs.bots, iteration, data, loss_value,
                                time.perf_counter() - started)
    net.eval()
    out = Path(config.out)
    metadata = make_metadata(space, config.network, config.name or out.stem, image_shape, sensor=sensors.names,
                             training=training)
    save_agent(out, net, metadata)
    return {"out": str(out), **training, "history": history}


def _training_record(config: ImitationConfig, expert, bots, iterations: int, data: Dataset, loss_value: float,
                     wall: float) -> dict:
    """The agent file's `training` record of a DAgger run."""
    training = {
        "method": "dagger", "expert": expert.name, "traffic": list(bots),
        "traffic_share": config.traffic_share, "lidar": bool(config.lidar),
        "tracks": list(dict.fromkeys(str(t) for t in config.tracks)),
        "directions": ["forward", "reverse"] if config.both_directions else ["forward"],
        "procedural_tracks": int(config.procedural_tracks), "randomize": config.randomize, "seed": config.seed,
        "init": init_lineage(config.init) if config.init else None,
        "minutes": config.minutes, "iterations": iterations, "samples": data.seen,
        "dataset_size": data.size, "final_loss": round(loss_value, 4), "wall_seconds": round(wall, 1),
    }
    if config.command:
        training["command"] = config.command
    return training
