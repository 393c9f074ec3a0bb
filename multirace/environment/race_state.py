"""`RaceState`: what the race core publishes once per step, read by everything around it.

Rules, bots and drivers, rewards, sensors, recorders (replay, sim-trace,
video), results and the league read a `RaceState` (``env.race_state``)
instead of reaching into the env: every car's pose, speed, command, where it
is on the track (located once per step), its lap, progress, rank and race
record, the step's contacts and events.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ..sim.car import CarSpec
from .rules import CarRace, RaceRules

if TYPE_CHECKING:
    from ..sim.tracks import Track


class CarState(NamedTuple):
    """One car at the end of a step. Lengths in metres, angles in radians, speeds in m/s.

    A named tuple: one is built for every car every step, and a named tuple is the cheapest to build.
    """

    index: int  # learning cars 0..num_cars-1, then the env's bots
    name: str
    x: float  # body centre
    y: float
    yaw: float
    speed: float  # drive speed along the car
    command: tuple[float, float]  # (steering rad, speed m/s) the car was given this step
    located: bool  # False once its run is over (parked): the track fields below are from where it stopped
    point_x: float  # DeepRacer's reported point (ahead of the body centre)
    point_y: float
    s: float  # arc length of the reported point on the centre line
    lateral: float  # signed offset from the centre line, left positive
    track_width: float
    segment: int  # centre-line segment the point projects on
    wheels_on: int  # wheels on the road, 0-4
    rank: int  # road position, 1 = leading (`RaceRules.ranking`)
    touched: tuple  # what it touched this step: ("car", j) / ("obstacle", k), sorted
    events: tuple  # the rules' events for it this step ("lap", "off_track", ...)
    race: CarRace  # its race record (laps, lap times, distance, penalties, resets, collisions, status)
    track_heading: float  # the centre line's direction at `s`
    left_width: float  # road extent left and right of the centre line at `s`
    right_width: float

    @property
    def racing(self) -> bool:
        return self.race.racing


class RaceState(NamedTuple):
    """The whole race after `step` action steps (`time` seconds of simulated time)."""

    step: int
    time: float
    dt: float
    track: Track
    rules: RaceRules
    cars: tuple[CarState, ...]
    obstacles: np.ndarray  # (boxes, 3): x, y, yaw
    num_learners: int  # cars 0..num_learners-1 are driven by actions, the rest are the env's bots
    car_spec: CarSpec = CarSpec()  # every car's size and command range (the env's cars are all alike)

    def traffic(self, i: int) -> list[tuple[float, float, float]]:
        """The other located cars as seen from car i: (metres ahead along the track, lateral offset, speed)."""
        me = self.cars[i]
        if not me.located:
            return []
        length = self.track.length
        return [((car.s - me.s) % length, car.lateral - me.lateral, car.speed)
                for car in self.cars if car.located and car.index != i]
