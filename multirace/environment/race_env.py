"""The multirace PettingZoo environment: camera cars racing on a DeepRacer track.

``parallel_env(**config)`` builds a `RaceEnv` (a PettingZoo ParallelEnv);
``env(**config)`` its AEC form. Agents are ``car_0 .. car_{n-1}`` and stay in
`agents` for the whole episode: a car that goes off track is reset by the
race rules, a car whose run is over is parked off the scene and its actions
are ignored until every car is done.

Per step (15 Hz): actions -> commands (with DeepRacer's steering and speed
noise) -> physics -> measurements (projection on the track, wheels on track,
contacts) -> DeepRacer reward params -> rewards -> race rules (laps,
penalties, resets) -> camera images.
"""
from __future__ import annotations

import functools
import math

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils import OrderEnforcingWrapper, parallel_to_aec

from .actions import load_action_space
from .kernels import announce_compile
from .bots import parse_bot
from ..sensors.camera import CameraSpec
from ..sensors.renderers import make_renderer
from ..sim.car import CarSpec
from ..sensors.lidar_sensors import scanner
from ..sensors.sensor import SensorView
from ..sensors.suite import declared_sensors
from ..sim.objects import objects_seen
from .randomize import Randomization, apply_command, apply_image
from .reward_process import load_reward_function
from .race_state import CarState, RaceState
from .formats import make_rules
from .rules import CarRace, StepMeasure, Stewards
from .state import CAR_FEATURES, GLOBAL_PER_CAR, STATE_BOUND, car_features, global_state
from ..sim.texture import DEFAULT_PALETTE, TrackTexture
from ..sim.tracks import Track, load_track
from ..sim.world import World

ACTION_HZ = 15
MAX_CARS = 8
MIN_AVERAGE_SPEED = 0.4  # m/s; sets the default step limit of a race
CAMERA_RANGE = 8.0  # m; objects farther ahead do not count as `object_in_camera`
CLEAR_RADIUS = 0.45  # m; a reset spot closer than this to another body is taken


def parallel_env(**config) -> "RaceEnv":
    """The multirace env as a PettingZoo ParallelEnv (keywords: see RaceEnv)."""
    return RaceEnv(**config)


def env(**config):
    """The multirace env in PettingZoo's AEC form (same keywords as parallel_env)."""
    return OrderEnforcingWrapper(parallel_to_aec(RaceEnv(**config)))


