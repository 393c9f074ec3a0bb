"""Every hyperparameter of `multirace train`, in one dataclass, with presets.

`TrainConfig` holds all the knobs (each documented on its line). Presets:

- ``fast`` (the default): what reaches 3-of-3 laps of reinvent_base from the
  camera in minutes on a 2-core CPU: the small CNN, a progress reward, off-track
  ends the car's training episode, 2 worker processes x 4 cars, rollouts of
  2048 agent-steps, 3 epochs of minibatch 512, discount 0.99.
- ``deepracer``: the AWS DeepRacer console's PPO defaults: batch 64, lr 3e-4,
  entropy 0.01, discount 0.999, 10 epochs, clip 0.2, GAE lambda 0.95, its
  shallow CNN and its default (centre-line) reward.
- ``race``: head-to-head racing: trains in traffic (a ``follow`` and a
  ``lanes`` bot in every env, a quarter of the cars driven by the opponent
  pool, which holds the shipped imitation agents and past snapshots), with a
  penalty on every collision the car causes and a smaller one for closing in
  on the car ahead in its lane or passing it too close, DeepRacer's faster sample action
  space (1 and 2 m/s), and evaluations in traffic. Meant with
  ``--init agents/dagger_fast.pt`` (see multirace/train/README.md).
- ``tiny``: one worker, about a second per iteration, for tests and smoke runs
  (returns rise visibly on Oval_track within 45 s).
"""
from __future__ import annotations

import dataclasses
import json
import math

from ..environment.rewards import RewardWeights
from ..environment.state import STATE_VIEWS
from ..racing.nets import SHALLOW, TINY
from ..resources import agents_dir
from ..sensors.suite import SensorSuite, declared_sensors
from .threads import PRECISIONS
from .track_sampling import TRACK_SAMPLINGS

SHIPPED_AGENTS = agents_dir()


