"""Race rules and scoring: what happens on a lap, an off-track, a crash, and who wins.

Each race format is a `RaceRules` (sub)class in `environment/formats/`, one
file per format, named in its registry (`formats.REGISTRY`); the env consults
it every step. The env measures (distance driven, wheels on track, contacts:
a `StepMeasure`); the rules decide (laps, penalties, resets, the end of a
car's run: a `Ruling`, with the car's `CarRace` state updated) and rank the
cars; the env then only carries out what they decided (moves a car back,
parks it). All times are simulated race time in seconds, not wall time.

`RaceRules` itself is the time trial: N laps; an off-track costs
`off_track_penalty` and a reset onto the centre line where the car left;
ranked by total time (time + penalties). A format changes its defaults (its
fields) and overrides what differs: `finished` (the end of a run),
`rank_key` (the result's order), `standings_key` (the order while racing),
`window_end` (what the end of `time_limit` makes of a run), `crash_resets`.

Contacts are judged by `Stewards` (one per race): a touch of the same pair
within `INCIDENT_GAP` of the last is the same incident, counted and
penalised once.

No reset loops: in every format a car that leaves the track again within
`reset_loop_seconds` of each of its last `reset_loop_count` resets, or that
needs more than `reset_cap` resets (formats with unlimited resets; 100 as in
DeepRacer-for-Cloud), ends its run as ``out_of_resets`` with the reason.
"""
from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

STATUSES = ("finished", "out_of_resets", "timed_out", "forfeit", "not_finished")
STANDINGS_MIN_SHARE = 0.05  # share of the race every racing car drives before standings project finishing times
OVERLAP_SHARE = 0.25  # of a car length: a car this far alongside another has overlap and keeps its line
LATERAL_MOVE = 0.1  # m/s towards the other car: a car moving across slower than this holds its line
CLOSING_SPEED = 0.05  # m/s faster along the track than the car ahead: the car behind is catching it
INCIDENT_GAP = 0.5  # s: the same pair touching again within this of its last touch is the same incident
PUSH_OFF_WINDOW = 1.0  # s: a car off track this soon after an incident another car was at fault for was pushed off


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
    collisions: list = dataclasses.field(default_factory=list)  # [{"time", "with", "caused", "kind"}], one per incident
    status: str = "racing"  # "racing" or one of STATUSES once the run is over
    reason: str = ""
    finish_time: float | None = None  # race clock when the run ended
    last_on_track_s: float = 0.0  # arc length where the car was last on the road
    last_reset_time: float | None = None  # sim time of the last reset
    quick_off_tracks: int = 0  # off-tracks in a row, each soon after the reset before it
    pushed: tuple | None = None  # (until sim time, incident records): an off-track by then was a push-off

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
        share = 100.0 * (self.distance - self.lap_start_distance) / (lap_len if lap_len > 1e-9 else 1e-9)
        return 0.0 if share < 0.0 else 100.0 if share > 100.0 else float(share)  # (every car, every step)

    def race_progress(self, track_length: float, laps: int) -> float:
        """Percent of the whole race distance (all laps, from the grid slot) driven, 0-100."""
        total = laps * track_length - self.start_distance
        return float(min(max(100.0 * (self.distance - self.start_distance) / total, 0.0), 100.0))

    def collisions_caused(self) -> int:
        return sum(1 for c in self.collisions if c["caused"])


@dataclasses.dataclass(frozen=True)
class StepMeasure:
    """What the env measured of one car over one action step: the rules' input."""

    prev_distance: float  # race distance (m along the centre line) before the step
    dt: float  # the step's length, s
    track_length: float
    wheels_on: int  # wheels on the road now
    s: float  # arc length of the car's point on the centre line now
    obstacle_hit: tuple[float, int] | None = None  # (arc length, lane) of a box touched this step


