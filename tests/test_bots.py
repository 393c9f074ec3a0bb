"""Scripted bots: names, parsing errors and traffic manners."""
import pytest

import multirace
from multirace.bots import parse_bot
from multirace.race import RaceConfig, make_controller, run_race


def test_bot_names_read_back_as_typed():
    assert parse_bot("bot:follow@1.0").name == "bot:follow@1.0"
    assert parse_bot("lanes@2").name == "bot:lanes@2"
    with pytest.raises(ValueError, match="bot:KIND@SPEED"):
        parse_bot("bot:zigzag@1")
    with pytest.raises(ValueError, match="outside"):
        parse_bot("bot:follow@9")


def test_a_fast_bot_behind_a_slow_one_slows_instead_of_ramming():
    # bot 0 at 0.6 m/s starts ahead of bot 1 at 2.0 m/s in the same (centre) lane
    result = run_race([make_controller("bot:follow@0.6"), make_controller("bot:follow@2.0")],
                      RaceConfig(track="reinvent_base", race="head_to_head", laps=1, max_steps=300))
    assert all(car["collisions"] == 0 for car in result["cars"])


def test_env_bots_drive_laps_among_learning_cars():
    env = multirace.parallel_env(num_cars=1, bots=("follow@1.5", "lanes@1.0"), laps=1, race="head_to_head")
    env.reset(seed=0)
    while env.agents:
        env.step({"car_0": 7})  # straight ahead: the learning car leaves the track and is reset
    names = [race.name for race in env.races]
    assert names == ["car_0", "bot:follow@1.5", "bot:lanes@1.0"]
    assert all(race.status == "finished" for race in env.races[1:])