@dataclasses.dataclass
class TrainConfig(RewardWeights):
    """All training settings; see `PRESETS` for named bundles. The reward weights (`progress_weight`,
    `collision_penalty`, ...) are `RewardWeights`' fields, declared there once."""

    # ---- what to train on
    tracks: tuple = ("reinvent_base",)  # bundled track names or .npy paths; several = multi-track training
    reverse: str = "no"  # "no", "yes" or "both": the direction(s) each track is raced in
    track_sampling: str = "uniform"  # how each env episode picks its run (track, direction): "uniform", or "failures" (runs with more off-tracks per lap raced more often, train/track_sampling.py)
    procedural_tracks: int = 0  # seeded generated tracks (multirace.sim.trackgen) added to the track list
    action_space: object = None  # model_metadata.json path or dict; None = DeepRacer's 10 discrete actions
    reward: str = "progress"  # a named reward (NAMED_REWARDS: "progress", built-in shaped; "centre", DeepRacer default) or a reward .py file
    camera: tuple = (120, 160)  # camera (height, width), grayscale as DeepRacer
    network: str = TINY  # nets.NETWORKS name: MULTIRACE_TINY_CNN, MULTIRACE_SMALL_CNN or DEEP_CONVOLUTIONAL_NETWORK_SHALLOW
    sensor: tuple = ("FRONT_FACING_CAMERA",)  # DeepRacer's sensor list the cars read, e.g. ["STEREO_CAMERAS"] or ["FRONT_FACING_CAMERA", "SECTOR_LIDAR"] (see multirace.sensors.suite)
    lidar: bool = False  # shorthand: add DeepRacer's 64-beam LIDAR to `sensor` (FRONT_FACING_CAMERA + LIDAR): sees cars alongside and too close for the camera
    # ---- environments
    num_envs: int = 2  # worker processes (one env each); 2 uses both cores of this machine
    cars_per_env: int = 4  # learning cars per env, all driven by the shared policy (self-play)
    bots: tuple = ()  # scripted cars added to each env, e.g. ("follow@1.0",)
    rivals: tuple = ()  # agent files or shipped agents' names that drive cars beside the learners, e.g. ("racer", "dagger_fast") (train/rivals.py)
    rival_cars: int = 2  # with rivals: cars per env driven by them, each by one drawn at random at every race start
    bots_ahead: float = 0.0  # > 0: the bots start this many metres ahead of the learning cars (2 m apart), so every episode begins with cars to pass; 0: behind them on the grid
    bots_ahead_spread: float = 0.0  # with bots_ahead: each bot starts up to this many metres further ahead, drawn per episode, so the passes happen all round the lap
    episode_steps: int = 1500  # env steps before the env is reset to the start grid (100 s at 15 Hz)
    terminate_off_track: bool = True  # an off-track ends that car's training episode (value target 0)
    terminate_collision: bool = False  # a collision the car causes ends its training episode (like an off-track)
    randomize: object = None  # env domain randomisation: None, "mild", "strong" or a dict (see randomize.py)
    # ---- PPO
    rollout_steps: int = 256  # steps per env per iteration (batch = num_envs * cars_per_env * rollout_steps)
    minibatch_size: int = 512  # samples per gradient step (DeepRacer: batch_size 64)
    epochs: int = 3  # passes over each rollout (DeepRacer: num_epochs 10)
    lr: float = 3e-4  # Adam learning rate (DeepRacer: 3e-4)
    anneal_lr: bool = True  # linearly decay lr to 10% over the time budget
    gamma: float = 0.99  # discount (DeepRacer: 0.999)
    gae_lambda: float = 0.95  # GAE lambda (DeepRacer: 0.95)
    clip: float = 0.2  # PPO ratio clip (DeepRacer: 0.2)
    norm_reward: bool = False  # divide rewards by a running std of the discounted return, so value targets stay near 1 (matters when fine-tuning an --init policy: large value errors reshape the shared trunk)
    clip_value: bool = False  # clip the value loss too (CleanRL option)
    ent_coef: float = 0.01  # entropy bonus (DeepRacer: beta_entropy 0.01)
    vf_coef: float = 0.5  # value loss weight
    max_grad_norm: float = 0.5  # gradient norm clip
    bound_coef: float = 0.0  # weight of a loss on a continuous policy's mean beyond its action box (squared, in half-ranges past the edge): a mean past the edge commands the edge whatever it is, so none of its samples does less and nothing teaches it back (trd3's speed mean sat above the top speed in traffic: train README); 0: none
    target_kl: float | None = None  # stop an iteration's epochs early above this approximate KL
    norm_adv: bool = True  # normalise advantages per minibatch
    expert_coef: float = 0.0  # weight of an auxiliary imitation loss toward the expert's action (privileged state); 0 = pure RL
    expert: str = ""  # the expert of expert_coef as a bot spec (e.g. "racingline@0.9"); "" = bot:pass at the action space's top speed
    value_warmup: int = 0  # with --init: first iterations train only the (new) value head, policy frozen
    # ---- learning by cheating (multirace.train.teacher / distill)
    privileged: bool = False  # stage 1: PPO of a state policy (the teacher) on the privileged state, no camera; stage 2: DAgger of the camera policy from it
    distill_share: float = 0.7  # with privileged: share of `minutes` for stage 2 (the camera student)
    teacher_hidden: int = 128  # width of the teacher's two hidden layers (policy and value MLPs)
    teacher_lr: float = 3e-4  # the teacher's Adam learning rate
    teacher_epochs: int = 5  # the teacher's passes over each rollout
    teacher_minibatch: int = 512  # the teacher's samples per gradient step
    teacher_ent_coef: float = 0.0  # the teacher's entropy bonus; 0 lets its std collapse (trd3's speed std fell to 0.08 m/s, so no sample braked: train README)
    teacher_norm_reward: bool = True  # the teacher divides rewards by a running std of the return (as norm_reward)
    teacher_init: str = ""  # with privileged: the teacher starts from this teacher file's weights (an RL fine-tune, e.g. in traffic); "" = from nothing
    teacher_view: str = "all"  # with privileged: the traffic in the teacher's state, "all" (the cars near it) or "camera" (only those its front camera shows: what a camera student can learn to do; environment.state)
    student_network: str = TINY  # with privileged: the camera student's network (nets.NETWORKS)
    distill_lr: float = 1e-3  # with privileged: the student's Adam learning rate
    distill_anneal_lr: bool = False  # with privileged: the student's learning rate falls linearly over its budget to 10 % (as anneal_lr)
    distill_batch: int = 128  # with privileged: labelled images per gradient step of the student
    distill_steps: int = 40  # with privileged: gradient steps after each rollout (of rollout_steps x cars)
    distill_speed_scale: float = 0.8  # with privileged: the student's labels ask for this share of the teacher's speed (a margin for a camera that sees less than the teacher's state; at 1.0 and 0.9 students left the road at one corner a lap, train README)
    init_blend: float = 1.0  # with privileged and an --init agent: the student evaluated, kept and shipped is this share of the trained weights plus the rest of the init agent's (weight-space ensembling, WiSE-FT: Wortsman et al. 2022); 1.0: the trained weights alone
    distill_overlap: bool = False  # with privileged: the student's fit on the labels gathered so far runs on a thread while the workers gather the next rollout's (driven by the student from before that fit: one iteration stale); False: the workers wait for each fit
    distill_samples: int = 60000  # with privileged: labelled images kept (beyond: new ones replace random old ones)
    distill_traffic: float = 0.0  # with privileged: > 0: the student's fit draws a label with weight (1 + distill_traffic) x its other weight where a car or box was less than distill_traffic_gap metres ahead (braking and passing are rare among free laps); 0: no boost
    distill_traffic_gap: float = 2.0  # metres along the track: the reach of distill_traffic
    distill_free_teacher: str = ""  # with privileged: a second teacher file (e.g. a time-trial teacher; PATH@SCALE: at that share of its speed) whose labels the student learns where no car or box is within distill_free_ahead metres ahead or distill_free_behind behind it along the track; the run's teacher labels the rest (a traffic teacher keeps a margin on an empty road too); "" = the one teacher everywhere
    distill_ahead_speed: float | None = None  # with privileged: m/s; the run's teacher labels as if every car ahead of the student drove no faster than this (one camera frame shows where a car is, not how fast it goes: the labels are what is safe whatever it does; train README); None: at the speeds they drive
    distill_ahead_seen: bool = False  # with distill_ahead_speed: only the cars ahead that the student's front camera shows are taken that slow (a car hidden round a bend is labelled at its own speed: slowing for what the student cannot see teaches it to slow on a road that looks empty; train README)
    distill_free_ahead: float = 3.0  # metres along the track ahead of a car: a car or box nearer hands its labels to the run's teacher (with distill_free_teacher)
    distill_free_behind: float = 1.0  # metres behind: a car alongside or just passed keeps the run's teacher labelling (with distill_free_teacher)
    distill_balance: float = 0.0  # with privileged: > 0: the student's fit draws a label with weight 1 + distill_balance x |its steering| / the widest steering (hard turns are rare among straights: steering-balanced sampling, as end-to-end driving datasets do); 0: uniform draws
    # ---- budget, logging, outputs
    minutes: float = 10.0  # wall-clock budget, including evaluations and checkpoints
    max_iterations: int = 0  # > 0: stop after this many PPO iterations too (a budget machine load cannot change)
    seed: int = 0  # seeds torch, the envs and sampling
    threads: int = 1  # torch threads of the learner while sampling (the workers need the cores then)
    overlap_update: bool = False  # True: the PPO update of a rollout runs on a thread while the workers sample the next one, with the policy from before that update (one iteration stale, decoupled PPO); False: the workers wait for each update (learnt faster per agent-step and per minute on the busy machine, see the train README's Throughput)
    actors: bool = True  # each env worker drives its own cars with a copy of the policy for a whole rollout (train/actors.py; the weights shared at each rollout) and the learner only updates: no round trip per step; False (and always with the opponent pool or expert_coef): the learner infers for every car at every step
    worker_spin_wait: float | None = None  # seconds an env worker polls for its next step before it sleeps; None: 0 with overlap_update (the update thread wants the core), else `vector.SPIN_WAIT`
    pool_inputs: bool = True  # workers send camera images pooled as the net's first layer pools them (block sums): the same outputs, less to copy and compute (not with the opponent pool, whose agents read full images)
    update_precision: str = "auto"  # the PPO update's forward and backward passes: "bfloat16" (mixed precision: weights, optimiser and inference stay float32), "float32", or "auto": bfloat16 where the CPU computes it natively (train/threads.py)
    update_threads: int = 2  # torch threads of the PPO update (the workers wait then; 2 is ~1.25x faster here)
    checkpoint_every: float = 60.0  # seconds between checkpoints (and evaluations, see eval_every)
    eval_every: float = 30.0  # seconds between greedy time-trial evaluations (0 = never; one costs about 1 s)
    eval_track: str | None = None  # track of the evaluation (default: the first training track)
    eval_tracks: tuple = ()  # further tracks each evaluation races, in each of `reverse`'s directions (laps, off-tracks and time summed: the kept policy is the one clean on most of them)
    eval_laps: int = 3  # laps of the evaluation time trial
    eval_bots: tuple = ()  # bots (or agent files / shipped agents' names, as rivals) to race in the evaluation (head-to-head, collisions caused count like off-tracks)
    eval_randomize: object = None  # domain randomisation of every evaluation run (None: the clean world; "mild", "strong" or a dict, as `randomize`), its seed fixed, so the kept policy is judged as `multirace evaluate --randomize` judges agents
    keep_best: bool = True  # write the best-evaluated policy (laps, then off-tracks, then time) as the agent file
    stop_on_success: bool = False  # end training at the first evaluation that finishes every lap with no off-track
    progress: bool = True  # show a progress bar
    deepracer_log: bool = True  # write FILE.deepracer/, a DeepRacer-for-Cloud training folder: training-simtrace/N-iteration.csv (a row per learning car per step), model/model_metadata.json, ip/hyperparameters.json, metrics/TrainingMetrics.json (the ppo engine; the rllib engine writes none)
    # ---- robust options (multirace.train.selfplay / nature)
    robust: bool = False  # shorthand: curriculum randomisation, opponent pool, nature adversary, procedural tracks
    curriculum: bool = False  # ramp domain randomisation from none to `randomize` over the first half
    opponent_pool: bool = False  # some cars in each env are driven by past snapshots / shipped agents (PFSP)
    pool_fraction: float = 0.25  # share of cars driven by pool opponents when the pool is on
    snapshot_every: float = 90.0  # seconds between snapshots added to the opponent pool
    nature: bool = False  # adversarial per-episode perturbations from an uncertainty set (Zhang et al. 2020)
    nature_temperature: float = 1.0  # softmax temperature of nature's choice (lower = more adversarial)

    def __post_init__(self):
        self.sensors()  # an unknown sensor list is refused before anything starts
        if self.update_precision not in PRECISIONS:
            raise ValueError(f"--set update_precision: expected one of {', '.join(PRECISIONS)}, "
                             f"got {self.update_precision!r}")
        if self.teacher_view not in STATE_VIEWS:
            raise ValueError(f"--set teacher_view: expected one of {', '.join(STATE_VIEWS)}, got {self.teacher_view!r}")
        if self.track_sampling not in TRACK_SAMPLINGS:
            raise ValueError(f"--set track_sampling: expected one of {', '.join(TRACK_SAMPLINGS)}, "
                             f"got {self.track_sampling!r}")
        if self.distill_ahead_seen and self.distill_ahead_speed is None:
            raise ValueError("--set distill_ahead_seen: needs --set distill_ahead_speed (the speed the cars the "
                             "camera shows are taken to drive at)")

    def to_dict(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self), default=str))

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.cars_per_env * self.rollout_steps

    def sensors(self) -> SensorSuite:
        """The sensors the cars read: `sensor`, with the LIDAR that `lidar` adds."""
        return declared_sensors(self.sensor, self.lidar)

    def directions(self) -> tuple:
        if self.reverse not in ("no", "yes", "both"):
            raise ValueError(f"reverse: expected 'no', 'yes' or 'both', got {self.reverse!r}")
        return {"no": (False,), "yes": (True,), "both": (False, True)}[self.reverse]


