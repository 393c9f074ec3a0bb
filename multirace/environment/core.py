"""The race core: the world, the cars' race records, the stewards and the rules, stepped once per action step.

`RaceCore` is to `race_env.RaceEnv` what f1tenth_gym's simulator is to its
gym env: it knows nothing of actions, observations or rewards. Per step,
`advance(commands)` runs the physics, locates every racing car on the track
once (the projection of its reported point, its wheels on the road), adds
what it drove to its race distance and hands the contacts to the stewards;
`apply_rules` carries out the rules' rulings (laps, penalties, resets, ends);
`publish` builds the step's `RaceState`, which everything outside reads.
A parked car (its run over) is not located again: its track fields stay where
it stopped.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..sim.car import CarSpec
from ..sim.tracks import CarLocation, Track
from ..sim.world import World
from .race_state import CarState, RaceState
from .rules import CarRace, RaceRules, StepMeasure, Stewards

CLEAR_RADIUS = 0.45  # m; a reset spot closer than this to another body is taken


class RaceCore:
    """Every car of one race (learning cars first, then bots) in one PyBullet world, under `rules`.

    `geometry[i]` is car i's location this step (a `tracks.CarLocation`: reported point, heading, projection,
    wheels on), None once its run is over; `state` is the last published `RaceState`.
    """

    def __init__(self, track: Track, rules: RaceRules, car_spec: CarSpec, car_names: list[str], num_learners: int,
                 physics_hz: int, action_hz: int, dynamics: str):
        self.track, self.rules, self.car_spec = track, rules, car_spec
        self.car_names = list(car_names)
        self.total_cars = len(self.car_names)
        self.num_learners = num_learners
        self.dt = 1.0 / action_hz
        self.world = World(car_spec, self.total_cars, rules.obstacles, physics_hz, action_hz, dynamics)
        self._wheels = np.array(car_spec.wheel_offsets())
        self.races: list[CarRace] = []
        self.steps = 0
        self.sim_time = 0.0
        self.commands = [(0.0, 0.0)] * self.total_cars  # (steer rad, speed m/s) per car
        self.geometry: list[CarLocation | None] = []
        self.obstacle_slots: list[tuple[float, int]] = []  # (arc length, lane) of every box
        self.obstacle_points = np.zeros((0, 5))  # every box's (x, y, arc length, lateral offset, yaw)
        self.points = np.zeros((self.total_cars, 5))  # each car's reported point, arc length, lateral offset and
        # yaw where last located (`Track.locate_cars`)
        self.located = np.ones(self.total_cars, bool)  # the cars `geometry` locates (not parked)
        self.state: RaceState | None = None
        self._s: list[float] = []  # each car's arc length when its distance was last advanced
        self._stopped: dict[int, CarLocation] = {}  # where each parked car was located last
        self._hints = np.full(self.total_cars, -1, np.int64)  # the segment each car was last located on (-1: none)
        self._prev_distance: list[float] = []
        self._stewards: Stewards | None = None

    # ------------------------------------------------------------- start
    def start(self, rng: np.random.Generator) -> None:
        """Every car at rest on its grid slot, the boxes around the lap (seeded by `rng`), fresh race records."""
        track = self.track
        self.steps, self.sim_time = 0, 0.0
        self.commands = [(0.0, 0.0)] * self.total_cars
        self.races, self._stopped = [], {}
        self._hints[:] = -1
        self.located[:] = True
        for i, (s, lateral) in enumerate(track.start_grid(self.total_cars)):
            # the grid slot is where DeepRacer's reported point (ahead of the body centre) starts
            self.world.place_car(i, *track.point_at(s - self.car_spec.reported_point_offset, lateral))
        self._place_obstacles(rng)
        self._measure_all()
        self._s = [loc.s for loc in self.geometry]
        self._prev_distance = [0.0] * self.total_cars
        for i, loc in enumerate(self.geometry):
            s = loc.s
            signed = s - track.length if s > track.length / 2 else s
            self.races.append(CarRace(name=self.car_names[i], distance=signed, start_distance=signed,
                                      lap_start_distance=signed, last_on_track_s=s))
        self._stewards = Stewards(self.rules, self.races, self.car_names, self.car_spec.length, track.length, self.dt)

    def _place_obstacles(self, rng: np.random.Generator) -> None:
        """Boxes spread around the lap, in alternating lanes, with seeded jitter."""
        count = self.rules.obstacles
        self.obstacle_slots = [()] * count
        self.obstacle_points = np.zeros((count, 5))
        if not count:
            return
        track = self.track
        spacing = 0.75 * track.length / count
        first = 0.15 * track.length + rng.uniform(0, 0.1) * track.length
        lane = int(rng.integers(2))
        for k in range(count):
            s = (first + k * spacing + rng.uniform(-0.1, 0.1) * spacing) % track.length
            self.place_obstacle(k, s, track.lane_offset(lane, s))
            lane = 1 - lane

    def place_obstacle(self, k: int, s: float, lateral: float) -> None:
        """Put box k at arc length s, `lateral` metres left of the centre line, facing along the track, in the lane
        of its half of the road (a car that hits it is put back in the other, `RaceRules.reset_behind_obstacle`)."""
        x, y, yaw = self.track.point_at(s, lateral)
        self.world.place_obstacle(k, x, y, yaw)
        self.obstacle_slots[k] = (s, self.track.lane_of(lateral))
        self.obstacle_points[k] = (x, y, s, lateral, yaw)

    # -------------------------------------------------------------- step
    def advance(self, commands: list[tuple[float, float]]) -> list[set]:
        """One action step of physics under `commands` (steer rad, speed m/s per car), then every racing car
        located and its distance advanced, and the contacts judged. Returns what each car touched."""
        self.commands = commands
        contacts = self.world.step(commands)
        self.steps += 1
        self.sim_time = self.steps * self.dt
        races, last_s, prev_distance = self.races, self._s, self._prev_distance
        length = self.track.length
        half = length / 2
        self._measure_all()
        for i, loc in enumerate(self.geometry):
            race = races[i]
            prev_distance[i] = race.distance
            if loc is not None:
                s = loc[3]  # loc.s
                race.distance += (s - last_s[i] + half) % length - half  # `Track.wrap_ds`, inline
                last_s[i] = s
        return self._apply_contacts(contacts)

    def _apply_contacts(self, contacts) -> list[set]:
        """Hand the step's contacts to the stewards (incidents, fault, penalties). Returns who each car touched
        (without contacts, one empty set shared by all)."""
        self._stewards.judge(contacts, self.geometry, self.sim_time)
        if not contacts:
            return [set()] * self.total_cars
        touched = [set() for _ in range(self.total_cars)]
        for contact in contacts:
            for me, other in ((contact.a, contact.b), (contact.b, contact.a)):
                if me[0] == "car":
                    touched[me[1]].add(other)
        return touched

    def apply_rules(self, touched: list[set]) -> list[list[str]]:
        """Ask the rules about every car's step and carry out their rulings (and the race's time limit);
        returns each car's events."""
        rules, length, geometry = self.rules, self.track.length, self.geometry
        events = []
        for i, (race, loc, near) in enumerate(zip(self.races, geometry, touched)):
            hit_box = sorted(o[1] for o in near if o[0] == "obstacle") if near else ()
            # a location's fields by position (wheels_on: 10, s: 3), cheaper than by name
            if loc is None or race.status != "racing" or rules.uneventful(race, loc[10], loc[3], bool(hit_box),
                                                                          length):
                events.append([])
            else:
                events.append(self._judge(i, loc, hit_box))
        if rules.time_up(self.sim_time):
            self.end_unfinished(*rules.window_end())
        return events

    def _judge(self, i: int, loc: CarLocation, hit_box: list[int]) -> list[str]:
        """Have the rules judge car i's eventful step (at `loc`, into the boxes `hit_box`) and carry out their
        ruling; returns the step's events."""
        race = self.races[i]
        measure = StepMeasure(prev_distance=self._prev_distance[i], dt=self.dt, track_length=self.track.length,
                              wheels_on=loc.wheels_on, s=loc.s,
                              obstacle_hit=self.obstacle_slots[hit_box[0]] if hit_box else None)
        ruling = self.rules.judge(race, measure, self.sim_time)
        if ruling.reset is not None:
            s, lane = ruling.reset
            self._reset_car(i, s, 0.0 if lane is None else self.track.lane_offset(lane, s))
        if ruling.end is not None:
            self._end_run(i, *ruling.end)
        return ruling.events

    # ------------------------------------------------------- measurement
    def _measure_all(self) -> None:
        """Locate every racing car: every car not parked (`_stopped`)."""
        stopped = self._stopped
        if not stopped:  # every car racing (`located` stays all True from the start): the usual step
            self.geometry = self._locate(range(self.total_cars))
            return
        cars = [i for i in range(self.total_cars) if i not in stopped]
        self.located[:] = False
        self.located[cars] = True
        self.geometry = [None] * self.total_cars
        if cars:
            for i, loc in zip(cars, self._locate(cars)):
                self.geometry[i] = loc

    def _locate(self, cars: Sequence[int]) -> list[CarLocation]:
        """Where these cars are: reported point, heading, projection and wheels on track. Each car's search hint
        (`_hints`) moves to the segment it is found on, its `points` row to its point."""
        offset, wheels = self.car_spec.reported_point_offset, self._wheels
        if len(cars) == self.total_cars:  # every car: hints and points are set in place
            return self.track.locate_cars(self.world.poses, self._hints, offset, wheels, self.points)
        hints, points = self._hints[cars], self.points[cars]
        located = self.track.locate_cars(self.world.poses[cars], hints, offset, wheels, points)
        self._hints[cars], self.points[cars] = hints, points
        return located

    def last_locations(self, count: int) -> list[CarLocation]:
        """`last_geometry` of the first `count` cars."""
        if not self._stopped:
            return self.geometry[:count]
        return [self.last_geometry(i) for i in range(count)]

    def last_geometry(self, i: int) -> CarLocation:
        """Car i's location this step, or where it was last located once its run is over."""
        geo = self.geometry[i]
        return geo if geo is not None else self._stopped[i]

    # ------------------------------------------------------ moving cars
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
        self._place(i, x, y, yaw)

    def _place(self, i: int, x: float, y: float, yaw: float) -> None:
        """Put car i at rest at a pose and locate it there, its race distance advanced as if it had driven there."""
        self.world.place_car(i, x, y, yaw)
        loc = self._locate([i])[0]
        self.races[i].distance += self.track.wrap_ds(loc.s - self._s[i])
        self._s[i] = loc.s
        self.geometry[i] = loc
        self.located[i] = True

    def place_cars(self, poses: dict) -> None:
        """Put cars at rest at {car index: (x, y, yaw)}, located as if they had driven there, and publish the race
        as it now stands (for tests and scenarios that set up a scene)."""
        for i, pose in poses.items():
            self._place(i, *pose)
        self.publish([set()] * self.total_cars, [()] * self.total_cars)

    def move_cars(self, slots: dict, clear: bool = True) -> None:
        """Put cars at rest at {car index: (arc length from the start line, lateral offset)}, as a reset does,
        and publish the race as it now stands (`clear=False`: exactly there, not moved back off a taken spot)."""
        for i, (s, lateral) in slots.items():
            self._reset_car(i, s % self.track.length, lateral, clear)
        self.publish([set()] * self.total_cars, [()] * self.total_cars)

    def _end_run(self, i: int, status: str, reason: str, clock: float | None = None) -> None:
        """End car i's run with `status` and park it; it keeps the location it had."""
        race = self.races[i]
        race.status, race.reason = status, reason
        race.finish_time = round(clock if clock is not None else race.clock(self.sim_time), 4)
        self._stopped[i] = self.last_geometry(i)
        self.world.park(i)

    def forfeit(self, i: int, reason: str) -> None:
        """End car i's run now (its agent failed) and publish the race as it now stands."""
        if self.races[i].racing:
            self._end_run(i, "forfeit", reason)
            self.publish([car.touched for car in self.state.cars], [car.events for car in self.state.cars])

    def end_unfinished(self, status: str, reason: str) -> None:
        """End the run of every car still racing (the race's time or step limit)."""
        for i, race in enumerate(self.races):
            if race.racing:
                self._end_run(i, status, reason)

    # ----------------------------------------------------------- outputs
    def ranks(self) -> list[int]:
        """Current position (1 = leading) of every car, learning cars then bots."""
        return _positions(self.rules.ranking(self.races, self.track.length))

    def standings(self) -> list[int]:
        """Every car's position with penalties counted while it races (`RaceRules.standings`)."""
        if not self.rules.projects_standings and self.state is not None:  # the ranking the step published
            return [car.rank for car in self.state.cars]
        return _positions(self.rules.standings(self.races, self.track.length, self.sim_time))

    def publish(self, touched: list[set], events: list) -> RaceState:
        """The step's `RaceState` (every car as the rules left it, ranked once), kept as `state`."""
        cars, stopped = [], self._stopped
        for i, name, (x, y, yaw), speed, command, loc, rank, near, car_events, race in zip(
                range(self.total_cars), self.car_names, self.world.poses.tolist(), self.world.drive_speed.tolist(),
                self.commands, self.geometry, self.ranks(), touched, events, self.races):
            located = loc is not None
            px, py, _, s, lateral, segment, heading, left, right, width, wheels_on = loc if located else stopped[i]
            cars.append(tuple.__new__(CarState, (  # a named tuple of its full row: no Python __new__ call
                i, name, x, y, yaw, speed, command, located, px, py, s, lateral, width, segment, wheels_on, rank,
                tuple(sorted(near)) if near else (), tuple(car_events), race, heading, left, right)))
        self.state = tuple.__new__(RaceState, (  # its full row, as the cars'
            self.steps, self.sim_time, self.dt, self.track, self.rules, tuple(cars), self.world.obstacle_poses,
            self.num_learners, self.car_spec))
        return self.state


def _positions(order: list[int]) -> list[int]:
    """Positions (1 = first) of the cars listed in `order` (car indices, first first)."""
    positions = [0] * len(order)
    for place, i in enumerate(order):
        positions[i] = place + 1
    return positions