def positive_int(value, name: str) -> int:
    """`value` as an int of at least 1; ValueError naming `name` for anything else (1.7, -1, "3", True)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name}: expected a whole number of at least 1, got {value!r}")
    return int(value)


class RaceEnv(ParallelEnv):
    """Several DeepRacer cars with front cameras racing in one PyBullet world.

    Keywords (the public contract): track, reverse, num_cars,
    race, laps, obstacles, bots, action_space, reward_function, camera,
    grayscale, lidar, renderer, randomize, render_mode ("human" or "rgb_array"),
    max_steps (or PettingZoo's `max_cycles`); plus
    `physics_hz` (default 60), `car_names` (names used in results) and
    `dynamics` ("dynamic": tyres with a grip limit and a drive train, the
    default; "kinematic": the grip-less bicycle of earlier versions).

    `sensor` is DeepRacer's model_metadata sensor list (default
    ``["FRONT_FACING_CAMERA"]``; see `sensors.suite`). Camera images are uint8
    (H, W) grey (the default), (H, W, 3) colour with ``grayscale=False`` or
    (H, W, 2) grey pairs [left, right] with ``STEREO_CAMERAS``
    (`camera.observation_shape`). An observation is the image, or with
    ``LIDAR`` (or ``lidar=True``) or ``SECTOR_LIDAR`` a dict ``{"camera": image,
    "lidar": 64 float32 ranges}`` or ``{"camera": image, "lidar": 8 binary sectors}``.

    ``observation="state"`` gives each car its privileged state instead
    (`state.car_features`: float32 vectors; nothing is rendered), for RL
    teachers; `state()` is the global state of every car (`state.global_state`).
    """

    metadata = {"name": "multirace_v0", "render_modes": ["human", "rgb_array"], "render_fps": ACTION_HZ,
                "is_parallelizable": True}

    def __init__(self, track="reinvent_base", reverse=False, num_cars=4, race="time_trial", laps=3,
                 obstacles=None, bots=(), action_space=None, reward_function=None, camera=(120, 160),
                 grayscale=True, lidar=False, renderer="fast", randomize=None, render_mode=None, max_steps=None,
                 physics_hz=60, car_names=None, max_cycles=None, sensor=None, dynamics="dynamic",
                 observation="camera"):
        self.track: Track = track if isinstance(track, Track) else load_track(track, reverse=reverse)
        self.rules = make_rules(race, laps, obstacles)
        self.bots = [parse_bot(b) for b in bots]
        if positive_int(num_cars, "num_cars") + len(self.bots) > MAX_CARS:
            raise ValueError(f"num_cars: need 1 to {MAX_CARS} cars in all, got {num_cars} "
                             f"learning cars and {len(self.bots)} bots")
        self.num_cars = int(num_cars)
        self._camera_cars = np.arange(self.num_cars)
        self.total_cars = self.num_cars + len(self.bots)
        self._check_args()
        self.actions = load_action_space(action_space)
        self.reward_function = load_reward_function(reward_function)
        self.randomization = Randomization.from_config(randomize)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode: {render_mode!r} is not supported; use None, 'human' or 'rgb_array'")
        self.render_mode = render_mode
        self._window = None  # render_mode="human": opened on the first render()
        if max_cycles is not None:  # PettingZoo's name for the step limit
            if max_steps is not None and max_steps != max_cycles:
                raise ValueError(f"max_cycles={max_cycles} and max_steps={max_steps}: give one step limit")
            max_steps = max_cycles
        try:
            height, width = (int(v) for v in camera)
        except (TypeError, ValueError):
            raise ValueError(f"camera: expected (height, width), got {camera!r}") from None
        if not (16 <= height <= 1080 and 16 <= width <= 1920):
            raise ValueError(f"camera: size {height}x{width} out of range 16x16 .. 1080x1920")
        self.camera = CameraSpec(height=height, width=width, grayscale=bool(grayscale))
        if renderer not in ("fast", "pybullet"):
            raise ValueError(f"renderer: unknown renderer {renderer!r}; choose 'fast' or 'pybullet'")
        self.renderer_name = renderer
        self.car_spec = CarSpec()
        self._wheels = np.array(self.car_spec.wheel_offsets())
        self.dt = 1.0 / ACTION_HZ
        self.world = World(self.car_spec, self.total_cars, self.rules.obstacles, physics_hz, ACTION_HZ, dynamics)
        self.max_steps = positive_int(max_steps, "max_steps") if max_steps is not None else self._default_max_steps()

        self.possible_agents = [f"car_{i}" for i in range(self.num_cars)]
        self.agents: list[str] = []
        names = list(car_names) if car_names is not None else list(self.possible_agents)
        if len(names) != self.num_cars:
            raise ValueError(f"car_names: expected {self.num_cars} names, got {len(names)}")
        self.car_names = names + [bot.name for bot in self.bots]
        self.sensors = declared_sensors(sensor, lidar)  # the registry's sensors the cars carry (`sensors.suite`)
        obs_space = self.sensors.space(self.camera)
        self.lidar = scanner(self.car_spec) if self.sensors.lidar else None  # its beams, for replays' echoes
        if observation not in ("camera", "state"):
            raise ValueError(f"observation: expected 'camera' or 'state', got {observation!r}")
        self.observation = observation
        if observation == "state":  # privileged state vectors instead of sensors: nothing is rendered
            obs_space = spaces.Box(-STATE_BOUND, STATE_BOUND, (CAR_FEATURES,), np.float32)
        self.observation_spaces = {a: obs_space for a in self.possible_agents}
        self.state_space = spaces.Box(-STATE_BOUND, STATE_BOUND, (self.total_cars * GLOBAL_PER_CAR,), np.float32)
        self.action_spaces = {a: self.actions.space for a in self.possible_agents}

        self._renderer = None
        self._texture = None
        self._rng = np.random.default_rng()
        self._randomizer_rng = np.random.default_rng()
        self._lidar_rng = np.random.default_rng()  # LIDAR noise: its own stream, so a scan changes no other draw
        self._draw = None  # this episode's domain-randomisation draw
        self.races: list[CarRace] = []
        self.steps = 0
        self.sim_time = 0.0
        self.race_state: RaceState | None = None  # published at the end of every reset and step

    def _check_args(self) -> None:
        """Refuse up front what would fail at reset: a loop too short for every car's start slot."""
        self.track.start_grid(self.total_cars)

    # ------------------------------------------------------------ spaces
    def observation_space(self, agent):
        return self.observation_spaces[agent]

    def action_space(self, agent):
        return self.action_spaces[agent]

    def _default_max_steps(self) -> int:
        if self.rules.time_limit is not None:
            return int(math.ceil(self.rules.time_limit * ACTION_HZ)) + 1
        seconds = max(60.0, self.rules.laps * self.track.length / MIN_AVERAGE_SPEED)
        return int(math.ceil(seconds * ACTION_HZ))

    @property
    def texture(self) -> TrackTexture:
        """The track's top-down texture (built on first use)."""
        if self._texture is None:
            self._texture = TrackTexture(self.track)
        return self._texture

    def __getstate__(self):
        state = self.__dict__.copy()
        state.update(_renderer=None, _texture=None, _window=None)
        return state

    # ------------------------------------------------------------- reset
    def reset(self, seed=None, options=None):
        announce_compile()  # once per process, and only if the kernels are not cached yet
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise ValueError(f"seed: expected a whole number of at least 0, got {seed!r}")
            self._rng = np.random.default_rng(seed)
            self._randomizer_rng = np.random.default_rng([seed, 3])  # its own stream: same grid either way
            self._lidar_rng = np.random.default_rng([seed, 5])
        self.world.connect()
        self._draw = None
        palette = DEFAULT_PALETTE
        self.world.grip[:], self.world.motor[:] = 1.0, 1.0
        if self.randomization.enabled:
            self._draw = self.randomization.draw_episode(self._randomizer_rng, self.total_cars)
            palette = self._draw.palette
            self.world.grip[:], self.world.motor[:] = self._draw.grip, self._draw.motor
        if self.renderer_name == "fast" and palette != self.texture.palette:  # (un)tinted track colours
            self._texture = TrackTexture(self.track, palette)
            self._renderer = None
        if self._renderer is None and self.observation == "camera":
            self._renderer = make_renderer(self.renderer_name, self.camera, self.texture)
        self.steps = 0
        self.sim_time = 0.0
        track = self.track
        self.races = []
        self._s = [0.0] * self.total_cars
        self._commands = [(0.0, 0.0)] * self.total_cars  # (steer rad, speed m/s) per car
        for i, (s, lateral) in enumerate(track.start_grid(self.total_cars)):
            # the grid slot is where DeepRacer's reported point (ahead of the body centre) starts
            self.world.place_car(i, *track.point_at(s - self.car_spec.reported_point_offset, lateral))
        self._place_obstacles()
        self._measure_all()
        for i, geo in enumerate(self._geometry):
            s = geo["proj"].s
            signed = s - track.length if s > track.length / 2 else s
            self._s[i] = s
            self.races.append(CarRace(name=self.car_names[i], distance=signed, start_distance=signed,
                                      lap_start_distance=signed, last_on_track_s=s,
                                      segment_hint=geo["proj"].segment))
        self._stewards = Stewards(self.rules, self.races, self.car_names, self.car_spec.length, track.length, self.dt)
        self.agents = list(self.possible_agents)
        table = self._object_table()
        params = [self._params(i, set(), table) for i in range(self.num_cars)]
        observations = self._observe()
        ranks = self.ranks()
        self.race_state = self._publish(ranks, [set()] * self.total_cars, [()] * self.total_cars)
        infos = {a: self._info(i, params[i], set(), ranks) for i, a in enumerate(self.agents)}
        return observations, infos

    def _place_obstacles(self) -> None:
        """Boxes spread around the lap, in alternating lanes, with seeded jitter."""
        count = self.rules.obstacles
        self.obstacle_slots = []
        self._obstacle_rows = []
        if not count:
            return
        track, rng = self.track, self._rng
        spacing = 0.75 * track.length / count
        first = 0.15 * track.length + rng.uniform(0, 0.1) * track.length
        lane = int(rng.integers(2))
        for k in range(count):
            s = (first + k * spacing + rng.uniform(-0.1, 0.1) * spacing) % track.length
            lateral = track.lane_offset(lane, s)
            x, y, yaw = track.point_at(s, lateral)
            self.world.place_obstacle(k, x, y, yaw)
            self.obstacle_slots.append((s, lane))
            self._obstacle_rows.append((-1, x, y, lateral > 0, 0.0, math.degrees(yaw), abs(lateral), s))
            lane = 1 - lane

    # -------------------------------------------------------------- step
    def step(self, actions):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        spec = self.car_spec
        noise = self._rng.standard_normal((self.num_cars, 2)).tolist()  # DeepRacer's action noise
        for i, agent in enumerate(self.possible_agents):
            if self.races[i].racing and agent in actions:
                try:
                    steer, speed = self.actions.command(actions[agent])
                except ValueError as exc:
                    raise ValueError(f"step {self.steps + 1}, {agent}: {exc}") from None
                if self._draw is not None and self.randomization.dynamics_enabled:
                    steer, speed = apply_command(steer, speed, self._draw, self._randomizer_rng, i, spec)
                    steer = math.radians(steer)
                else:
                    steer = math.radians(steer) + spec.steer_noise * noise[i][0]
                    speed = speed + spec.speed_noise * noise[i][1]
                self._commands[i] = spec.clamp_command(steer, speed)
        for b, bot in enumerate(self.bots):
            i = self.num_cars + b
            if self.races[i].racing:
                steer, speed = bot.drive(self.race_state, i)
                self._commands[i] = spec.clamp_command(math.radians(steer), speed)
        contacts = self.world.step(self._commands)
        self.steps += 1
        self.sim_time = self.steps * self.dt

        prev_distance = [race.distance for race in self.races]
        self._measure_all()
        self._advance_distances()
        touched = self._apply_contacts(contacts)
        table = self._object_table()
        params = [self._params(i, touched[i], table) for i in range(self.num_cars)]
        racing = [i for i in range(self.num_cars) if self.races[i].racing]
        rewards = dict.fromkeys(self.possible_agents, 0.0)
        if racing:  # one call for all cars: a reward file answers from its own process
            values = self.reward_function.rewards([params[i] for i in racing], self.steps,
                                                  [self.possible_agents[i] for i in racing])
            rewards.update(zip((self.possible_agents[i] for i in racing), values))
        events = [self._apply_rules(i, prev_distance[i], touched[i]) for i in range(self.total_cars)]
        if self.rules.time_up(self.sim_time):
            status, reason = self.rules.window_end()
            for i, race in enumerate(self.races):
                if race.racing:
                    self._end_run(i, status, reason)

        done = not any(race.racing for race in self.races)
        truncated = not done and self.steps >= self.max_steps
        if truncated:
            for i, race in enumerate(self.races):
                if race.racing:
                    self._end_run(i, "not_finished", f"step limit {self.max_steps} reached")
        observations = self._observe()
        ranks = self.ranks()
        self.race_state = self._publish(ranks, touched, events)
        infos = {a: self._info(i, params[i], touched[i], ranks, events[i])
                 for i, a in enumerate(self.possible_agents)}
        terminations = {a: done for a in self.possible_agents}
        truncations = {a: truncated for a in self.possible_agents}
        if done or truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def _publish(self, ranks: list[int], touched: list[set], events: list) -> RaceState:
        """The step's `RaceState`: every car as the rules left it."""
        poses, speeds = self.world.poses.tolist(), self.world.drive_speed.tolist()
        cars = []
        for i, race in enumerate(self.races):
            geo = self._geometry[i]
            located = geo is not None
            if not located:
                geo = self._last_params_geometry(i)
            proj = geo["proj"]
            x, y, yaw = poses[i]
            cars.append(CarState(i, self.car_names[i], x, y, yaw, speeds[i], self._commands[i], located,
                                 geo["x"], geo["y"], proj.s, proj.lateral, proj.width, proj.segment,
                                 geo["wheels_on"], ranks[i], tuple(sorted(touched[i])), tuple(events[i]), race))
        return RaceState(self.steps, self.sim_time, self.dt, self.track, self.rules, tuple(cars),
                         np.asarray(self.world.obstacle_poses, float).reshape(-1, 3), self.num_cars)

    # ------------------------------------------------------- measurement
    def _measure_all(self) -> None:
        """Project every racing car on the track and test its wheels."""
        self._geometry = [None] * self.total_cars
        cars = [i for i in range(self.total_cars) if i >= len(self.races) or self.races[i].racing]
        if cars:
            for i, geo in zip(cars, self._locate(cars)):
                self._geometry[i] = geo

    def _measure(self, i: int) -> dict | None:
        """Car i's geometry (None when its run is over)."""
        racing = i >= len(self.races) or self.races[i].racing
        return self._locate([i])[0] if racing else None

    def _locate(self, cars: list[int]) -> list[dict]:
        """Geometry of these cars: reported point, heading, projection and wheels on track."""
        hints = [self.races[i].segment_hint if i < len(self.races) else None for i in cars]
        hints = np.array([-1 if hint is None else hint for hint in hints], np.int64)
        poses = self.world.poses[cars]
        located = self.track.locate_cars(poses, hints, self.car_spec.reported_point_offset, self._wheels)
        geometry = []
        for i, yaw, (px, py, proj, wheels_on) in zip(cars, poses[:, 2].tolist(), located):
            if i < len(self.races):
                self.races[i].segment_hint = proj.segment
            geometry.append({"x": px, "y": py, "yaw": yaw, "proj": proj, "wheels_on": wheels_on})
        return geometry

    def _advance_distances(self) -> None:
        """Add what each car drove along the centre line since the last step to its race distance."""
        for i, geo in enumerate(self._geometry):
            if geo is not None:
                s = geo["proj"].s
                self.races[i].distance += self.track.wrap_ds(s - self._s[i])
                self._s[i] = s

    def _apply_contacts(self, contacts) -> list[set]:
        """Hand the step's contacts to the stewards (incidents, fault, penalties). Returns who each car touched."""
        touched = [set() for _ in range(self.total_cars)]
        for contact in contacts:
            for me, other in ((contact.a, contact.b), (contact.b, contact.a)):
                if me[0] == "car":
                    touched[me[1]].add(other)
        places = {i: (self.races[i].distance, geo["proj"].lateral)
                  for i, geo in enumerate(self._geometry) if geo is not None}
        self._stewards.judge(contacts, places, self.sim_time)
        return touched

    # ------------------------------------------------------------- rules
    def _apply_rules(self, i: int, prev_distance: float, touched: set) -> list[str]:
        """Ask the rules about car i's step and carry out their ruling; returns the step's events."""
        race, geo = self.races[i], self._geometry[i]
        if geo is None or not race.racing:
            return []
        hit_box = sorted(o[1] for o in touched if o[0] == "obstacle")
        measure = StepMeasure(prev_distance=prev_distance, dt=self.dt, track_length=self.track.length,
                              wheels_on=geo["wheels_on"], s=geo["proj"].s,
                              obstacle_hit=self.obstacle_slots[hit_box[0]] if hit_box else None)
        ruling = self.rules.judge(race, measure, self.sim_time)
        if ruling.reset is not None:
            s, lane = ruling.reset
            self._reset_car(i, s, 0.0 if lane is None else self.track.lane_offset(lane, s))
        if ruling.end is not None:
            self._end_run(i, *ruling.end)
        return ruling.events

    def _reset_car(self, i: int, s: float, lateral: float, clear: bool = True) -> None:
        """Put car i back on the track at arc length s, facing along the track, at rest.

        If another car or a box occupies the spot, the car is put further back until it is clear (`clear`).
        """
        track = self.track
        others = [self.world.poses[j][:2] for j in range(self.total_cars)
                  if j != i and not self.world.parked[j]] + [p[:2] for p in self.world.obstacle_poses]
        for _ in range(8):
            x, y, yaw = track.point_at(s, lateral)
            if not clear or all(math.hypot(x - ox, y - oy) > CLEAR_RADIUS for ox, oy in others):
                break
            s -= CLEAR_RADIUS
        self.world.place_car(i, x, y, yaw)
        geo = self._measure(i)
        self.races[i].distance += track.wrap_ds(geo["proj"].s - self._s[i])
        self._s[i] = geo["proj"].s
        self._geometry[i] = geo

    def move_cars(self, slots: dict, clear: bool = True) -> dict:
        """Put cars at rest at {car index: (arc length from the start line, lateral offset)}, as a reset does
        (`clear=False`: exactly there, side by side if asked, not moved back off a spot next to a car).

        For training set-ups (bots started ahead of the learners). Returns the camera cars' new observations.
        """
        for i, (s, lateral) in slots.items():
            self._reset_car(i, s % self.track.length, lateral, clear)
        self.race_state = self._publish(self.ranks(), [set()] * self.total_cars, [()] * self.total_cars)
        return self._observe()

    def traffic(self, i: int) -> list[tuple[float, float, float]]:
        """The other cars on track as seen from car i: (metres ahead, lateral offset, speed)."""
        mine = self._geometry[i]
        if mine is None:
            return []
        s_i, lateral_i = mine["proj"].s, mine["proj"].lateral
        length = self.track.length
        return [((geo["proj"].s - s_i) % length, geo["proj"].lateral - lateral_i, float(self.world.drive_speed[j]))
                for j, geo in enumerate(self._geometry) if geo is not None and j != i]

    def forfeit(self, i: int, reason: str) -> None:
        """End car i's run now (its agent failed); the race goes on for the others."""
        if self.races[i].racing:
            self._end_run(i, "forfeit", reason)

    def _end_run(self, i: int, status: str, reason: str, clock: float | None = None) -> None:
        race = self.races[i]
        race.status, race.reason = status, reason
        race.finish_time = round(clock if clock is not None else race.clock(self.sim_time), 4)
        self.world.park(i)

    # ----------------------------------------------------------- outputs
    def _observe(self) -> dict:
        if self.observation == "state":
            return {agent: car_features(self, i) for i, agent in enumerate(self.possible_agents)}
        draw, randomization = self._draw, self.randomization
        jitter = perturb = None
        if draw is not None and randomization.camera_enabled:
            jitter = np.array(draw.camera_jitter[:self.num_cars])
        if draw is not None and randomization.perception_enabled:
            perturb = functools.partial(apply_image, rng=self._randomizer_rng, draw=draw)
        view = SensorView(self.world, self._camera_cars, self.camera, self.car_spec, self._lidar_rng,
                          self._renderer, jitter, perturb, self.race_state)
        return self.sensors.observe(view, self.possible_agents)

    def car_state(self, i: int) -> np.ndarray:
        """Car i's privileged ego state (`state.car_features`), what an RL teacher reads."""
        return car_features(self, i)

    def state(self) -> np.ndarray:
        """PettingZoo's global state: every car's pose, motion, race distance, road position and the curvature
        ahead (`state.global_state`), for centralised critics; `state_space` gives its shape."""
        return global_state(self)

    def _params(self, i: int, touched: set, table: tuple) -> dict:
        """The 27 DeepRacer reward params of car i, in DeepRacer's units."""
        geo = self._geometry[i] if self._geometry[i] is not None else self._last_params_geometry(i)
        race, track = self.races[i], self.track
        proj = geo["proj"]
        steer, speed = self._commands[i]
        objects = self._objects_for(i, table)
        return {
            "all_wheels_on_track": geo["wheels_on"] == 4,
            "x": geo["x"],
            "y": geo["y"],
            "heading": math.degrees(geo["yaw"]),
            "distance_from_center": abs(proj.lateral),
            "projection_distance": proj.s,
            "progress": race.lap_progress(track.length) if race.racing else 100.0 * (race.status == "finished"),
            "steps": self.steps,
            "speed": float(speed),
            "steering_angle": math.degrees(steer),
            "track_width": proj.width,
            "track_length": track.length,
            "waypoints": track.waypoints,
            "closest_waypoints": list(track.closest_waypoints(proj)),
            "is_left_of_center": proj.lateral > 0,
            "is_reversed": track.reverse,
            **objects,
            "is_crashed": bool(touched),
            "is_offtrack": geo["wheels_on"] == 0,
            "sim_time": self.sim_time,
        }

    def _last_params_geometry(self, i: int) -> dict:
        """Geometry of a parked car: where it was when its run ended."""
        x, y, yaw = self.world.poses[i]
        return {"x": x, "y": y, "yaw": yaw, "proj": self.track.project(x, y), "wheels_on": 4}

    def _object_table(self) -> tuple:
        """Every object a car can see this step (boxes, then cars on track), as columns:

        (car index or -1, x, y, left_of_centre, speed, heading_deg, distance_from_centre, s),
        then per learning car `object_in_camera` and `closest_objects` (see `objects.objects_seen`).
        """
        rows = list(self._obstacle_rows)
        for j, geo in enumerate(self._geometry):
            if geo is None:
                continue
            proj = geo["proj"]
            rows.append((j, geo["x"], geo["y"], proj.lateral > 0, float(self.world.drive_speed[j]),
                         math.degrees(geo["yaw"]), abs(proj.lateral), proj.s))
        columns = tuple(list(column) for column in zip(*rows)) if rows else ([],) * 8
        car_s = [geo["proj"].s if geo is not None else self._s[i]
                 for i, geo in enumerate(self._geometry[:self.num_cars])]
        in_camera, closest = objects_seen(np.array(columns[0], np.int64), np.array(columns[1], float),
                                          np.array(columns[2], float), np.array(columns[7], float),
                                          self.world.poses[:self.num_cars], np.array(car_s), self.track.length,
                                          math.tan(self.camera.hfov / 2), CAMERA_RANGE)
        return columns, in_camera.tolist(), closest.tolist()

    def _objects_for(self, i: int, table: tuple) -> dict:
        """DeepRacer's object params for car i: the boxes and every other car on track."""
        columns, in_camera, closest = table
        owners = columns[0]
        if i in owners:  # leave car i itself out of every column
            k = owners.index(i)
            xs, ys, left, speed, heading, from_centre, along = (c[:k] + c[k + 1:] for c in columns[1:])
        else:
            xs, ys, left, speed, heading, from_centre, along = (list(c) for c in columns[1:])
        return {
            "closest_objects": closest[i],
            "objects_location": list(zip(xs, ys)),
            "objects_left_of_center": left,
            "object_in_camera": in_camera[i],
            "objects_speed": speed,
            "objects_heading": heading,
            "objects_distance_from_center": from_centre,
            "objects_distance": along,
        }

    def ranks(self) -> list[int]:
        """Current position (1 = leading) of every car, learning cars then bots."""
        return _positions(self.rules.ranking(self.races, self.track.length))

    def standings(self) -> list[int]:
        """Every car's position with penalties counted while it races (`RaceRules.standings`; the race view's
        panel): the result's positions once the race is over."""
        return _positions(self.rules.standings(self.races, self.track.length, self.sim_time))

    def _info(self, i: int, params: dict, touched: set, ranks: list[int], events=()) -> dict:
        """Car i's info: its reward params (the same dict, extended) plus its race state."""
        race = self.races[i]
        names = sorted(self.car_names[o[1]] if o[0] == "car" else f"obstacle_{o[1]}" for o in touched)
        params.update(
            lap=race.laps + (1 if race.racing else 0),
            laps_completed=race.laps,
            lap_times=list(race.lap_times),
            race_time=race.clock(self.sim_time) if race.racing else race.finish_time,
            resets=race.resets,
            penalties=race.penalties,
            penalty_time=race.penalty_time,
            off_track=params["is_offtrack"],
            collisions=names,
            rank=ranks[i],
            status=race.status,
            events=list(events),
        )
        return params

    # ------------------------------------------------------------ render
    def render(self):
        """The top-down race view: an RGB array ("rgb_array"), shown in a window ("human"), or None."""
        if self.render_mode is None:
            return None
        from ..sensors.topdown import render_topdown

        frame = render_topdown(self)
        if self.render_mode == "rgb_array":
            return frame
        if self._window is None:
            from ..sensors.window import RaceWindow

            self._window = RaceWindow()
        self._window.show(frame)
        return None

    def close(self):
        self.reward_function.close()
        if self._window is not None:
            self._window.close()
            self._window = None
        if self._renderer is not None:
            self._renderer.close()
        self.world.close()


def _positions(order: list[int]) -> list[int]:
    """Positions (1 = first) of the cars listed in `order` (car indices, first first)."""
    positions = [0] * len(order)
    for place, i in enumerate(order):
        positions[i] = place + 1
    return positions