PRESETS: dict[str, dict] = {
    "fast": {},
    # the PPO loop's fastest settings on 2 cores (issue 26 item 4): with the actors (the default), the update beside
    # the next rollout, 8 cars per worker (the same 2,048-sample batch); not the default until its learning is
    # checked as fast's was
    "throughput": {"overlap_update": True, "cars_per_env": 8, "rollout_steps": 128},
    "deepracer": {"anneal_lr": False, "minibatch_size": 64, "lr": 3e-4, "ent_coef": 0.01, "gamma": 0.999, "epochs": 10, "clip": 0.2,
                  "gae_lambda": 0.95, "network": SHALLOW, "reward": "centre"},
    "race": {"bots": ("follow@1.0", "lanes@1.0"), "opponent_pool": True, "collision_penalty": 20.0,
             "proximity_penalty": 1.0,
             "action_space": str(SHIPPED_AGENTS / "action_space_fast.json"), "eval_bots": ("follow@1.0", "lanes@1.0"),
             "value_warmup": 5},
    "tiny": {"num_envs": 1, "cars_per_env": 4, "rollout_steps": 128, "minibatch_size": 128, "epochs": 4,
             "lr": 1e-3, "gamma": 0.95, "anneal_lr": False, "episode_steps": 300, "eval_every": 0,
             "checkpoint_every": 1e9},
}


