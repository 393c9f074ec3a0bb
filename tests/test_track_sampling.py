"""Which run (track, direction) a training episode races on (train/track_sampling.py), and evaluations
over several tracks (`eval_tracks`: train/run.py `evaluation_runs`, `combined_evaluation`)."""
import numpy as np
import pytest

from multirace.train.config import SHIPPED_AGENTS, make_config
from multirace.train.envs import TrainEnv
from multirace.train.run import combined_evaluation, evaluation_runs
from multirace.train.track_sampling import CAP, FLOOR, RunSampler


def test_uniform_sampling_draws_as_before():
    """The default keeps the draws of the same seeds (training runs before the option raced the same tracks)."""
    sampler = RunSampler(7, "uniform")
    mine, before = np.random.default_rng(3), np.random.default_rng(3)
    assert [sampler.pick(mine) for _ in range(50)] == [int(before.integers(7)) for _ in range(50)]
    sampler.record(2, off_tracks=9, laps=1.0)
    assert np.allclose(sampler.weights(), 1 / 7)


def test_failures_race_the_hard_runs_more_often_and_drop_none():
    sampler = RunSampler(3, "failures")
    assert np.allclose(sampler.weights(), 1 / 3), "nothing raced yet: all alike"
    sampler.record(0, off_tracks=6, laps=2.0)  # 3 off-tracks a lap
    sampler.record(1, off_tracks=0, laps=2.0)  # clean
    weights = sampler.weights()
    assert weights[0] == pytest.approx(weights[2]), "a run not raced yet counts as the hardest seen"
    assert weights[0] == pytest.approx((FLOOR + 3.0) / (2 * (FLOOR + 3.0) + FLOOR))
    assert weights[1] > 0, "a clean run is still raced"
    rng = np.random.default_rng(0)
    draws = np.bincount([sampler.pick(rng) for _ in range(4000)], minlength=3) / 4000
    assert np.allclose(draws, weights, atol=0.03)


def test_a_run_score_is_a_running_mean_with_a_cap():
    sampler = RunSampler(2, "failures")
    sampler.record(0, off_tracks=100, laps=1.0)
    assert sampler.scores[0] == CAP, "one wild episode counts as CAP off-tracks a lap"
    sampler.record(0, off_tracks=0, laps=3.0)
    assert sampler.scores[0] == pytest.approx(CAP / 2)
    sampler.record(1, off_tracks=0, laps=0.0)
    assert np.isnan(sampler.scores[1]), "an episode that went nowhere and left no mark teaches nothing"


def test_bad_sampling_modes_are_refused_naming_the_setting():
    with pytest.raises(ValueError, match="track_sampling"):
        RunSampler(3, "hardest")
    with pytest.raises(ValueError, match="--set track_sampling: expected one of uniform, failures"):
        make_config("fast", track_sampling="hardest")


def test_train_env_scores_the_run_its_cars_left_the_track_on():
    """Real envs: cars steering hard left at full speed leave the track; the next reset scores that run."""
    env = TrainEnv([("Oval_track", False), ("reinvent_base", False)], num_cars=2, episode_steps=60,
                   action_space={"action_space_type": "continuous",
                                 "action_space": {"steering_angle": {"low": -30, "high": 30},
                                                  "speed": {"low": 0.5, "high": 4.0}}},
                   observation="state", track_sampling="failures")
    try:
        env.reset(seed=1)
        raced = env._run
        while env.agents:
            env.step({agent: np.array([30.0, 4.0], np.float32) for agent in env.possible_agents})
        assert np.isnan(env.sampler.scores).all()
        env.reset()
        assert env.sampler.scores[raced] > 1.0, "off the track more than once a lap"
        assert np.isnan(env.sampler.scores[1 - raced])
    finally:
        env.close()


def test_evaluations_over_several_tracks_add_up():
    config = make_config("fast", tracks=("reinvent_base", "Oval_track"), reverse="both",
                         eval_tracks=("Bowtie_track", "reinvent_base"))
    assert evaluation_runs(config) == [("reinvent_base", False), ("Bowtie_track", False), ("Bowtie_track", True),
                                       ("reinvent_base", True)], "the first run is not raced twice"
    rows = [{"laps": 2, "resets": 0, "total_time": 20.0, "best_lap": 9.5, "status": "finished"},
            {"laps": 1, "resets": 4, "total_time": None, "best_lap": 12.0, "status": "timed out"}]
    row = combined_evaluation(rows, laps=2)
    assert (row["laps"], row["target"], row["resets"], row["total_time"]) == (3, 4, 4, None)
    assert row["best_lap"] == 9.5 and row["status"] == "finished" and row["runs"] == 2


def test_evaluations_race_in_the_world_eval_randomize_perturbs():
    """`eval_randomize` judges the kept policy in the perturbed world `evaluate --randomize` races in: the same
    race as `multirace race` with that randomisation (seed 0), not the clean world's."""
    from multirace.racing.agentfile import AgentController
    from multirace.racing.runner import RaceConfig, run_race
    from multirace.train.run import evaluate_agent

    agent = SHIPPED_AGENTS / "racer.pt"
    config = make_config("fast", tracks=("reinvent_base",), eval_laps=1, eval_randomize="strong")
    judged = evaluate_agent(agent, config)
    raced = run_race([AgentController(agent, step_budget=5.0)],
                     RaceConfig(track="reinvent_base", race="time_trial", laps=1, seed=0, randomize="strong"))
    assert judged["total_time"] == pytest.approx(raced["cars"][0]["total_time"], abs=1e-3)  # the sum is rounded
    assert judged["resets"] == raced["cars"][0]["resets"]
    clean = evaluate_agent(agent, make_config("fast", tracks=("reinvent_base",), eval_laps=1))
    assert clean["total_time"] != pytest.approx(judged["total_time"], abs=1e-3)
