"""bot:racingline, the reference lap of every track, and the calibration against DeepRacer's records."""
import json

import numpy as np
import pytest

from multirace.racing.runner import RaceConfig, make_controller, run_race
from multirace.resources import list_tracks
from multirace.sim.racingline import plan_racing_line
from multirace.sim.tracks import load_track

# best laps of the DeepRacer community on virtual tracks (aws-deepracer-community/deepracer-race-data)
RECORDS = {"2022_summit_speedway": 7.257, "Monaco": 18.196}


def best_lap(driver, track, laps=2, reverse=False, seed=0):
    result = run_race([make_controller(driver)], RaceConfig(track=track, reverse=reverse, race="time_trial",
                                                            laps=laps, seed=seed))
    return result["cars"][0]


@pytest.mark.parametrize("track", sorted(RECORDS))
def test_the_racing_line_laps_just_under_the_deepracer_record(track):
    car = best_lap("bot:racingline", track)
    assert car["status"] == "finished" and car["off_tracks"] == 0
    assert 0.85 * RECORDS[track] <= car["best_lap"] <= RECORDS[track], json.dumps(car)


def test_centre_line_at_full_speed_slides_off_the_hairpins_and_a_gentle_one_laps_clean():
    assert best_lap("bot:follow@4.0", "reinvent_base")["off_tracks"] > 0
    gentle = best_lap("bot:follow@1.5", "reinvent_base")
    assert gentle["off_tracks"] == 0 and gentle["laps"] == 2


def test_a_scaled_racing_line_is_a_gentler_driver():
    full, gentle = best_lap("bot:racingline", "reinvent_base"), best_lap("bot:racingline@0.8", "reinvent_base")
    assert gentle["off_tracks"] == 0 and gentle["best_lap"] > full["best_lap"] * 1.1


def test_racing_line_keeps_the_bots_courtesy_in_traffic():
    result = run_race([make_controller("bot:racingline"), make_controller("bot:follow@1.0")],
                      RaceConfig(track="reInvent2019_track", race="head_to_head", laps=1, seed=1))
    cars = {c["name"]: c for c in result["cars"]}
    assert cars["bot:racingline"]["collisions_caused"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("reverse", [False, True], ids=["forward", "reverse"])
@pytest.mark.parametrize("track", list_tracks())
def test_racing_line_laps_every_shipped_track_clean(track, reverse):
    line = plan_racing_line(load_track(track, reverse=reverse))
    assert np.all(line.speed > 0.5) and line.lap_time > 0
    car = best_lap("bot:racingline", track, laps=1, reverse=reverse)
    assert car["status"] == "finished" and car["off_tracks"] == 0, json.dumps(car)
    assert car["best_lap"] < 1.25 * line.lap_time + 1.5  # it drives close to its plan (the lap starts standing)
