"""Overtakes as a measured skill: passes for position on track, attempted and completed.

`OvertakeRecorder` is a `run_race` recorder. Every step it compares each pair
of racing cars by race distance (metres driven along the centre line since
the start line, laps included), with a hysteresis of half a car length: a car
is *behind* another once it trails it by more than that, *ahead* once it
leads it by more than that. Per car, in the result record:

- ``overtakes``: passes for position on track: from behind another car to
  ahead of it, while both race. A pass within `VOID_SECONDS` of either car's
  off-track (and so its reset) does not count: it came from the other car's
  mistake or from being put back, not from racing. Penalties never move a car
  on the road, so no overtake comes from one; lapping a car is no pass either
  (the lapping car was ahead in race distance already).
- ``overtaken``: the same seen from the car passed.
- ``overtakes_attempted``: times the car closed in on a car ahead: within one
  car length of its tail (nose to tail) and faster than it by at least
  `CLOSING_SPEED`. An attempt lasts until it is ``completed`` (an overtake of
  that car) or fails: the car falls back more than `GIVE_UP_LENGTHS` car
  lengths behind, either run ends, the pass is void, or the race ends.
- ``overtakes_completed``: attempts that ended in an overtake.
"""
from __future__ import annotations

VOID_SECONDS = 2.0  # s: a pass this soon after either car's off-track is void
CLOSING_SPEED = 0.05  # m/s faster than the car ahead: closing in
ATTEMPT_LENGTHS = 1.0  # car lengths, nose to tail: closer than this and closing is an attempt
GIVE_UP_LENGTHS = 3.0  # car lengths, nose to tail: farther back than this an attempt has failed
FIELDS = ("overtakes", "overtaken", "overtakes_attempted", "overtakes_completed")


class OvertakeTracker:
    """Counts overtakes of every car of a race from its cars' race distances, step by step."""

    def __init__(self, num_cars: int, car_length: float):
        self.length = car_length
        self.counts = [dict.fromkeys(FIELDS, 0) for _ in range(num_cars)]
        self._side: dict = {}  # (i, j) -> -1 (i behind j) or +1 (i ahead of j)
        self._attempts: set = set()  # (i, j): i is attempting to pass j
        self._last: list = [None] * num_cars  # race distance at the last step
        self._off: list = [(0, -1e9)] * num_cars  # (off-tracks seen, sim time of the last one)

    def update(self, races, sim_time: float, dt: float) -> None:
        """Take one step: `races` are the env's `CarRace`s after it, at `sim_time`."""
        for i, race in enumerate(races):
            if race.off_tracks != self._off[i][0]:
                self._off[i] = (race.off_tracks, sim_time)
        speeds = [None if last is None else (race.distance - last) / dt for race, last in zip(races, self._last)]
        self._last = [race.distance for race in races]
        racing = [i for i, race in enumerate(races) if race.racing]
        for i in racing:
            for j in racing:
                if i != j:
                    self._pair(i, j, races[i].distance - races[j].distance, speeds, sim_time)
        for i, j in [pair for pair in self._attempts if not (races[pair[0]].racing and races[pair[1]].racing)]:
            self._attempts.discard((i, j))

    def _pair(self, i: int, j: int, gap: float, speeds: list, sim_time: float) -> None:
        """Car i against car j, `gap` metres ahead of it (negative: behind)."""
        margin = self.length / 2
        side = -1 if gap < -margin else (1 if gap > margin else self._side.get((i, j)))
        before = self._side.get((i, j))
        self._side[(i, j)] = side
        nose_to_tail = -gap - self.length
        if (i, j) in self._attempts and side == -1 and nose_to_tail > GIVE_UP_LENGTHS * self.length:
            self._attempts.discard((i, j))
        elif side == -1 and nose_to_tail <= ATTEMPT_LENGTHS * self.length and (i, j) not in self._attempts \
                and speeds[i] is not None and speeds[j] is not None and speeds[i] - speeds[j] >= CLOSING_SPEED:
            self._attempts.add((i, j))
            self.counts[i]["overtakes_attempted"] += 1
        if before == -1 and side == 1:
            attempted = (i, j) in self._attempts
            self._attempts.discard((i, j))
            if all(sim_time - self._off[k][1] > VOID_SECONDS for k in (i, j)):
                self.counts[i]["overtakes"] += 1
                self.counts[j]["overtaken"] += 1
                self.counts[i]["overtakes_completed"] += int(attempted)


class OvertakeRecorder:
    """A `run_race` recorder that adds every car's overtake figures (`FIELDS`) to the result's cars."""

    def start(self, env) -> None:
        self.tracker = OvertakeTracker(len(env.race_state.cars), env.car_spec.length)
        self.step(env)

    def step(self, env, observations=None, rewards=None, infos=None) -> None:
        state = env.race_state
        self.tracker.update([car.race for car in state.cars], state.time, state.dt)

    def finish(self, env, result: dict) -> None:
        for car in result["cars"]:
            car.update(self.tracker.counts[int(car["car"].split("_")[1])])
