"""Overtakes as a measured skill: passes for position counted in real races, and the overtake scenarios."""
import pytest

from multirace.environment.rules import CarRace
from multirace.racing.entrant import BotController
from multirace.racing.overtakes import OvertakeRecorder, OvertakeTracker
from multirace.racing.runner import RaceConfig, run_race
from multirace.sim.car import CarSpec
from multirace.sim.tracks import load_track
from multirace.train.scenarios import SCENARIOS, placements, run_scenario, track_sites

LENGTH = 0.32  # m, a car


def test_a_faster_car_that_passes_a_slower_one_scores_an_attempted_and_completed_overtake():
    # bot:follow@0.8 on the pole never passes; bot:pass@2.0 behind it closes in and overtakes it once
    result = run_race([BotController("bot:follow@0.8"), BotController("bot:pass@2.0")],
                      RaceConfig(race="head_to_head", laps=1, seed=0), recorders=[OvertakeRecorder()])
    cars = {c["name"]: c for c in result["cars"]}
    follow, passer = cars["bot:follow@0.8"], cars["bot:pass@2.0"]
    assert passer["position"] == 1 and passer["collisions_caused"] == 0
    assert (passer["overtakes"], passer["overtakes_attempted"], passer["overtakes_completed"]) == (1, 1, 1)
    assert (follow["overtaken"], follow["overtakes"], follow["overtakes_attempted"]) == (1, 0, 0)


def _step(tracker, races, t, moves):
    for race, ds in zip(races, moves):
        race.distance += ds
    tracker.update(races, t, 1 / 15)


def test_a_pass_of_a_car_that_just_left_the_track_is_no_overtake():
    races = [CarRace("a", distance=0.0), CarRace("b", distance=0.6)]
    tracker = OvertakeTracker(2, LENGTH)
    tracker.update(races, 0.0, 1 / 15)
    races[1].off_tracks = 1  # b leaves the track and is put back: a drives by
    for k in range(1, 16):
        _step(tracker, races, k / 15, (0.1, 0.0))
    assert races[0].distance - races[1].distance > LENGTH
    assert tracker.counts[0]["overtakes"] == 0 and tracker.counts[1]["overtaken"] == 0
    for k in range(16, 110):  # b gets away again, then is passed for real, more than 2 s after its off-track
        _step(tracker, races, k / 15, (0.0 if k < 40 else 0.1, 0.2 if k < 40 else 0.0))
    assert tracker.counts[0]["overtakes"] == 1 and tracker.counts[1]["overtaken"] == 1
    # two attempts (closing in from the grid, then again): the void pass ended the first, the real one completed
    assert (tracker.counts[0]["overtakes_attempted"], tracker.counts[0]["overtakes_completed"]) == (2, 1)


def test_an_attempt_that_falls_back_fails_and_side_by_side_wobbles_are_no_passes():
    races = [CarRace("a", distance=0.0), CarRace("b", distance=0.5)]
    tracker = OvertakeTracker(2, LENGTH)
    tracker.update(races, 0.0, 1 / 15)
    for k in range(1, 5):  # a closes in to within a car length of b's tail
        _step(tracker, races, k / 15, (0.1, 0.0))
    assert tracker.counts[0]["overtakes_attempted"] == 1
    for k in range(5, 20):  # then falls back
        _step(tracker, races, k / 15, (0.0, 0.1))
    for k in range(20, 40):  # level, a few centimetres either way: no pass either way
        races[0].distance = races[1].distance + (0.05 if k % 2 else -0.05)
        tracker.update(races, k / 15, 1 / 15)
    assert tracker.counts[0]["overtakes"] == tracker.counts[1]["overtakes"] == 0
    assert tracker.counts[0]["overtakes_completed"] == 0


def test_scenario_placements_are_seeded_and_sit_on_the_tracks_features():
    track = load_track("reinvent_base")
    sites = track_sites(track)
    assert all(sites[kind] for kind in ("straight", "corner", "chicane"))
    for scenario in SCENARIOS:
        assert placements(scenario, track, sites, 3) == placements(scenario, track, sites, 3)
        slots = placements(scenario, track, sites, 3)
        assert len(slots) == 1 + len(scenario.others)
    alongside = next(s for s in SCENARIOS if s.site == "corner")
    sides = {placements(alongside, track, sites, seed)[0][1] > 0 for seed in range(8)}
    assert sides == {True, False}  # the agent's side of the car alongside is seeded
    assert placements(SCENARIOS[1], load_track("Oval_track"), track_sites(load_track("Oval_track")), 0) is None


@pytest.mark.parametrize("driver, success", [("bot:pass@2.0", True), ("bot:follow@1.0", False)])
def test_a_passer_clears_the_slower_car_on_a_straight_and_a_follower_does_not(driver, success):
    row = run_scenario(driver, SCENARIOS[0], seed=0)
    assert row["success"] is success
    assert (row["passed_at"] is not None) is success and row["caused"] == 0


def test_a_race_with_set_up_starts_hands_the_drivers_infos_of_where_their_cars_stand():
    """`RaceConfig.start` moves cars after the grid; their drivers' first infos read the moved cars, not the grid."""
    class Recording(BotController):
        first = None

        def act(self, observation, info):
            if self.first is None:
                self.first = dict(info)
            return super().act(observation, info)

    drivers = [Recording("bot:follow@0.8"), Recording("bot:follow@0.8")]
    start = ((0, (6.0, 0.0)), (1, (4.0, 0.2)))
    run_race(drivers, RaceConfig(race="head_to_head", laps=1, seed=0, max_steps=3, start=start))
    ahead = CarSpec().reported_point_offset  # a car is put with its body centre on the slot
    for driver, (_, (s, lateral)) in zip(drivers, start):
        info = driver.first
        assert info["projection_distance"] == pytest.approx(s + ahead, abs=0.05), info["projection_distance"]  # (curves)
        assert info["distance_from_center"] == pytest.approx(lateral, abs=0.02)
        assert info["is_left_of_center"] == (lateral > 0) and info["speed"] == 0.0
    assert drivers[0].first["rank"] == 1 and drivers[1].first["rank"] == 2  # car 0 is now the one ahead
