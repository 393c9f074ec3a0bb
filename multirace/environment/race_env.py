"""The multirace PettingZoo environment: camera cars racing on a DeepRacer track.

``parallel_env(**config)`` builds a `RaceEnv` (a PettingZoo ParallelEnv);
``env(**config)`` its AEC form. Agents are ``car_0 .. car_{n-1}`` and stay in
`agents` for the whole episode: a car that goes off track is reset by the
race rules, a car whose run is over is parked off the scene and its actions
are ignored until every car is done.

`RaceEnv` is a thin adapter over `core.RaceCore` (the world, the race
records, the stewards and the rules): per step (15 Hz) it turns actions into
commands (with DeepRacer's steering and speed noise), lets the core run the
physics and locate the cars, builds the DeepRacer reward params and rewards,
lets the core apply the race rules (laps, penalties, resets) and publish the
`RaceState` (``env.race_state``), then renders the camera images and infos.
"""
from __future__ import annotations

import functools
import math

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils import OrderEnforcingWrapper, parallel_to_aec

from .kernels import announce_compile
from .bots import parse_bot
from .drivers import Driver
from .actions import DRIVER_COMMANDS, Command, load_action_space
from ..sensors.camera import CameraSpec
from ..sensors.renderers import make_renderer
from ..sim.car import CarSpec
from ..sensors.lidar_sensors import scanner
from ..sensors.sensor import SensorView
from ..sensors.suite import declared_sensors, race_suite
from ..sim.objects import object_table
from .noise import NoiseBlocks
from .randomize import Randomization, apply_command, apply_image
from .reward_process import load_reward_function
from .rewards import PARAM_KEYS
from .core import RaceCore
from .race_state import CarState, RaceState
from .formats import make_rules
from .rules import CarRace
from .state import CAR_FEATURES, GLOBAL_PER_CAR, STATE_BOUND, STATE_VIEWS, car_features, global_state
from ..sim.texture import DEFAULT_PALETTE, TrackTexture
from ..sim.tracks import Track, load_track
from ..sim.world import World