@dataclasses.dataclass
class Ruling:
    """What the rules decided for one car this step; the env carries it out."""

    events: list = dataclasses.field(default_factory=list)
    reset: tuple[float, int | None] | None = None  # put the car back at (arc length, lane; None: centre line)
    end: tuple[str, str, float | None] | None = None  # end its run: (status, reason, race clock or None: now)


@dataclasses.dataclass
class RaceRules:
    """A race format with its parameters: the time trial; each format of `formats` subclasses it."""

    name: str = "time_trial"
    laps: int = 3
    off_track_penalty: float = 2.0  # seconds added per off-track
    crash_penalty: float = 5.0  # seconds added per crash into a box / rival (where penalised)
    max_resets: int | None = None  # None: unlimited; reset_rule: 3
    time_limit: float | None = None  # seconds of race time; reset_rule: 240
    obstacles: int = 0  # boxes placed; object_avoidance default 3
    penalise_striker: bool = False  # head_to_head: the car at fault in an incident pays (`at_fault`)
    reset_behind_obstacle: float = 1.0  # object_avoidance: metres behind the box, other lane
    reset_cap: int = 100  # formats with unlimited resets: the run ends after this many (DeepRacer-for-Cloud's)
    reset_loop_count: int = 5  # off-tracks in a row, each within reset_loop_seconds of the reset before it,
    reset_loop_seconds: float = 1.0  # end the run: the car cannot drive on from where it is put back

    crash_resets: ClassVar[bool] = False  # does a crash into a box reset the car (object avoidance)?
    projects_standings: ClassVar[bool] = True  # standings project finishing times (False: they are the ranking)
    solo: ClassVar[bool] = True  # each car's run is scored on its own (a time trial), not against the others
    league_stage: ClassVar[str | None] = None  # the league.toml section (stage) that races this format, if any

    def __post_init__(self):
        if not 0 <= self.obstacles <= 6:
            raise ValueError(f"obstacles: must be 0 to 6, got {self.obstacles}")

    def time_up(self, sim_time: float) -> bool:
        """Has the format's time window (reset_rule: 4 minutes) ended?"""
        return self.time_limit is not None and sim_time >= self.time_limit - 1e-9

    def window_end(self) -> tuple[str, str]:
        """(status, reason) of a run still going when the time window ends."""
        return "timed_out", f"{self.time_limit:g} s window ended"

    def finished(self, race: CarRace) -> bool:
        """Has the car finished its race (after a lap it completed)?"""
        return race.laps >= self.laps

    def contact(self, race: CarRace, clock: float, other: str, kind: str = "contact") -> dict:
        """Record a new incident of `race`'s car with `other` (a car or a box), nobody at fault yet; returns
        the record (the stewards set its `caused` by `blame` and its `kind` as they judge the incident)."""
        record = {"time": round(clock, 3), "with": other, "caused": False, "kind": kind}
        race.collisions.append(record)
        return record

    def blame(self, race: CarRace, record: dict, with_car: bool) -> None:
        """Put `race`'s car at fault for the incident of `record`; head-to-head: it pays `crash_penalty`."""
        record["caused"] = True
        if with_car and self.penalise_striker:
            race.penalty_time += self.crash_penalty
            race.penalties += 1

    def uneventful(self, race: CarRace, wheels_on: int, s: float, hit_box: bool, track_length: float) -> bool:
        """Is this step of a racing car one `judge` rules nothing on (no lap boundary crossed, its wheels on the
        road, no box hit that resets it)? If so, records in `race` what `judge` records of such a step (where
        the car was last on the road), so that most steps need no `StepMeasure` and no `Ruling`. `judge` asks
        it first; a format that overrides `judge` overrides this too."""
        if wheels_on == 0 or race.distance >= (race.laps + 1) * track_length or (hit_box and self.crash_resets):
            return False
        race.last_on_track_s = s
        return True

    def judge(self, race: CarRace, step: StepMeasure, sim_time: float) -> Ruling:
        """Laps, off-track and crash resets for one racing car after a step; updates `race`."""
        ruling = Ruling()
        if self.uneventful(race, step.wheels_on, step.s, step.obstacle_hit is not None, step.track_length):
            return ruling
        # laps: every crossing of a lap boundary, timed by interpolation within the step
        while race.distance >= (race.laps + 1) * step.track_length:
            boundary = (race.laps + 1) * step.track_length
            moved = max(race.distance - step.prev_distance, 1e-9)
            t_cross = sim_time - step.dt + step.dt * min(max((boundary - step.prev_distance) / moved, 0.0), 1.0)
            clock = race.clock(t_cross)
            race.lap_times.append(round(clock - race.lap_start_time, 4))
            race.laps += 1
            race.lap_start_time = clock
            race.lap_start_distance = boundary
            ruling.events.append("lap_complete")
            if self.finished(race):
                ruling.end = ("finished", "", clock)
                return ruling
        if step.wheels_on == 0:
            ruling.events.append("off_track")
            race.off_tracks += 1
            ruling.end = self._no_more_resets(race, sim_time)
            pushed_off = self._pushed_off(race, sim_time)
            if ruling.end is None:
                race.resets += 1
                race.last_reset_time = sim_time
                if self.off_track_penalty and not pushed_off:
                    race.penalty_time += self.off_track_penalty
                    race.penalties += 1
                ruling.reset = (race.last_on_track_s, None)
            return ruling
        race.last_on_track_s = step.s
        if step.obstacle_hit is not None and self.crash_resets:
            ruling.events.append("crashed")
            s_box, lane = step.obstacle_hit
            race.resets += 1
            race.last_reset_time = sim_time
            race.penalty_time += self.crash_penalty
            race.penalties += 1
            ruling.reset = (s_box - self.reset_behind_obstacle, 1 - lane)
        return ruling

    def _pushed_off(self, race: CarRace, sim_time: float) -> bool:
        """Was this off-track a push-off (head-to-head: within `PUSH_OFF_WINDOW` of an incident another car
        was at fault for)? Marks the incident ``push_off``."""
        if race.pushed is None or not self.penalise_striker:
            return False
        until, records = race.pushed
        race.pushed = None
        if sim_time > until + 1e-9:
            return False
        for record in records:
            record["kind"] = "push_off"
        return True

    def _no_more_resets(self, race: CarRace, sim_time: float) -> tuple[str, str, None] | None:
        """The end of a run that left the track and may not be put back again, or None."""
        if self.max_resets is not None and race.resets >= self.max_resets:
            return ("out_of_resets", f"off track after {race.resets} resets", None)
        if race.last_reset_time is not None and sim_time - race.last_reset_time <= self.reset_loop_seconds:
            race.quick_off_tracks += 1
        else:
            race.quick_off_tracks = 0
        if race.quick_off_tracks >= self.reset_loop_count:
            return ("out_of_resets", f"reset loop: off track within {self.reset_loop_seconds:g} s of each of "
                                     f"the last {self.reset_loop_count} resets", None)
        if self.max_resets is None and race.resets >= self.reset_cap:
            return ("out_of_resets", f"reset cap: off track after {race.resets} resets", None)
        return None

    def rank_key(self, car: CarRace, track_length: float):
        """Sort key: smaller ranks first. The time trial: finished cars by total time, then the others by
        laps and distance."""
        finished = car.status == "finished"
        total = car.finish_time if finished else math.inf
        return (0 if finished else 1, total, -car.laps, -(car.distance - car.start_distance))

    def standings_key(self, projected: float) -> tuple:
        """`rank_key` of a car still racing whose finishing time (race clock) is projected as `projected`."""
        return (0, projected, -self.laps, 0.0)

    def ranking(self, cars: list[CarRace], track_length: float) -> list[int]:
        """Indices of `cars` in finishing order (forfeits last)."""
        keys = [(car.status == "forfeit",) + self.rank_key(car, track_length) for car in cars]
        return sorted(range(len(cars)), key=keys.__getitem__)

    def standings(self, cars: list[CarRace], track_length: float, sim_time: float) -> list[int]:
        """Indices of `cars` in the order the race stands now, penalties counted (the race view's panel).

        `ranking` ranks a car still racing by the road (laps, then distance) and counts its penalties only
        when it finishes; here each racing car's finishing time is projected instead: its race clock at
        its average pace so far (sim time over the share of the race driven, plus its penalties). So a car
        that leads on the road with 10 s of penalties stands where it will finish, and once no car is
        racing the order is `ranking`'s, the result's. Before every racing car has driven
        `STANDINGS_MIN_SHARE` of the race (the grid, the first metres) and in formats that do not project
        (`projects_standings`: the reset rule, scored on the best lap) it is `ranking`'s throughout."""
        shares = {i: car.race_progress(track_length, self.laps) / 100.0 for i, car in enumerate(cars) if car.racing}
        if not self.projects_standings or not shares or min(shares.values()) < STANDINGS_MIN_SHARE:
            return self.ranking(cars, track_length)

        def key(i):
            car = cars[i]
            if i not in shares:
                return (car.status == "forfeit",) + self.rank_key(car, track_length)
            return (False,) + self.standings_key(sim_time / shares[i] + car.penalty_time)

        return sorted(range(len(cars)), key=key)


