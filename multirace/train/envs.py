"""The training env: a `RaceEnv` per (track, direction), switched per episode, with training rewards.

`TrainEnv` runs inside a `vector.SubprocVectorEnv` worker. It looks like a
PettingZoo ParallelEnv to the worker (reset/step/possible_agents/close) and
adds what training needs on top of the race env:

- several tracks and directions: each env episode (reset) picks one of the
  `runs` at random (uniformly, or more often where its cars left the track
  more often: `track_sampling.RunSampler`); one `RaceEnv` per run is built
  lazily and kept;
- a named training reward (`rewards.NAMED_REWARDS`): the built-in
  ``"progress"`` (`rewards.progress_reward`: metres gained along the centre
  line per step in units of 1 m/s, plus a small centre-line bonus, minus a
  penalty on an off-track), computed here while the env computes none
  (`rewards.NO_REWARD`); or the env's DeepRacer reward function (``"centre"``
  or a ``.py`` file) unchanged; the weights are one `RewardWeights`;
- per-car training episodes: an off-track ends that car's episode (the race
  rules have already put it back on the centre line where it left, which is
  where its next episode starts), so there is no need to end the whole race;
- a penalty on every collision the car causes (the env's contact record
  names the striker of each new contact: the car that drove into the other
  or into a box; the car that was hit is not penalised);
- optionally, DeepRacer's usual object-avoidance shaping: a penalty growing
  as the car closes in on the next car or box ahead in its own lane, or runs
  alongside one with too little room to the side (from the params
  `closest_objects`, `objects_distance` and the lateral offsets), so it
  learns to pass wide or hold back before it collides, not only after;
- `time_limit` in the infos when only the env's step limit ended the car's
  episode (the learner bootstraps those from its value estimate, as the car
  could have driven on);
- optionally (`expert_labels`), the action an expert would take from each
  car's next observation, for the learner's auxiliary imitation loss
  (`expert_coef`): a scripted driver (by default ``pass``,
  `bots.passing_line`) or an RL teacher on the car's privileged state
  (``expert="teacher:PATH"``, `teacher.py`); with ``free_expert``, a second
  teacher labels the cars with no car or box near them (a time-trial
  teacher's pace on an open road, the traffic teacher's craft near cars);
  with ``expert_ahead_speed``, the traffic teacher labels as if the cars
  ahead drove no faster than that (`state.slowed_ahead`; with
  ``expert_ahead_seen``, only the cars ahead that the car's camera shows);
- per-car episode statistics in the infos (return, length, laps driven,
  collisions caused);
- optionally (`deepracer_log`), each car's sim-trace row, formatted here (in
  parallel, in the workers) for the learner's DeepRacer-for-Cloud training
  folder, which only writes it;
- optionally (`pool`), camera images pooled in the worker as the net's first
  layer would pool them (16x fewer bytes to copy, and the learner skips that
  layer);
- robust options read per episode from shared memory the learner writes:
  a domain-randomisation scale (curriculum) and nature's perturbation weights.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..environment.actions import Command
from ..environment.rewards import NAMED_REWARDS, RewardWeights
from ..recording.simtrace import CarSimTrace
from ..racing.entrant import TEACHER_PREFIX
from .experts import expert_commands, make_expert
from .track_sampling import RunSampler

BOT_SPACING = 2.0  # metres between bots started ahead of the learning cars (bots_ahead)
INFO_KEYS = ("train_done", "time_limit", "ep_return", "ep_length", "ep_laps", "ep_caused", "off_track", "collisions",
             "caused", "perturbation", "expert_action", "deepracer", "gap_ahead")


def env_settings(config) -> dict:
    """The `TrainEnv` keyword arguments a `TrainConfig` sets (everything but the runs, shared state and worker)."""
    return {"num_cars": config.cars_per_env, "bots": tuple(config.bots), "action_space": config.action_space,
            "reward": config.reward, "camera": tuple(config.camera), "sensor": config.sensors().names,
            "episode_steps": config.episode_steps,
            "terminate_off_track": bool(config.terminate_off_track), "randomize": config.randomize,
            "terminate_collision": config.terminate_collision, **dataclasses.asdict(RewardWeights.of(config)),
            "bots_ahead": config.bots_ahead, "bots_ahead_spread": config.bots_ahead_spread,
            "rivals": tuple(config.rivals), "rival_cars": config.rival_cars,
            "expert_labels": config.expert_coef > 0, "expert": config.expert, "deepracer_log": config.deepracer_log,
            "free_expert": f"{TEACHER_PREFIX}{config.distill_free_teacher}" if config.distill_free_teacher else "",
            "free_reach": (config.distill_free_ahead, config.distill_free_behind),
            "expert_ahead_speed": config.distill_ahead_speed, "expert_ahead_seen": config.distill_ahead_seen,
            "track_sampling": config.track_sampling}


class TrainEnv:
    """See the module docstring. All arguments are plain data so the env pickles to worker processes; the
    reward weights are `RewardWeights`' fields by name (`progress_weight=`, `collision_penalty=`, ...)."""

    def __init__(self, runs, num_cars=4, bots=(), action_space=None, reward="progress", camera=(120, 160),
                 sensor=None, episode_steps=1500, terminate_off_track=True, randomize=None, shared=None, worker=0,
                 terminate_collision=False, bots_ahead=0.0, bots_ahead_spread=0.0, expert_labels=False, expert="",
                 deepracer_log=False, observation="camera", pool=1, track_sampling="uniform", rivals=(), rival_cars=0,
                 state_view="all", free_expert="", free_reach=(3.0, 1.0), expert_ahead_speed=None,
                 expert_ahead_seen=False, **weights):
        self.runs = list(runs)  # [(track name/path or Track rows, reverse)]
        self.sampler = RunSampler(len(self.runs), track_sampling)  # which run each episode races on
        self.num_cars = int(num_cars)
        self.bots = tuple(bots)
        self.rivals = tuple(rivals)  # agent files / shipped agents' names driving `rival_cars` cars (`rivals.py`)
        self.rival_cars = int(rival_cars) if self.rivals else 0
        self._seats = None  # the rival seats (built on first use, in the worker, and shared by every run's env)
        self.action_space = action_space
        self.reward = reward
        self.named_reward = NAMED_REWARDS.get(reward)  # None: a reward file
        self.weights = RewardWeights(**{name: float(value) for name, value in weights.items()})
        self.camera = tuple(camera)
        self.sensor = sensor  # DeepRacer's sensor list (None: the single camera)
        self.episode_steps = int(episode_steps)
        self.terminate_off_track = bool(terminate_off_track)
        self.terminate_collision = bool(terminate_collision)
        self.bots_ahead = float(bots_ahead)
        self.bots_ahead_spread = float(bots_ahead_spread)
        self.expert_labels = bool(expert_labels)
        self.expert = str(expert or "")  # the labelling driver: a bot spec or "teacher:PATH"; "" = bot:pass at top speed
        self._expert = None  # that driver (built on first use)
        self.free_expert = str(free_expert or "")  # "teacher:PATH" labelling the cars with no traffic near; "": none
        self.free_reach = tuple(float(m) for m in free_reach)  # (ahead, behind): metres along the track that count as near
        self._free_expert = None
        # m/s: a teacher expert takes the cars ahead to drive no faster than this (None: as fast as they drive)
        self.expert_ahead_speed = None if expert_ahead_speed is None else float(expert_ahead_speed)
        self.expert_ahead_seen = bool(expert_ahead_seen)  # ... only the cars ahead that the car's camera shows
        self.deepracer_log = bool(deepracer_log)  # each step's info carries the car's sim-trace row, formatted here
        self._sim_traces: list[CarSimTrace] = []  # each car's sim-trace rows (new at every reset)
        self.observation = observation  # "camera" (the sensors) or "state" (privileged vectors, for RL teachers)
        self.state_view = state_view  # with "state": the traffic those vectors list ("all" or "camera")
        self.pool = int(pool)  # > 1: camera images go out as int16 sums of pool x pool pixel blocks (`nets.pool_image`)
        self.randomize = randomize
        self.shared = shared  # optional {"scale": mp.Value, "nature": mp.Array} written by the learner
        self.worker = int(worker)
        self.possible_agents = [f"car_{i}" for i in range(self.num_cars)]
        self.agents = list(self.possible_agents)
        self._envs: dict = {}
        self._reward = None  # the loaded reward file, shared by the envs
        self.env = None
        self._run = None  # the index of the run being raced, with its off-tracks and metres so far (all cars)
        self._run_off_tracks, self._run_metres = 0, 0.0
        self._rng = np.random.default_rng([worker, 7])
        self.perturbation = -1

    # -------------------------------------------------------------- envs
    def env_for(self, k: int):
        """The race env of run k (built on first use, then kept)."""
        if k not in self._envs:
            from ..environment.race_env import RaceEnv
            from ..sim.tracks import Track

            track, reverse = self.runs[k]
            if isinstance(track, np.ndarray):
                track = Track(track, name=f"generated_{k}", source="<trackgen>", reverse=reverse)
            reward = self._reward_file() if self.named_reward is None else self.named_reward.env_reward()
            self._envs[k] = RaceEnv(track=track, reverse=reverse, num_cars=self.num_cars, race="time_trial",
                                    laps=100000, bots=self.bots + self._rival_seats(), action_space=self.action_space,
                                    reward_function=reward, camera=self.camera, sensor=self.sensor,
                                    max_steps=self.episode_steps, observation=self.observation,
                                    state_view=self.state_view)
        return self._envs[k]

    def _rival_seats(self) -> tuple:
        """The rival cars' drivers (`rivals.RivalSeat`), their agents loaded once per worker."""
        if self._seats is None:
            from .rivals import RivalSeat

            self._seats = tuple(RivalSeat(self.rivals, np.random.default_rng([self.worker, 11, k]), f"rival_{k}")
                                for k in range(self.rival_cars))
        return self._seats

    def _reward_file(self):
        """The reward file, loaded once for every track this env switches between (it runs in one process)."""
        if self._reward is None:
            from ..environment.reward_process import load_reward_function

            self._reward = load_reward_function(self.reward)
        return self._reward

    def _episode_randomization(self):
        """This episode's randomisation: the configured one or nature's pick, scaled by the curriculum."""
        from ..environment.randomize import Randomization
        from .nature import scale_randomization

        self.perturbation = -1
        scale = float(self.shared["scale"].value) if self.shared is not None and "scale" in self.shared else 1.0
        use_nature = self.randomize is None or self._rng.random() < 0.5  # with a curriculum too: half the episodes
        if self.shared is not None and "nature" in self.shared and use_nature:
            from .nature import UNCERTAINTY_SET, sample_perturbation

            weights = np.frombuffer(self.shared["nature"].get_obj(), dtype=np.float64).copy()
            self.perturbation = sample_perturbation(weights, self._rng)
            base = Randomization.from_config(UNCERTAINTY_SET[self.perturbation][1])
        elif self.randomize is None:
            return Randomization.from_config(None)
        else:
            base = Randomization.from_config(self.randomize)
        return base if scale >= 1.0 else scale_randomization(base, scale)

    def reset(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng([int(seed), self.worker, 7])
        if self._run is not None:
            self.sampler.record(self._run, self._run_off_tracks, self._run_metres / self.track_length)
        k = self.sampler.pick(self._rng)
        self._run, self._run_off_tracks, self._run_metres = k, 0, 0.0
        self.env = self.env_for(k)
        self.env.randomization = self._episode_randomization()
        obs, infos = self.env.reset(seed=None if seed is None else int(seed))
        if self.bots_ahead > 0:  # every episode starts with slower cars to pass: bots on the centre line ahead
            bots = len(self.env.bots)  # the scripted bots, then the rivals
            extra = self._rng.uniform(0.0, self.bots_ahead_spread, bots)
            obs = self.env.move_cars({self.num_cars + b: (self.bots_ahead + BOT_SPACING * b + extra[b], 0.0)
                                      for b in range(bots)})
            infos = self.env.standing_infos()
        obs = self._pooled(obs)
        track = self.env.track
        self.track_length = track.length
        self._prev_s = [infos[a]["projection_distance"] for a in self.possible_agents]
        self._ep_return = [0.0] * self.num_cars
        self._ep_length = [0] * self.num_cars
        self._ep_dist = [0.0] * self.num_cars
        self._ep_caused = [0] * self.num_cars
        self._collisions_seen = [0] * self.num_cars
        self._sim_traces = [CarSimTrace() for _ in range(self.num_cars)]
        self.agents = list(self.possible_agents)
        small = {a: self._small(infos[a], False, None) for a in self.possible_agents}
        if self.expert_labels:
            for a, label in zip(self.possible_agents, self._expert_actions()):
                small[a]["expert_action"] = label
        return obs, small

    def _expert_actions(self, known: bool = True) -> list:
        """The expert's action for each car where it stands (`expert`, else the pass driver at the space's top
        speed; with `free_expert`, that teacher's for the cars with no car or box near them).

        With `known` False (the worker resets the env after this step, so the labels would not match
        the next observations) the labels are marked missing: -1, or NaNs for a continuous space.
        """
        env, space = self.env, self.env.actions
        if not known:
            return [-1 if space.discrete else [math.nan, math.nan]] * self.num_cars
        if self._expert is None:  # every run shares the action space, so one driver serves all
            top = max(a[1] for a in space.actions) if space.discrete else float(space.high[1])
            self._expert = make_expert(self.expert, top)
            self._free_expert = make_expert(self.free_expert, top) if self.free_expert else None
        cars = range(self.num_cars)
        free = [i for i in cars if self._free_expert is not None and not self._traffic_near(i)]
        busy = [i for i in cars if i not in free]
        commands = {}
        for expert, group, ahead_speed in ((self._expert, busy, self.expert_ahead_speed),
                                           (self._free_expert, free, None)):
            if group:
                commands.update(zip(group, expert_commands(expert, env, group, ahead_speed, self.expert_ahead_seen)))
        labels = [space.nearest(*commands[i]) for i in cars]
        return labels if space.discrete else [[float(v) for v in label] for label in labels]

    def _traffic_near(self, i: int) -> bool:
        """Whether another car or a box is within `free_reach` of car i along the track (ahead, behind), where
        they stand now."""
        env = self.env
        me = env.race_state.cars[i]
        if not me.located:
            return False
        ahead, behind = self.free_reach
        length = env.track.length
        gaps = [gap for gap, _, _ in env.traffic(i)] + [(s - me.s) % length for s in env.core.obstacle_points[:, 2]]
        return any(gap < ahead or gap > length - behind for gap in gaps)

    def _small(self, info, done, episode, caused=0, time_limit=False):
        small = {"train_done": done, "time_limit": time_limit, "off_track": bool(info.get("off_track", False)),
                 "collisions": len(info.get("collisions", ())), "caused": caused, "perturbation": self.perturbation,
                 "gap_ahead": self._gap_ahead(info)}
        if episode is not None:
            small.update(episode)
        return small

    def _new_collisions_caused(self, i: int) -> int:
        """Collisions car i caused since the last step (new contacts in which it was the striker)."""
        record = self.env.races[i].collisions
        new = record[self._collisions_seen[i]:]
        self._collisions_seen[i] = len(record)
        return sum(1 for c in new if c["caused"])

    def _gap_ahead(self, info) -> float:
        """Metres along the track from the car's reported point to the nearest car or box ahead (inf: none)."""
        along = info["objects_distance"]
        if not along:
            return math.inf
        return (along[info["closest_objects"][1]] - info["projection_distance"]) % self.env.track.length

    def _closing_in(self, info) -> float:
        """How close the car runs to the car or box next to it: 0 (clear) rising to 1 (touching).

        Two cases, the worse counts: closing in on the object ahead in its own lane (less than
        `proximity_side_room` between them sideways), 0 at `proximity_gap` metres and 1 at none; and running
        alongside the object just behind its reported point (still overlapping it lengthwise) with
        less than `proximity_side_room` to spare sideways, 1 when the sides touch.
        """
        along = info["objects_distance"]
        if not along:
            return 0.0
        spec = self.env.car_spec
        here = info["projection_distance"]
        behind, ahead = info["closest_objects"]

        own = info["distance_from_center"] * (1.0 if info["is_left_of_center"] else -1.0)

        def side_room(k: int) -> float:
            other = info["objects_distance_from_center"][k] * (1.0 if info["objects_left_of_center"][k] else -1.0)
            return abs(own - other) - spec.width

        cost = 0.0
        if side_room(ahead) < self.weights.proximity_side_room:
            gap = (along[ahead] - here) % self.track_length
            cost = max(0.0, 1.0 - gap / self.weights.proximity_gap)
        if (here - along[behind]) % self.track_length < spec.length:
            cost = max(cost, min(1.0, 1.0 - side_room(behind) / self.weights.proximity_side_room))
        return cost

    def _braking_needed(self, info, speed: float) -> float:
        """How hard the car must brake not to run into the object ahead in its lane (less than
        `proximity_side_room` between them sideways): the deceleration that brings its closing speed to 0 within
        the bumper-to-bumper gap, over its braking (`CarSpec.brake`), capped at 1; 0 when it is not closing in.
        `speed` is the car's own (actual) speed; the object's is its `objects_speed`."""
        along = info["objects_distance"]
        if not along:
            return 0.0
        spec = self.env.car_spec
        ahead = info["closest_objects"][1]
        own = info["distance_from_center"] * (1.0 if info["is_left_of_center"] else -1.0)
        other = info["objects_distance_from_center"][ahead] * (1.0 if info["objects_left_of_center"][ahead] else -1.0)
        closing = speed - info["objects_speed"][ahead]
        if closing <= 0.0 or abs(own - other) - spec.width >= self.weights.proximity_side_room:
            return 0.0
        gap = (along[ahead] - info["projection_distance"]) % self.track_length - spec.length
        if gap <= 0.0:
            return 1.0
        return min(1.0, closing * closing / (2.0 * gap) / spec.brake)

    def step(self, actions):
        env = self.env
        obs, rewards, terms, truncs, infos = env.step(actions)
        dt = env.dt
        out_rewards, out_infos = {}, {}
        truncated = all(truncs.values()) or all(terms.values())
        trainer = self.named_reward.trainer if self.named_reward is not None else None  # None: the env's reward
        labels = self._expert_actions(known=not truncated) if self.expert_labels else None
        for i, agent in enumerate(self.possible_agents):
            info = infos[agent]
            off = bool(info["off_track"])
            s = info["projection_distance"]
            ds = 0.0 if self._prev_s[i] is None else env.track.wrap_ds(s - self._prev_s[i])
            self._prev_s[i] = None if off else s
            r = trainer(info, ds, dt, self.weights) if trainer is not None else float(rewards[agent])
            caused = self._new_collisions_caused(i)
            r -= self.weights.collision_penalty * caused
            if self.weights.proximity_penalty and not off:
                r -= self.weights.proximity_penalty * self._closing_in(info)
            if self.weights.braking_penalty and not off:
                r -= self.weights.braking_penalty * self._braking_needed(info, env.race_state.cars[i].speed)
            self._ep_caused[i] += caused
            self._ep_return[i] += r
            self._ep_length[i] += 1
            self._ep_dist[i] += ds
            self._run_off_tracks += off
            self._run_metres += ds
            terminal = (off and self.terminate_off_track) or bool(caused and self.terminate_collision)
            done = terminal or truncated
            episode = None
            if done:
                episode = {"ep_return": self._ep_return[i], "ep_length": self._ep_length[i],
                           "ep_laps": self._ep_dist[i] / self.track_length, "ep_caused": self._ep_caused[i]}
                self._ep_return[i], self._ep_length[i], self._ep_dist[i], self._ep_caused[i] = 0.0, 0, 0.0, 0
            out_rewards[agent] = r
            out_infos[agent] = self._small(info, done, episode, caused, time_limit=truncated and not terminal)
            if self.expert_labels:
                out_infos[agent]["expert_action"] = labels[i]
            if self.deepracer_log:
                out_infos[agent]["deepracer"] = self._simtrace_step(i, info, float(np.float32(r)), done, actions[agent])
        if truncated:
            self.agents = []
        return self._pooled(obs), out_rewards, terms, truncs, out_infos

    def _simtrace_step(self, i: int, info: dict, reward: float, done: bool, action):
        """Car i's sim-trace row of this step (`recording.simtrace.CarSimTrace`), with the reward as the learner
        reads it (float32) and the commanded action; a car driven by commands (a pool opponent) logs what it
        executed."""
        if type(action) is Command:
            return self._sim_traces[i].step(info, reward=reward, done=done)
        space = self.env.actions
        index = int(action) if space.discrete else None
        return self._sim_traces[i].step(info, reward=reward, done=done, action=index, command=space.command(action))

    def _pooled(self, obs: dict) -> dict:
        """The observations with their camera images pooled by `pool` (as they are if it is 1)."""
        if self.pool == 1:
            return obs
        from ..racing.nets import pool_image

        if isinstance(next(iter(obs.values())), dict):
            return {a: {**o, "camera": pool_image(o["camera"], self.pool)} for a, o in obs.items()}
        return {a: pool_image(o, self.pool) for a, o in obs.items()}

    def close(self):
        for env in self._envs.values():
            env.close()
