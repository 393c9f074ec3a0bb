"""Race formats and scoring: what happens on a lap, an off-track, a crash, and who wins.

Each format is a `RaceRules` object that the env consults every step. The env
measures (distance driven, wheels on track, contacts); the rules decide
(penalties, resets, end of a car's run) and rank the cars. All times are
simulated race time in seconds, not wall time.

Formats (DeepRacer's, see DESIGN.md "Race formats and scoring"):
- ``time_trial``: N laps; off track costs a 2 s penalty and a reset onto the
  centre line where the car left. Ranked by total time (time + penalties).
- ``reset_rule``: AWS Summit rules, a 4-minute window and up to 3 resets; the
  next off-track ends the run. Ranked by best lap, then laps, then progress.
- ``object_avoidance``: a time trial with static boxes in alternating lanes; a
  crash into a box costs 5 s and a reset 1.0 m behind the box in the other lane.
- ``head_to_head``: 2-8 cars on a staggered grid; the car that ran into the
  other is penalised 5 s. Ranked by laps, then total time, then progress.
"""
from __future__ import annotations

import dataclasses
import math

FORMATS = ("time_trial", "reset_rule", "object_avoidance", "head_to_head")
STATUSES = ("finished", "out_of_resets", "timed_out", "forfeit", "not_finished")


@dataclasses.dataclass
class CarRace:
    """The race state of one car (learning car or bot)."""

    name: str
    distance: float = 0.0  # metres driven along the centre line since the start line (signed)
    start_distance: float = 0.0  # `distance` at the start of the episode (<= 0 for grid slots behind)
    lap_start_distance: float = 0.0
    lap_start_time: float = 0.0  # race clock (incl. penalties) when the current lap began
    laps: int = 0
    lap_times: list = dataclasses.field(default_factory=list)
    penalty_time: float = 0.0
    penalties: int = 0
    resets: int = 0
    off_tracks: int = 0
    collisions: list = dataclasses.field(default_factory=list)  # [{"time", "with", "caused"}]
    status: str = "racing"  # "racing" or one of STATUSES once the run is over
    reason: str = ""
    finish_time: float | None = None  # race clock when the run ended
    last_on_track_s: float = 0.0  # arc length where the car was last on the road
    segment_hint: int | None = None

    @property
    def racing(self) -> bool:
        return self.status == "racing"

    @property
    def best_lap(self) -> float | None:
        return min(self.lap_times) if self.lap_times else None

    def clock(self, sim_time: float) -> float:
        """This car's race clock: simulated time plus its penalties."""
        return sim_time + self.penalty_time

    def lap_progress(self, track_length: float) -> float:
        """DeepRacer's `progress`: percent of the current lap, 0-100, from where it began."""
        lap_len = track_length * (self.laps + 1) - self.lap_start_distance
        done = self.distance - self.lap_start_distance
        return float(min(max(100.0 * done / max(lap_len, 1e-9), 0.0), 100.0))

    def race_progress(self, track_length: float, laps: int) -> float:
        """Percent of the whole race distance (all laps, from the grid slot) driven, 0-100."""
        total = laps * track_length - self.start_distance
        return float(min(max(100.0 * (self.distance - self.start_distance) / total, 0.0), 100.0))

    def collisions_caused(self) -> int:
        return sum(1 for c in self.collisions if c["caused"])


@dataclasses.dataclass
class RaceRules:
    """A race format with its parameters; see the module docstring."""

    name: str = "time_trial"
    laps: int = 3
    off_track_penalty: float = 2.0  # seconds added per off-track
    crash_penalty: float = 5.0  # seconds added per crash into a box / rival (where penalised)
    max_resets: int | None = None  # None: unlimited; reset_rule: 3
    time_limit: float | None = None  # seconds of race time; reset_rule: 240
    obstacles: int = 0  # boxes placed; object_avoidance default 3
    penalise_striker: bool = False  # head_to_head: the car that ran into the other pays
    reset_behind_obstacle: float = 1.0  # object_avoidance: metres behind the box, other lane

    @property
    def crash_resets(self) -> bool:
        """Does a crash into a box reset the car (object avoidance)?"""
        return self.name == "object_avoidance"

    def rank_key(self, car: CarRace, track_length: float):
        """Sort key: smaller ranks first."""
        progress = car.distance - car.start_distance
        if self.name == "reset_rule":
            best = car.best_lap if car.best_lap is not None else math.inf
            return (best, -car.laps, -progress)
        finished = car.status == "finished"
        total = car.finish_time if finished else math.inf
        if self.name == "head_to_head":
            return (-car.laps, total, -progress)
        return (0 if finished else 1, total, -car.laps, -progress)

    def ranking(self, cars: list[CarRace], track_length: float) -> list[int]:
        """Indices of `cars` in finishing order (forfeits last)."""
        def key(i):
            car = cars[i]
            return (car.status == "forfeit",) + self.rank_key(car, track_length)

        return sorted(range(len(cars)), key=key)


def make_rules(race: str = "time_trial", laps: int = 3, obstacles: int | None = None, **overrides) -> RaceRules:
    """The rules of a named format with DeepRacer's defaults, overridable per field."""
    if race not in FORMATS:
        raise ValueError(f"race: unknown format {race!r}; choose one of {', '.join(FORMATS)}")
    if int(laps) < 1:
        raise ValueError(f"laps: must be at least 1, got {laps}")
    defaults: dict = {"name": race, "laps": int(laps), "obstacles": 0}
    if race == "reset_rule":
        defaults.update(max_resets=3, time_limit=240.0, off_track_penalty=0.0)
    elif race == "object_avoidance":
        defaults.update(obstacles=3)
    elif race == "head_to_head":
        defaults.update(penalise_striker=True)
    if obstacles is not None:
        defaults["obstacles"] = int(obstacles)
    defaults.update(overrides)
    if not 0 <= defaults["obstacles"] <= 6:
        raise ValueError(f"obstacles: must be 0 to 6, got {defaults['obstacles']}")
    return RaceRules(**defaults)