@dataclasses.dataclass(frozen=True)
class CarMotion:
    """One car at a contact: where it is on the track and how it was moving (`at_fault`'s input)."""

    distance: float  # race distance, m along the centre line
    lateral: float  # m from the centre line, + left
    along_speed: float = 0.0  # m/s along the track going into the contact
    lateral_speed: float = 0.0  # m/s across the track going into the contact, + left


def at_fault(a: CarMotion, b: CarMotion, striker: int | None, car_length: float,
             track_length: float) -> tuple[int | None, str]:
    """Who of two touching cars is at fault (0: `a`, 1: `b`, None: nobody) and the kind of incident.

    The README's "Race rules": nobody where neither drove into the other or the one that did was pushed
    into it (`striker` None: `world.Contact`). With less than `OVERLAP_SHARE` of a car length alongside,
    the car behind has no overlap (a ``rear_end``): the car ahead owns the line and the car behind is at
    fault if it was catching it (by `CLOSING_SPEED` or more); the car ahead if it went backwards into it.
    Alongside (overlap), and in a rear-end where neither was catching the other, the car that moved
    across towards the other (by `LATERAL_MOVE` or more, the faster of the two) is at fault: a
    ``cut_across`` where it is the car ahead and the other had overlap, a ``side_swipe`` otherwise. Where
    neither moved across either, the striker of the contact is (the one that closed faster along the
    contact normal; in a graze, the faster car)."""
    if striker is None:
        return None, "contact"
    gap = (b.distance - a.distance + track_length / 2) % track_length - track_length / 2  # + : b ahead
    ahead = 1 if gap >= 0 else 0
    cars = (a, b)
    side = 1.0 if b.lateral >= a.lateral else -1.0  # where b is, seen from a
    towards = (a.lateral_speed * side, -b.lateral_speed * side)
    mover = 0 if towards[0] >= towards[1] else 1
    mover = mover if towards[mover] >= LATERAL_MOVE else None
    if 1.0 - abs(gap) / car_length < OVERLAP_SHARE:
        rear, front = cars[1 - ahead], cars[ahead]
        if -front.along_speed > max(rear.along_speed, 0.0):
            return ahead, "rear_end"  # the car ahead backed into it
        if rear.along_speed - front.along_speed >= CLOSING_SPEED:
            return 1 - ahead, "rear_end"
        return (striker if mover is None else mover), "rear_end"
    if mover is None:
        return striker, "side_swipe"
    return mover, ("cut_across" if mover == ahead and abs(gap) > 0.1 * car_length else "side_swipe")


