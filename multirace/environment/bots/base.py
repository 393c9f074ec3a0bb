"""What every scripted bot shares: the `Bot` driver, pure-pursuit steering and manners in traffic.

A bot reads privileged state: its car's true pose, the track and the other
cars. From the race's `RaceState` it takes its car's pose, the segment the
env located the car on and the traffic; it projects its body centre on the
centre line itself, once per step (the env locates DeepRacer's reported
point, ahead of the body centre: a different point), and steers from there.
"""
from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, ClassVar

from ...sim.car import CarSpec
from ..drivers import Driver, car_pose
from ..race_state import RaceState

if TYPE_CHECKING:
    from ...sim.tracks import Projection, Track

SPEED_RANGE = (0.1, 4.0)  # m/s a bot may be asked to drive


@dataclasses.dataclass
class PurePursuit:
    """Steers toward a point `lookahead` metres ahead on a path parallel to the centre line."""

    speed: float = 1.0  # m/s
    lookahead: float = 0.45  # metres (grows with speed)
    lateral: float = 0.0  # target offset from the centre line, + left

    def command(self, track: Track, spec: CarSpec, pose, segment_hint=None) -> tuple[float, float]:
        """(steering degrees, speed m/s) for a car whose body centre is at `pose` (x, y, yaw)."""
        return self.command_at(track, spec, pose, track.project(pose[0], pose[1], segment_hint))

    def command_at(self, track: Track, spec: CarSpec, pose, proj: Projection) -> tuple[float, float]:
        """The command for a car at `pose` whose body centre projects on the centre line at `proj`."""
        x, y, yaw = pose
        rear_x = x - spec.wheelbase / 2 * math.cos(yaw)
        rear_y = y - spec.wheelbase / 2 * math.sin(yaw)
        lookahead = self.lookahead + 0.25 * self.speed
        tx, ty, _ = track.point_at(proj.s + lookahead, self.lateral)
        return pursuit_steer(spec, rear_x, rear_y, yaw, tx, ty), self.speed


def pursuit_steer(spec: CarSpec, rear_x: float, rear_y: float, yaw: float, tx: float, ty: float) -> float:
    """Pure-pursuit steering (degrees, within the car's lock) of a car whose rear axle is at (rear_x, rear_y)
    toward the point (tx, ty)."""
    alpha = math.atan2(ty - rear_y, tx - rear_x) - yaw
    steer = math.atan2(2.0 * spec.wheelbase * math.sin(alpha), math.hypot(tx - rear_x, ty - rear_y))
    return math.degrees(max(-spec.max_steer, min(spec.max_steer, steer)))


@dataclasses.dataclass
class Bot(Driver):
    """A scripted car of kind `kind` (a registered name, `bots.BOTS`), driving at `speed` m/s.

    A kind implements `steer`; `parse` reads its ``@NUMBER`` (a speed in m/s unless the kind says otherwise).
    """

    speed: float
    speed_text: str = ""  # the number as the user wrote it, so names read back as typed
    kind: ClassVar[str] = ""
    number_is_speed: ClassVar[bool] = True  # False: its number means something else and may be left out
    usage: ClassVar[str] = ""  # how a kind whose number is not a speed is written, for help texts

    @property
    def name(self) -> str:
        return f"bot:{self.kind}@{self.speed_text or format(self.speed, 'g')}"

    @classmethod
    def parse(cls, text: str, number: str | None) -> Bot:
        """The bot `text` names, `number` the text after its ``@``; ValueError for a speed out of range."""
        speed = float(number)
        if not SPEED_RANGE[0] <= speed <= SPEED_RANGE[1]:
            raise ValueError(f"bot {text!r}: speed {speed} outside 0.1-4.0 m/s")
        return cls(speed=speed, speed_text=number)

    def drive(self, state: RaceState, car: int, observation=None) -> tuple[float, float]:
        """Car `car`'s command from the race state: its pose, the segment it was located on, the traffic."""
        me = state.cars[car]
        return self.command(state.track, state.car_spec, car_pose(me), state.time, me.segment, state.traffic(car))

    def command(self, track: Track, spec: CarSpec, pose, sim_time: float, segment_hint=None, traffic=()):
        """(steering degrees, speed m/s) at race time `sim_time` of a car whose body centre is at `pose`.

        `traffic` lists the other cars as (metres ahead along the track, lateral
        offset from this car, speed); a bot slows behind a car in its way.
        """
        proj = track.project(pose[0], pose[1], segment_hint)  # the body centre's one projection this step
        return self.steer(Situation(track, spec, pose, proj, segment_hint, sim_time, list(traffic)))

    def steer(self, at: Situation) -> tuple[float, float]:
        """The command of the car `at` describes."""
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class Situation:
    """What a bot steers from: its car's body-centre pose and its projection, the race time and the traffic."""

    track: Track
    spec: CarSpec
    pose: tuple  # (x, y, yaw) of the body centre
    proj: Projection  # the body centre on the centre line
    segment_hint: int | None  # the segment the env located the car on (where to search for other points)
    time: float  # race time, s
    traffic: list  # the other cars: (metres ahead along the track, lateral offset from this car, speed)

    def pursue(self, speed: float, lateral: float) -> tuple[float, float]:
        """Pure pursuit at `speed` of the path `lateral` metres off the centre line."""
        return PurePursuit(speed=speed, lateral=lateral).command_at(self.track, self.spec, self.pose, self.proj)


FOLLOW_DISTANCE = 1.2  # m; a car closer than this ahead, in the same lane, sets the pace
STOP_DISTANCE = 0.55  # m; closer than this the bot crawls
LANE_HALF_WIDTH = 0.4  # m; cars closer than this sideways are in the way (two car widths)


def speed_in_traffic(speed: float, traffic, spec: CarSpec) -> float:
    """Speed that keeps a scripted driver from running into the car ahead."""
    for ahead, lateral, other_speed in traffic:
        if 0.0 < ahead < FOLLOW_DISTANCE and abs(lateral) < LANE_HALF_WIDTH:
            if ahead < STOP_DISTANCE:
                return spec.min_speed
            speed = min(speed, max(spec.min_speed, 0.9 * other_speed))
    return speed
