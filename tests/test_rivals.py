"""Agent files as rivals beside the learners: cars the race env drives from their own cameras (train/rivals.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from multirace.environment.race_env import RaceEnv
from multirace.train.cli import check_rivals
from multirace.train.config import make_config
from multirace.train.envs import TrainEnv
from multirace.train.rivals import RivalSeat, race_opponents


def test_a_rival_laps_from_its_own_camera_beside_a_state_learner():
    seat = RivalSeat(["racer"], np.random.default_rng(0))
    env = RaceEnv(num_cars=1, bots=(seat,), observation="state", race="head_to_head", laps=1)
    obs, _ = env.reset(seed=3)
    assert obs["car_0"].shape == env.observation_space("car_0").shape  # the learner still reads its state
    image = env._bot_observations[1]
    assert image.shape == (120, 160) and image.dtype == np.uint8 and image.std() > 5  # a real picture of the track
    steps = 0
    while env.races[1].racing and steps < 450:  # 30 s; the racer laps re:Invent 2018 in about 10
        env.step({"car_0": 0})
        steps += 1
    rival = env.races[1]
    assert rival.status == "finished" and rival.resets == 0
    assert seat.driver.steps == steps  # it chose a command at every step it raced


def test_a_rival_seat_draws_its_agent_at_every_race_start():
    seat = RivalSeat(["racer", "dagger_small"], np.random.default_rng(1))
    env = RaceEnv(num_cars=1, bots=(seat,), observation="state")
    drawn = set()
    for seed in range(8):
        env.reset(seed=seed)
        drawn.add(seat.driver.name)
        assert seat.driver.car == 1 and seat.driver.env is env
    assert len(drawn) == 2


def test_a_rival_reading_lidar_gets_its_scan():
    seat = RivalSeat(["racer_lidar"], np.random.default_rng(0))
    env = RaceEnv(num_cars=1, bots=(seat,), observation="state")
    env.reset(seed=0)
    reading = env._bot_observations[1]
    assert set(reading) == {"camera", "lidar"} and reading["lidar"].shape == (64,)


def test_training_envs_place_rivals_ahead_and_report_only_the_learners():
    env = TrainEnv([("reinvent_base", False)], num_cars=2, bots=("follow@1.0",), rivals=("racer",), rival_cars=1,
                   bots_ahead=3.0, observation="state", action_space=None)
    try:
        obs, infos = env.reset(seed=0)
        assert sorted(obs) == sorted(infos) == ["car_0", "car_1"]
        race_env = env.env
        assert race_env.total_cars == 4 and race_env.car_names[3] == "rival_0"
        start = race_env.races[3].distance
        assert start > race_env.races[2].distance > max(race_env.races[0].distance, race_env.races[1].distance) + 2.5
        # the bot, then the rival, started ahead of the learners (bots_ahead 3 m, 2 m apart)
        for _ in range(60):
            obs, rewards, *_ = env.step({"car_0": 0, "car_1": 0})
        assert sorted(rewards) == ["car_0", "car_1"]
        assert race_env.races[3].distance - start > 2.0  # the rival drove off on its own
    finally:
        env.close()


@pytest.mark.parametrize("settings, message", [
    ({"rivals": ("bot:follow@1.0",)}, "scripted cars go in `bots`"),
    ({"rivals": ("no_such_agent",)}, "no_such_agent"),
    ({"rivals": ("racer",), "rival_cars": 5}, "a race holds 1 to 8 cars"),
])
def test_bad_rivals_are_refused_before_training(settings, message):
    config = make_config("fast", **settings)
    with pytest.raises(ValueError, match=message):
        check_rivals(config)


def test_race_opponents_keep_bots_and_load_agents():
    opponents = race_opponents(("weave@1.2", "dagger_small"))
    assert opponents[0] == "weave@1.2" and opponents[1].name == "dagger_small"
    with pytest.raises(ValueError, match="bot:KIND@SPEED.*nor is 'no_such_agent' an agent file"):
        race_opponents(("no_such_agent",))


def test_training_infos_give_the_gap_to_the_car_ahead():
    """`gap_ahead` (what `distill_traffic` weighs labels by): metres along the track to the nearest car ahead."""
    env = TrainEnv([("reinvent_base", False)], num_cars=1, bots=("follow@0.5",), bots_ahead=1.5, observation="state",
                   action_space=str(Path(__file__).parents[1] / "agents" / "action_space_racer.json"))
    try:
        env.reset(seed=0)
        _, _, _, _, infos = env.step({"car_0": np.array([0.0, 0.5], np.float32)})
        race_env = env.env
        gap = race_env.races[1].distance - race_env.races[0].distance
        assert infos["car_0"]["gap_ahead"] == pytest.approx(gap, abs=0.3)  # reported points, not body centres
        assert 1.0 < infos["car_0"]["gap_ahead"] < 2.5
    finally:
        env.close()