class Stewards:
    """The incidents of one race: debounced contacts judged by `at_fault`, penalties and push-offs.

    `judge(contacts, geometry, sim_time)` every step with the world's contacts and every car's location
    (None: not racing); a pair touching again within `INCIDENT_GAP` of its last touch is the same incident
    (recorded and penalised once; a car at fault found later in it is blamed then)."""

    def __init__(self, rules: RaceRules, races: list[CarRace], names: list[str], car_length: float,
                 track_length: float, dt: float):
        self.rules, self.races, self.names = rules, races, names
        self.car_length, self.track_length, self.dt = car_length, track_length, dt
        self._open: dict = {}  # pair -> {"last": sim time, "records": (record a, record b or None), "victim"}
        # (this step, the last, the one before): each car's (distance, lateral, resets), None while not racing
        self._trail = ([None] * len(races),) * 3

    def judge(self, contacts, geometry: list, sim_time: float) -> None:
        """Record this step's contacts (`world.Contact`s) as incidents; `geometry`: each car's `CarLocation`
        this step (None: not racing)."""
        now = [None if loc is None else (race.distance, loc.lateral, race.resets)
               for race, loc in zip(self.races, geometry)]
        self._trail = (now,) + self._trail[:2]
        if not contacts:
            return
        for contact in contacts:
            pair = (contact.a, contact.b)
            incident = self._open.get(pair)
            if incident is None or sim_time - incident["last"] > INCIDENT_GAP + 1e-9:
                incident = self._open[pair] = {"records": self._record(contact, sim_time), "victim": None}
            incident["last"] = sim_time
            if incident["victim"] is None and not any(r is not None and r["caused"] for r in incident["records"]):
                incident["victim"] = self._blame(contact, incident["records"])
            if incident["victim"] is not None:  # a push-off can follow until PUSH_OFF_WINDOW after its last touch
                self.races[incident["victim"]].pushed = (sim_time + PUSH_OFF_WINDOW, incident["records"])

    def _motion(self, i: int) -> CarMotion | None:
        """Car i's `CarMotion`: where it is now, moving as it did over the step before this one (going into the
        contact: this step's motion has the contact's push in it); at rest if it was put back on the track since
        (or was not racing) then. None while it is not racing."""
        (now, last, before), dt = self._trail, self.dt
        if now[i] is None:
            return None
        distance, lateral, resets = now[i]
        prev, older = last[i], before[i]
        along = across = 0.0
        if prev is not None and older is not None and older[2] == prev[2] == resets:
            along, across = (prev[0] - older[0]) / dt, (prev[1] - older[1]) / dt
        return CarMotion(distance, lateral, along, across)

    def _record(self, contact, sim_time: float) -> tuple:
        """A new incident's records, one per car in it (None for a box)."""
        records = []
        for me, other in ((contact.a, contact.b), (contact.b, contact.a)):
            if me[0] != "car":
                records.append(None)
                continue
            race = self.races[me[1]]
            name = self.names[other[1]] if other[0] == "car" else f"obstacle_{other[1]}"
            records.append(self.rules.contact(race, race.clock(sim_time), name))
        return tuple(records)

    def _blame(self, contact, records: tuple) -> int | None:
        """Judge a contact of an incident nobody is at fault for yet: blame the car at fault, if any, and
        return the car it hit (None: nobody at fault, or a box)."""
        a, b = contact.a, contact.b
        if a[0] != "car" or b[0] != "car":  # a box: the car ran into it
            car = 0 if a[0] == "car" else 1
            records[car]["kind"] = "obstacle"
            self.rules.blame(self.races[(a, b)[car][1]], records[car], with_car=False)
            return None
        motion_a, motion_b = self._motion(a[1]), self._motion(b[1])
        if motion_a is None or motion_b is None:
            return None
        striker = None if contact.striker is None else (0 if contact.striker == a else 1)
        fault, kind = at_fault(motion_a, motion_b, striker, self.car_length, self.track_length)
        for record in records:
            record["kind"] = kind
        if fault is None:
            return None
        self.rules.blame(self.races[(a, b)[fault][1]], records[fault], with_car=True)
        return (a, b)[1 - fault][1]