def make_config(preset: str = "fast", **overrides) -> TrainConfig:
    """A TrainConfig from a preset name plus field overrides (None values are ignored)."""
    if preset not in PRESETS:
        raise ValueError(f"--config: unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    values = dict(PRESETS[preset])
    for key, value in overrides.items():
        if key not in fields:
            raise ValueError(f"--set {key}: unknown training setting {key!r} (see `multirace train --list-settings`)")
        if value is not None:
            values[key] = checked_setting(fields[key], value)
    return TrainConfig(**values)


KINDS = {"int": int, "float": float, "bool": bool, "str": str, "tuple": tuple}
RANGES = {  # setting: (lowest, highest), inclusive; None: no bound
    "num_envs": (1, None), "cars_per_env": (1, 8), "rollout_steps": (1, None), "minibatch_size": (1, None),
    "epochs": (1, None), "episode_steps": (1, None), "eval_laps": (1, None), "threads": (1, None),
    "update_threads": (1, None), "procedural_tracks": (0, None), "max_iterations": (0, None), "seed": (0, 2**32 - 1),
    "value_warmup": (0, None), "minutes": (1e-6, None), "lr": (1e-12, None), "gamma": (0, 1), "gae_lambda": (0, 1),
    "clip": (1e-6, None), "pool_fraction": (0, 1), "checkpoint_every": (0, None), "eval_every": (0, None),
    "snapshot_every": (1e-6, None), "worker_spin_wait": (0, 1), "nature_temperature": (1e-6, None), "max_grad_norm": (1e-12, None),
    "distill_speed_scale": (0.1, 1.0), "init_blend": (0, 1), "distill_balance": (0, None), "distill_traffic": (0, None),
    "distill_traffic_gap": (0, None), "distill_ahead_speed": (0, None),
    "bound_coef": (0, None), "teacher_ent_coef": (0, None), "distill_free_ahead": (0, None), "distill_free_behind": (0, None),
}


def checked_setting(field: dataclasses.Field, value):
    """`value` for the setting `field`, if it is of the setting's kind (a whole number for an int, a number
    for a float, true/false for a bool, a list for a tuple) and in its range; else a ValueError naming it."""
    kind = KINDS.get(str(field.type).replace(" | None", ""))
    ok = {int: lambda v: isinstance(v, int) and not isinstance(v, bool),
          float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
          bool: lambda v: isinstance(v, bool), str: lambda v: isinstance(v, str),
          tuple: lambda v: isinstance(v, (list, tuple)), None: lambda v: True}[kind]
    if not ok(value):
        wanted = {int: "a whole number", float: "a number", bool: "true or false", str: "a string",
                  tuple: "a list"}[kind]
        raise ValueError(f"--set {field.name}: expected {wanted}, got {json.dumps(value)}")
    low, high = RANGES.get(field.name, (None, None))
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"--set {field.name}: must be from {low} to {high if high is not None else 'any'}, "
                         f"got {value}")
    return float(value) if kind is float else tuple(value) if kind is tuple else value


def describe() -> str:
    """Every setting with its default and one-line doc (for --help and the README)."""
    import inspect

    lines = []
    source = (inspect.getsource(TrainConfig) + inspect.getsource(RewardWeights)).splitlines()
    for f in dataclasses.fields(TrainConfig):
        doc = next((line.split("#", 1)[1].strip() for line in source
                    if line.strip().startswith(f"{f.name}:") and "#" in line), "")
        lines.append(f"{f.name} = {f.default!r}: {doc}")
    return "\n".join(lines)