ACTION_HZ = 15
MAX_CARS = 8
MIN_AVERAGE_SPEED = 0.4  # m/s; sets the default step limit of a race
CAMERA_RANGE = 8.0  # m; objects farther ahead do not count as `object_in_camera`
_NO_ACTION = object()  # `_commands_for`: an agent without an action this step


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
    (H, W, 2) grey pairs [left, right] with ``STEREO_CAMERAS`` or [this
    step's, the previous step's] with ``FRONT_FACING_CAMERA_TWO_FRAMES``
    (`camera.observation_shape`). An observation is the image, or with
    ``LIDAR`` (or ``lidar=True``) or ``SECTOR_LIDAR`` a dict ``{"camera": image,
    "lidar": 64 float32 ranges}`` or ``{"camera": image, "lidar": 8 binary sectors}``.

    `bots` are cars the env drives after the learning cars: scripted bot specs
    (``"follow@1.0"``, `environment.bots`) or `drivers.Driver` objects; a
    driver with `sensors` (an agent file's controller) gets its car's
    observation of the last step, rendered for it, as a learner would.

    ``observation="state"`` gives each car its privileged state instead
    (`state.car_features`: float32 vectors; nothing is rendered), for RL
    teachers, listing the cars near it (``state_view="all"``) or only those
    its front camera shows (``state_view="camera"``); `state()` is the global
    state of every car (`state.global_state`).
    """

    metadata = {"name": "multirace_v0", "render_modes": ["human", "rgb_array"], "render_fps": ACTION_HZ,
                "is_parallelizable": True}

    def __init__(self, track="reinvent_base", reverse=False, num_cars=4, race="time_trial", laps=3,
                 obstacles=None, bots=(), action_space=None, reward_function=None, camera=(120, 160),
                 grayscale=True, lidar=False, renderer="fast", randomize=None, render_mode=None, max_steps=None,
                 physics_hz=60, car_names=None, max_cycles=None, sensor=None, dynamics="dynamic",
                 observation="camera", state_view="all"):
        self.track: Track = track if isinstance(track, Track) else load_track(track, reverse=reverse)
        self.rules = make_rules(race, laps, obstacles)
        self.bots = [b if isinstance(b, Driver) else parse_bot(b) for b in bots]
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
        self._tan_half_fov = math.tan(self.camera.hfov / 2)  # the object table's `object_in_camera` cone
        self._object_arrays = (np.empty((6, 0)), np.empty(0, np.bool_), np.empty((0, 4), np.int64))  # its outputs
        if renderer not in ("fast", "pybullet"):
            raise ValueError(f"renderer: unknown renderer {renderer!r}; choose 'fast' or 'pybullet'")
        self.renderer_name = renderer
        self.car_spec = CarSpec()
        self.max_steps = positive_int(max_steps, "max_steps") if max_steps is not None else self._default_max_steps()

        self.possible_agents = [f"car_{i}" for i in range(self.num_cars)]
        self.agents: list[str] = []
        names = list(car_names) if car_names is not None else list(self.possible_agents)
        if len(names) != self.num_cars:
            raise ValueError(f"car_names: expected {self.num_cars} names, got {len(names)}")
        self.core = RaceCore(self.track, self.rules, self.car_spec, names + [bot.name for bot in self.bots],
                             self.num_cars, physics_hz, ACTION_HZ, dynamics)
        # the reward params every car shares in a step (`_reward_params` fills in the rest), in DeepRacer's order
        self._shared_params = dict.fromkeys(PARAM_KEYS)
        self._shared_params.update(track_length=self.track.length, waypoints=self.track.waypoints,
                                   is_reversed=self.track.reverse)
        self.sensors = declared_sensors(sensor, lidar)  # the registry's sensors the cars carry (`sensors.suite`)
        # bots that read sensors (agent files driving beside the learners): their cars and what they read
        self._sensor_bots = np.array([self.num_cars + b for b, bot in enumerate(self.bots) if bot.sensors is not None],
                                     np.int64)
        self._bot_sensors = race_suite(self.bots[i - self.num_cars].sensors for i in self._sensor_bots)
        self._bot_observations: dict = {}  # their observations after the last reset or step
        self._last_images: dict = {}  # {car: its previous camera image}, for sensors that read two frames
        obs_space = self.sensors.space(self.camera)
        self.lidar = scanner(self.car_spec) if self.sensors.lidar else None  # its beams, for replays' echoes
        if observation not in ("camera", "state"):
            raise ValueError(f"observation: expected 'camera' or 'state', got {observation!r}")
        self.observation = observation
        if state_view not in STATE_VIEWS:
            raise ValueError(f"state_view: expected one of {', '.join(STATE_VIEWS)}, got {state_view!r}")
        self.state_view = state_view
        if observation == "state":  # privileged state vectors instead of sensors: nothing is rendered
            obs_space = spaces.Box(-STATE_BOUND, STATE_BOUND, (CAR_FEATURES,), np.float32)
        self.observation_spaces = {a: obs_space for a in self.possible_agents}
        self.state_space = spaces.Box(-STATE_BOUND, STATE_BOUND, (self.total_cars * GLOBAL_PER_CAR,), np.float32)
        self.action_spaces = {a: self.actions.space for a in self.possible_agents}

        self._renderer = None
        self._texture = None
        self._rng = np.random.default_rng()
        self._noise = NoiseBlocks(self._rng, (self.num_cars, 2))  # DeepRacer's action noise, from `_rng`
        self._randomizer_rng = np.random.default_rng()
        self._lidar_rng = np.random.default_rng()  # LIDAR noise: its own stream, so a scan changes no other draw
        self._draw = None  # this episode's domain-randomisation draw

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

    # ------------------------------------------------ the core, read-only
    @property
    def world(self) -> World:
        return self.core.world

    @property
    def races(self) -> list[CarRace]:
        """Every car's race record (laps, lap times, distance, penalties, status), learning cars then bots."""
        return self.core.races

    @property
    def race_state(self) -> RaceState | None:
        """The `RaceState` published at the end of the last reset or step (None before the first reset)."""
        return self.core.state

    @property
    def car_names(self) -> list[str]:
        return self.core.car_names

    @property
    def steps(self) -> int:
        return self.core.steps

    @property
    def sim_time(self) -> float:
        return self.core.sim_time

    @property
    def dt(self) -> float:
        return self.core.dt

    @property
    def obstacle_slots(self) -> list[tuple[float, int]]:
        """(arc length, lane) of every box."""
        return self.core.obstacle_slots

    @property
    def renderer(self):
        """The camera renderer (built at reset; None before, and for ``observation="state"`` envs)."""
        return self._renderer

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
            self._noise = NoiseBlocks(self._rng, (self.num_cars, 2))
            self._randomizer_rng = np.random.default_rng([seed, 3])  # its own stream: same grid either way
            self._lidar_rng = np.random.default_rng([seed, 5])
        self.world.connect()
        self._draw = None
        self._last_images.clear()
        palette = DEFAULT_PALETTE
        self.world.grip[:], self.world.motor[:] = 1.0, 1.0
        if self.randomization.enabled:
            self._draw = self.randomization.draw_episode(self._randomizer_rng, self.total_cars)
            palette = self._draw.palette
            self.world.grip[:], self.world.motor[:] = self._draw.grip, self._draw.motor
        if self.renderer_name == "fast" and palette != self.texture.palette:  # (un)tinted track colours
            self._texture = TrackTexture(self.track, palette)
            self._renderer = None
        if self._renderer is None and (self.observation == "camera" or len(self._sensor_bots)):
            self._renderer = make_renderer(self.renderer_name, self.camera, self.texture)
        self._noise.settle()  # `_rng` as if the noise had been drawn step by step: the boxes' draws come next
        self.core.start(self._rng)
        for i, bot in enumerate(self.bots, start=self.num_cars):
            bot.reset(self, i)
        self.agents = list(self.possible_agents)
        self.core.publish([set()] * self.total_cars, [()] * self.total_cars)
        return self._observe(), self.standing_infos()

    # -------------------------------------------------------------- step
    def step(self, actions):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        core = self.core
        touched = core.advance(self._commands_for(actions))
        params = self._reward_params(touched)
        races, agents = core.races, self.possible_agents
        racing = [i for i, race in enumerate(races[:self.num_cars]) if race.status == "racing"]
        rewards = dict.fromkeys(agents, 0.0)
        if racing:  # one call for all cars: a reward file answers from its own process
            racing_agents = [agents[i] for i in racing]
            values = self.reward_function.rewards([params[i] for i in racing], core.steps, racing_agents)
            rewards.update(zip(racing_agents, values))
        events = core.apply_rules(touched)  # self.rules.judge per car, then self.rules.time_up

        done = "racing" not in [race.status for race in races]
        truncated = not done and core.steps >= self.max_steps
        if truncated:
            core.end_unfinished("not_finished", f"step limit {self.max_steps} reached")
        state = core.publish(touched, events)
        observations = self._observe()
        infos = {a: self._info(params[i], state.cars[i], state.time) for i, a in enumerate(agents)}
        terminations = dict.fromkeys(agents, done)
        truncations = dict.fromkeys(agents, truncated)
        if done or truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def _commands_for(self, actions: dict) -> list[tuple[float, float]]:
        """Every car's (steer rad, speed m/s) this step: the racing learners' actions (a `Command`: that command,
        whatever the action space) with DeepRacer's noise (or the episode's randomised dynamics), the bots' own
        commands; a car without one keeps its last command."""
        spec, races, draw = self.car_spec, self.core.races, self._draw
        randomised = draw is not None and self.randomization.dynamics_enabled
        commands = list(self.core.commands)
        noise = self._noise.next()  # DeepRacer's action noise: learning car i's steer and speed at 2i and 2i + 1
        steer_noise, speed_noise, clamp = spec.steer_noise, spec.speed_noise, spec.clamp_command
        space = self.actions
        for i, agent in enumerate(self.possible_agents):
            action = actions.get(agent, _NO_ACTION)
            if action is _NO_ACTION or races[i].status != "racing":
                continue
            try:
                steer, speed = (DRIVER_COMMANDS if type(action) is Command else space).command(action)
            except ValueError as exc:
                raise ValueError(f"step {self.steps + 1}, {agent}: {exc}") from None
            if randomised:
                steer, speed = apply_command(steer, speed, draw, self._randomizer_rng, i, spec)
                steer = math.radians(steer)
            else:
                steer = math.radians(steer) + steer_noise * noise[2 * i]
                speed = speed + speed_noise * noise[2 * i + 1]
            commands[i] = clamp(steer, speed)
        for b, bot in enumerate(self.bots):
            i = self.num_cars + b
            if races[i].racing:
                steer, speed = bot.drive(self.race_state, i, self._bot_observations.get(i))
                commands[i] = spec.clamp_command(math.radians(steer), speed)
        return commands

    # ------------------------------------------------- moving and ending
    def move_cars(self, slots: dict, clear: bool = True) -> dict:
        """Put cars at rest at {car index: (arc length from the start line, lateral offset)}, as a reset does
        (`clear=False`: exactly there, side by side if asked, not moved back off a spot next to a car).

        For training set-ups (bots started ahead of the learners). Returns the camera cars' new observations;
        `standing_infos` gives their infos.
        """
        self.core.move_cars(slots, clear)
        for car in slots:  # a car put somewhere else starts its frames afresh
            self._last_images.pop(car, None)
        return self._observe()

    def standing_infos(self) -> dict:
        """Every learning car's info as the cars stand now, nothing touched: what `reset` returns, and what a
        set-up that moved cars after it (`move_cars`) hands its drivers."""
        params = self._reward_params([set()] * self.num_cars)
        state = self.race_state
        return {a: self._info(params[i], state.cars[i], state.time) for i, a in enumerate(self.agents)}

    def traffic(self, i: int) -> list[tuple[float, float, float]]:
        """The other cars on track as seen from car i: (metres ahead, lateral offset, speed)."""
        return self.core.state.traffic(i)

    def forfeit(self, i: int, reason: str) -> None:
        """End car i's run now (its agent failed); the race goes on for the others."""
        self.core.forfeit(i, reason)

    # ----------------------------------------------------------- outputs
    def _observe(self) -> dict:
        """The learning cars' observations (and, kept for their next commands, those of the bots that read
        sensors)."""
        if len(self._sensor_bots):
            view = self._sensor_view(self._sensor_bots)
            self._bot_observations = self._bot_sensors.observe(view, self._sensor_bots.tolist())
        if self.observation == "state":
            return {agent: car_features(self, i, self.state_view) for i, agent in enumerate(self.possible_agents)}
        return self.sensors.observe(self._sensor_view(self._camera_cars), self.possible_agents)

    def _sensor_view(self, cars: np.ndarray) -> SensorView:
        """What the sensors of `cars` read this step: the world, this episode's camera jitter and image
        perturbation (domain randomisation), the race state."""
        draw, randomization = self._draw, self.randomization
        jitter = perturb = None
        if draw is not None and randomization.camera_enabled:
            jitter = np.array(draw.camera_jitter)[cars]
        if draw is not None and randomization.perception_enabled:
            perturb = functools.partial(apply_image, rng=self._randomizer_rng, draw=draw)
        return SensorView(self.world, cars, self.camera, self.car_spec, self._lidar_rng, self._renderer, jitter,
                          perturb, self.race_state, self._last_images)

    def car_state(self, i: int, view: str = "all") -> np.ndarray:
        """Car i's privileged ego state (`state.car_features`, listing the traffic of `view`), what an RL
        teacher reads."""
        return car_features(self, i, view)

    def state(self) -> np.ndarray:
        """PettingZoo's global state: every car's pose, motion, race distance, road position and the curvature
        ahead (`state.global_state`), for centralised critics; `state_space` gives its shape."""
        return global_state(self)

    def _reward_params(self, touched: list[set]) -> list[dict]:
        """The 27 DeepRacer reward params of every learning car, in DeepRacer's units (its object params: the boxes
        and every other car on track, from `_object_table`); a parked car reads where its run ended."""
        core, track = self.core, self.track
        columns, seen = self._object_table()
        length, races, commands = track.length, core.races, core.commands
        # each car's dict is a copy of one with the step's shared values, in DeepRacer's key order: a dict's copy
        # costs far less than building a 27-key dict
        shared = self._shared_params
        shared["steps"], shared["sim_time"] = core.steps, core.sim_time
        every_params = []
        for i, (x, y, yaw, s, lateral, segment, _, _, _, width, wheels_on) in enumerate(core.last_locations(
                self.num_cars)):
            race = races[i]
            steer, speed = commands[i]
            in_camera, behind, ahead, k = seen[i]
            locations, left, speeds, heading, from_centre, along = map(list.copy, columns)
            if k >= 0:  # leave car i itself out of every column
                del locations[k], left[k], speeds[k], heading[k], from_centre[k], along[k]
            status = race.status
            params = shared.copy()
            params["all_wheels_on_track"] = wheels_on == 4
            params["x"], params["y"] = x, y
            params["heading"] = math.degrees(yaw)
            params["distance_from_center"] = abs(lateral)
            params["projection_distance"] = s
            params["progress"] = race.lap_progress(length) if status == "racing" else 100.0 * (status == "finished")
            params["speed"] = float(speed)
            params["steering_angle"] = math.degrees(steer)
            params["track_width"] = width
            params["closest_waypoints"] = [segment, segment + 1]  # `Track.closest_waypoints`, inline
            params["is_left_of_center"] = lateral > 0
            params["closest_objects"] = [behind, ahead]
            params["objects_location"] = locations
            params["objects_left_of_center"] = left
            params["object_in_camera"] = in_camera == 1
            params["objects_speed"] = speeds
            params["objects_heading"] = heading
            params["objects_distance_from_center"] = from_centre
            params["objects_distance"] = along
            params["is_crashed"] = bool(touched[i])
            params["is_offtrack"] = wheels_on == 0
            every_params.append(params)
        return every_params

    def _object_table(self) -> tuple:
        """Every object a car can see this step (boxes, then cars on track) as the params' columns (locations
        (x, y), left_of_centre, speed, heading_deg, distance_from_centre, s), then per learning car
        ``[object_in_camera, *closest_objects, its own place in the columns or -1]`` (`objects.object_table`)."""
        core, world = self.core, self.world
        size = len(core.obstacle_points) + self.total_cars
        if self._object_arrays[1].shape[0] != size:  # (the boxes of this episode)
            self._object_arrays = np.empty((6, size)), np.empty(size, np.bool_), np.empty((self.num_cars, 4), np.int64)
        values, left, seen = self._object_arrays
        count = object_table(core.obstacle_points, core.points, core.located, world.drive_speed, world.poses,
                             self.num_cars, self.track.length, self._tan_half_fov, CAMERA_RANGE, values, left, seen)
        xs, ys, speed, heading, from_centre, along = values[:, :count].tolist()
        return (list(zip(xs, ys)), left[:count].tolist(), speed, heading, from_centre, along), seen.tolist()

    def ranks(self) -> list[int]:
        """Current position (1 = leading) of every car, learning cars then bots."""
        return self.core.ranks()

    def standings(self) -> list[int]:
        """Every car's position with penalties counted while it races (`RaceRules.standings`; the race view's
        panel): the result's positions once the race is over."""
        return self.core.standings()

    def _info(self, params: dict, car: CarState, sim_time: float) -> dict:
        """A car's info: its reward params (the same dict, extended) plus its published race state."""
        race, touched = car.race, []
        if car.touched:
            names = self.car_names
            touched = sorted(names[o[1]] if o[0] == "car" else f"obstacle_{o[1]}" for o in car.touched)
        racing = race.status == "racing"
        # item by item: an update from a dict literal builds that dict first (twice the time, every car and step)
        params["lap"] = race.laps + (1 if racing else 0)
        params["laps_completed"] = race.laps
        params["lap_times"] = list(race.lap_times)
        params["race_time"] = sim_time + race.penalty_time if racing else race.finish_time  # `race.clock`
        params["resets"] = race.resets
        params["penalties"] = race.penalties
        params["penalty_time"] = race.penalty_time
        params["off_track"] = params["is_offtrack"]
        params["collisions"] = touched
        params["rank"] = car.rank
        params["status"] = race.status
        params["events"] = list(car.events)
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

