"""Training: a short PPO run writes an agent file that loads and races, and its returns rise.

Real env, real torch, real worker process; about a minute in all.
"""
import json
from pathlib import Path

import numpy as np
import pytest

from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import AgentController, load_agent
from multirace.racing.runner import RaceConfig, run_race
from multirace.train.config import PRESETS, TrainConfig, describe, make_config
from multirace.train.nature import Nature, UNCERTAINTY_SET, scale_randomization
from multirace.environment.randomize import Randomization


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from multirace.train.ppo import train

    out = tmp_path_factory.mktemp("train") / "ppo_test.pt"
    # an iteration budget, not a time one: the same learning on an idle and on a busy machine
    config = make_config("tiny", tracks=("Oval_track",), minutes=10, max_iterations=16, seed=1, progress=False)
    summary = train(config, out)
    return out, summary


def test_agent_file_loads_and_races(trained):
    out, summary = trained
    agent = load_agent(out, step_budget=None)
    assert agent.metadata["training_algorithm"] == "clipped_ppo"
    assert agent.metadata["training"]["agent_steps"] == summary["agent_steps"] > 0
    result = run_race([AgentController(out, step_budget=0.5)],
                      RaceConfig(track="Oval_track", race="time_trial", laps=1, max_steps=60))
    car = result["cars"][0]
    assert car["status"] in ("finished", "not_finished")  # drove, did not forfeit
    assert car["progress"] > 0
    assert out.with_suffix(".png").stat().st_size > 1000  # learning curve
    history = json.loads(out.with_suffix(".train.json").read_text())["history"]
    assert len(history) == summary["iterations"]
    assert (out.parent / (out.stem + ".ckpt") / "checkpoint.pt").exists()


def test_returns_rise_on_a_simple_track(trained):
    _, summary = trained
    rewards = [h["mean_reward"] for h in summary["history"]]
    assert len(rewards) == 16  # max_iterations ends the run
    k = max(3, len(rewards) // 4)
    first, last = np.mean(rewards[:k]), np.mean(rewards[-k:])
    # 16 tiny iterations: seed 1 rises 0.71 -> 0.81 (the pooled inputs' rounding moved it from just over 0.1)
    assert last > first + 0.05, f"mean reward per step did not rise: first {first:.3f}, last {last:.3f}"


def test_resume_continues_from_the_checkpoint(trained, tmp_path):
    from multirace.train.ppo import train

    out, summary = trained
    config = make_config("tiny", tracks=("Oval_track",), minutes=0.05, seed=1, progress=False)
    config.deepracer_log = False
    resumed = train(config, tmp_path / "resumed.pt", resume=out.parent / (out.stem + ".ckpt") / "checkpoint.pt")
    assert not (tmp_path / "resumed.deepracer").exists()
    assert resumed["agent_steps"] > summary["agent_steps"]
    assert resumed["iterations"] > summary["iterations"]


def test_training_writes_a_folder_deepracer_utils_reads_as_deepracer_for_cloud_output(trained):
    """out.deepracer/: the agent's action space, the config's PPO settings under DeepRacer's names, one
    sim-trace per PPO iteration with a row per learning car per step, the exact action breakdown, and a
    training-metrics entry per finished learner episode."""
    logs = pytest.importorskip("deepracer.logs")
    out, summary = trained
    folder = out.with_name(out.stem + ".deepracer")
    metadata = load_agent(out, step_budget=None).metadata
    space = load_action_space(metadata)
    reader = logs.DeepRacerLog(str(folder))
    assert reader.fh.type.name == "DRFC_MODEL_SINGLE_WORKERS"  # not UNKNOWN_FOLDER
    reader.load_training_trace()
    df = reader.dataframe()
    assert sorted(df["iteration"].unique()) == list(range(summary["iterations"]))
    assert len(df) == summary["agent_steps"]
    hyperparameters = reader.hyperparameters()
    assert (hyperparameters["lr"], hyperparameters["batch_size"], hyperparameters["num_epochs"],
            hyperparameters["discount_factor"]) == (1e-3, 128, 4, 0.95)
    assert reader.action_space() == metadata["action_space"]
    chosen = sorted(set(zip(df["action"], df["steering_angle"], df["speed"])))
    assert len(chosen) > 1 and all(space.actions[a] == (steer, speed) for a, steer, speed in chosen)
    assert len(logs.ActionBreakdownUtils.determine_action_names(df)) == len(chosen)
    metrics = logs.TrainingMetrics(None, fname=str(folder / "metrics" / "TrainingMetrics.json"))
    assert len(metrics.getTraining()) == sum(h["episodes"] for h in summary["history"]) > 0


def test_config_presets_and_docs():
    deepracer = make_config("deepracer")
    assert (deepracer.minibatch_size, deepracer.lr, deepracer.ent_coef, deepracer.gamma, deepracer.epochs,
            deepracer.clip, deepracer.gae_lambda) == (64, 3e-4, 0.01, 0.999, 10, 0.2, 0.95)
    assert set(PRESETS) >= {"fast", "deepracer", "tiny"}
    text = describe()
    for line in text.splitlines():
        assert line.split(": ", 1)[1].strip(), f"undocumented setting: {line}"
    with pytest.raises(ValueError, match="unknown"):
        make_config("nope")
    assert TrainConfig().batch_size == 2 * 4 * 256


def test_nature_prefers_the_worst_perturbation():
    nature = Nature(seed=0)
    for k in range(len(UNCERTAINTY_SET)):
        nature.update(k, 1.0)
    nature.update(3, 0.0)
    nature.update(3, 0.0)
    w = nature.weights()
    assert int(np.argmax(w)) == 3 and w.sum() == pytest.approx(1.0) and w.min() > 0
    for _, cfg in UNCERTAINTY_SET:
        Randomization.from_config(cfg)
    off = scale_randomization(Randomization.preset("strong"), 0.0)
    assert not off.enabled


def test_evaluate_rows_with_perturbation_and_traffic(trained, tmp_path):
    from multirace.train.evaluate import plot_report, race_agent, summarise

    out, _ = trained
    perturbed = race_agent(out, "Oval_track", laps=1, randomize="mild", max_steps=40)
    traffic = race_agent(out, "Oval_track", laps=1, bots=("follow@0.8",), race="head_to_head", max_steps=40)
    for row in (perturbed, traffic):
        assert row["status"] != "forfeit", row["reason"]
        assert 0.0 <= row["completion"] <= 1.0 and row["laps_driven"] >= 0
    assert traffic["position"] in (1, 2)
    report = {"agent": str(out), "reference_track": "Oval_track", "laps": 1, "trained_on": ["Oval_track"],
              "held_out": [dict(perturbed, perturbation="x")], "perturbations": [dict(perturbed, perturbation="none"),
                                                                                dict(perturbed, perturbation="mild")],
              "traffic": [traffic]}
    report["summary"] = summarise(report)
    assert report["summary"]["completion_drop_points"] == 0.0
    plot_report([report], tmp_path / "eval.png")
    assert (tmp_path / "eval.png").stat().st_size > 1000


def _ram(collision_penalty, terminate_collision=False, proximity_penalty=0.0, braking_penalty=0.0):
    """Three cars on the start grid: car_2 (last) drives at 2 m/s into the cars ahead, which crawl at 0.1 m/s."""
    from multirace.train.envs import TrainEnv

    space = {"action_space_type": "discrete",
             "action_space": [{"steering_angle": 0, "speed": 0.1}, {"steering_angle": 0, "speed": 2.0}]}
    env = TrainEnv([("reinvent_base", False)], num_cars=3, action_space=space, camera=(30, 40),
                   collision_penalty=collision_penalty, terminate_collision=terminate_collision,
                   proximity_penalty=proximity_penalty, braking_penalty=braking_penalty)
    env.reset(seed=0)
    steps = []
    for _ in range(12):
        _, rewards, _, _, infos = env.step({"car_0": 0, "car_1": 0, "car_2": 1})
        steps.append((rewards, infos))
    record = [race.collisions for race in env.env.races]
    env.close()
    return steps, record


def test_collision_penalty_hits_the_striker_only():
    plain, _ = _ram(0.0)
    penalised, record = _ram(10.0, terminate_collision=True)
    caused = [k for k, (_, infos) in enumerate(penalised) if infos["car_2"]["caused"]]
    assert caused, f"car_2 never struck a car: {record}"
    assert any(c["caused"] for c in record[2]) and not any(c["caused"] for c in record[0] + record[1])
    hit = [k for k, (_, infos) in enumerate(penalised) if infos["car_0"]["collisions"] or infos["car_1"]["collisions"]]
    assert hit, "the rammed car saw no contact"
    for (r0, i0), (r1, i1) in zip(plain, penalised):  # same seed, same drive: rewards differ by the penalty only
        for car in ("car_0", "car_1"):
            assert r1[car] == pytest.approx(r0[car]) and not i1[car]["caused"]
        assert r1["car_2"] == pytest.approx(r0["car_2"] - 10.0 * i1["car_2"]["caused"])
        # terminate_collision: the striker's training episode ends with the strike, nobody else's
        assert i1["car_2"]["train_done"] == bool(i1["car_2"]["caused"]) and not i0["car_2"]["train_done"]
        assert not i1["car_0"]["train_done"] and not i1["car_1"]["train_done"]
        assert not i1["car_2"]["time_limit"]  # a crash is a real end: no bootstrapping


def test_proximity_penalty_grows_as_the_striker_closes_in_before_it_strikes():
    plain, _ = _ram(0.0)
    shaped, _ = _ram(0.0, proximity_penalty=1.0)
    first_strike = next(k for k, (_, infos) in enumerate(shaped) if infos["car_2"]["caused"])
    costs = [r0["car_2"] - r1["car_2"] for (r0, _), (r1, _) in zip(plain, shaped)]
    assert all(-1e-9 <= c <= 1.0 + 1e-9 for c in costs)
    before = costs[:first_strike + 1]
    assert before[0] == pytest.approx(0.0) and max(before) > 0.3, before  # far behind: nothing; close: a real cost
    assert before == sorted(before), before  # the closer, the costlier
    assert all(r0["car_0"] == pytest.approx(r1["car_0"]) for (r0, _), (r1, _) in zip(plain, shaped))  # nothing ahead of it


def test_proximity_penalty_counts_a_car_alongside_with_too_little_room():
    from multirace.train.envs import TrainEnv

    env = TrainEnv([("reinvent_base", False)], num_cars=2, camera=(30, 40), proximity_penalty=1.0)
    env.reset(seed=0)
    width, room = env.env.car_spec.width, env.weights.proximity_side_room

    def cost(lateral_gap, behind_by, ahead_by=5.0):
        """The car on the centre line, the other `behind_by` m behind its point, `lateral_gap` m to its left."""
        here = 3.0
        return env._closing_in({"objects_distance": [here - behind_by, here + ahead_by], "closest_objects": [0, 1],
                                "projection_distance": here, "distance_from_center": 0.0, "is_left_of_center": True,
                                "objects_distance_from_center": [lateral_gap, 0.6],
                                "objects_left_of_center": [True, True]})

    assert cost(width, 0.1) == pytest.approx(1.0)  # side by side, sides touching
    assert 0.0 < cost(width + room / 2, 0.1) < 1.0
    assert cost(width + room, 0.1) == pytest.approx(0.0)  # enough room to the side
    assert cost(width, env.env.car_spec.length + 0.05) == pytest.approx(0.0)  # passed: no longer alongside
    env.close()


def test_braking_penalty_is_the_braking_needed_not_to_rear_end_the_car_ahead():
    """Closing in on a slower car in its lane costs the braking that would stop the closing within the gap over
    the car's braking: more for a faster approach or a shorter gap, 1 at the limit; nothing when it is not
    closing in or the car ahead is in the other lane; and in a rear-end run the cost comes before the strike."""
    from multirace.train.envs import TrainEnv

    env = TrainEnv([("reinvent_base", False)], num_cars=2, camera=(30, 40), braking_penalty=1.0)
    env.reset(seed=0)
    spec = env.env.car_spec

    def cost(speed, other_speed, gap, lateral_gap=0.0):
        """The car on the centre line at `speed`, the other `gap` m bumper to bumper ahead, `lateral_gap` left."""
        here = 3.0
        return env._braking_needed({"objects_distance": [here - 5.0, here + spec.length + gap],
                                    "closest_objects": [0, 1], "projection_distance": here,
                                    "distance_from_center": 0.0, "is_left_of_center": True,
                                    "objects_distance_from_center": [0.0, lateral_gap],
                                    "objects_left_of_center": [True, True], "objects_speed": [0.0, other_speed]},
                                   speed)

    assert cost(2.0, 1.0, 0.5) == pytest.approx(1.0 ** 2 / (2 * 0.5) / spec.brake)  # v^2 / 2d over the brakes
    assert cost(2.0, 1.0, 0.2) > cost(2.0, 1.0, 0.5) > cost(2.0, 1.0, 2.0) > 0.0  # the nearer, the costlier
    assert cost(3.0, 1.0, 0.5) > cost(2.0, 1.0, 0.5)  # the faster the approach, the costlier
    assert cost(4.0, 0.5, 0.3) == pytest.approx(1.0)  # past the brakes' limit: capped
    assert cost(1.0, 1.5, 0.3) == 0.0 and cost(1.0, 1.0, 0.3) == 0.0  # not closing in
    assert cost(3.0, 1.0, 0.5, lateral_gap=spec.width + 0.2) == 0.0  # the car ahead is in the other lane
    env.close()

    plain, _ = _ram(0.0)
    shaped, _ = _ram(0.0, braking_penalty=1.0)
    first_strike = next(k for k, (_, infos) in enumerate(shaped) if infos["car_2"]["caused"])
    costs = [r0["car_2"] - r1["car_2"] for (r0, _), (r1, _) in zip(plain, shaped)]
    assert all(-1e-9 <= c <= 1.0 + 1e-9 for c in costs)
    assert costs[0] == pytest.approx(0.0) and max(costs[:first_strike]) > 0.1, costs  # warned before it strikes
    assert all(r0["car_0"] == pytest.approx(r1["car_0"]) for (r0, _), (r1, _) in zip(plain, shaped))  # nothing ahead


def test_bots_ahead_start_on_the_centre_line_in_front_of_the_learning_cars_and_drive_on():
    from multirace.train.envs import BOT_SPACING, TrainEnv

    env = TrainEnv([("reinvent_base", False)], num_cars=2, bots=("follow@1.0", "follow@1.0"), camera=(30, 40),
                   bots_ahead=3.0, episode_steps=15)
    _, infos = env.reset(seed=0)
    start = env.env.race_state.cars
    for k, bot in enumerate(start[2:]):
        assert bot.s == pytest.approx(3.0 + BOT_SPACING * k, abs=0.1) and abs(bot.lateral) < 0.02
    length = env.env.track.length
    for i, agent in enumerate(("car_0", "car_1")):  # the reset's infos see the bots where they were moved to
        nearest = min((other.s - start[i].s) % length for other in start if other.index != i)
        assert infos[agent]["gap_ahead"] == pytest.approx(nearest, abs=0.05)
    assert max(info["gap_ahead"] for info in infos.values()) < 4.0  # the leading learner has a bot 3 m ahead
    for step in range(15):
        _, _, _, _, infos = env.step({"car_0": 0, "car_1": 0})
        last = step == 14  # the step limit ends every car's episode, marked for bootstrapping; an off-track is not
        assert all(info["train_done"] == (last or info["off_track"]) for info in infos.values())
        assert all(info["time_limit"] == (last and not info["off_track"]) for info in infos.values())
    assert all(race.distance > 3.5 for race in env.env.races[2:])  # the bots drive on from there
    env.close()


def test_bots_ahead_spread_starts_the_bots_at_random_gaps_each_episode():
    from multirace.train.envs import BOT_SPACING, TrainEnv

    env = TrainEnv([("reinvent_base", False)], num_cars=2, bots=("follow@1.0", "follow@1.0"), camera=(30, 40),
                   bots_ahead=3.0, bots_ahead_spread=8.0)
    starts = []
    for seed in range(4):
        env.reset(seed=seed)
        bots = [car.s for car in env.env.race_state.cars[2:]]
        for k, s in enumerate(bots):
            assert 3.0 + BOT_SPACING * k - 0.1 < s < 3.0 + BOT_SPACING * k + 8.0 + 0.1
        starts.append(tuple(round(s, 1) for s in bots))
    assert len(set(starts)) == 4, starts
    env.close()


def test_race_preset_sets_traffic_and_penalty_and_leaves_the_default_alone():
    race = make_config("race")
    assert race.bots and race.opponent_pool and race.collision_penalty > 0 and race.proximity_penalty > 0 and race.eval_bots
    fast = make_config("fast")
    assert fast.collision_penalty == 0.0 and fast.proximity_penalty == 0.0 and not fast.bots  # the default is unchanged


def test_expert_labels_name_the_pass_drivers_action_and_see_the_traffic():
    from multirace.train.envs import TrainEnv

    def labels(bots):
        env = TrainEnv([("reinvent_base", False)], num_cars=1, bots=bots, camera=(30, 40), episode_steps=4,
                       bots_ahead=1.0, expert_labels=True)
        _, infos = env.reset(seed=0)
        seen = [infos["car_0"]["expert_action"]]
        for _ in range(4):
            _, _, _, _, infos = env.step({"car_0": seen[-1] if seen[-1] >= 0 else 0})
            seen.append(infos["car_0"]["expert_action"])
        size = env.env.actions.space.n
        env.close()
        return seen, size

    empty, size = labels(())
    assert all(0 <= a < size for a in empty[:-1]) and empty[-1] == -1  # the step limit's label is marked missing
    slow_car_ahead, _ = labels(("follow@0.3",))  # a crawling car 1 m ahead on the centre line: steer round it
    assert slow_car_ahead[:-1] != empty[:-1]


def test_expert_loss_pulls_the_policy_toward_the_pass_driver(tmp_path):
    from multirace.train.ppo import train

    config = make_config("tiny", tracks=("Oval_track",), minutes=10, max_iterations=8, seed=2, progress=False,
                         expert_coef=2.0, bots=("follow@0.5",))
    losses = [h["expert_loss"] for h in train(config, tmp_path / "expert.pt")["history"]]
    assert len(losses) == 8 and np.mean(losses[-3:]) < 0.8 * losses[0], losses  # from a near-uniform policy


def test_reward_scale_keeps_discounted_returns_near_unit_size():
    from multirace.train.ppo import RewardScale

    rng = np.random.default_rng(0)
    scale, gamma = RewardScale(8, 0.99), 0.99
    raw_returns, scaled_returns, raw, scaled = [], [], np.zeros(8), np.zeros(8)
    for t in range(3000):  # 2 m/s progress rewards, episodes of 500 steps
        rewards = rng.normal(2.0, 0.5, 8)
        done = np.full(8, t % 500 == 499)
        out = scale(rewards, done)
        raw, scaled = raw * gamma + rewards, scaled * gamma + out
        raw_returns.append(raw.copy()), scaled_returns.append(scaled.copy())
        raw[done], scaled[done] = 0.0, 0.0
    assert np.mean(raw_returns[1000:]) > 100  # value targets in the hundreds without it
    assert 0.3 < np.std(scaled_returns[1000:]) < 3.0 and np.mean(scaled_returns[1000:]) < 20


REWARD_FILES = Path(__file__).parent / "reward_files"


def test_train_command_counts_every_evaluation_run_in_its_closing_line(tmp_path, capsys):
    from multirace.cli import main

    assert main(["train", "--config", "tiny", "--envs", "1", "--cars", "1", "--no-progress", "--set", "max_iterations=1",
                 "--set", "eval_laps=1", "--set", 'eval_tracks=["Bowtie_track"]', "--out", str(tmp_path / "a.pt")]) == 0
    summary = " ".join(capsys.readouterr().out.split())  # one lap on the training track and one on Bowtie
    assert "first clean 2/2 evaluation (no off-track)" in summary and "first 2/2 counting resets" in summary


def test_train_command_takes_a_reward_file_and_names_a_bad_one(tmp_path, capsys):
    from multirace.cli import main

    out = tmp_path / "agent.pt"
    tiny = ["--config", "tiny", "--minutes", "0.05", "--no-progress", "--envs", "1", "--cars", "1"]
    assert main(["train", *tiny, "--reward", str(REWARD_FILES / "centerline.py"), "--out", str(out)]) == 0
    summary = " ".join(capsys.readouterr().out.split())  # the clean evaluation first, then the one with resets
    assert summary.index("first clean 3/3 evaluation (no off-track)") < summary.index("first 3/3 counting resets")
    agent = load_agent(out, step_budget=None)
    assert agent.metadata["training"]["reward"].endswith("centerline.py")
    assert main(["train", *tiny, "--reward", str(REWARD_FILES / "bad_raises.py"),
                 "--out", str(tmp_path / "bad.pt")]) == 2
    err = capsys.readouterr().err
    assert "bad_raises.py" in err and "Traceback" not in err
    assert not (tmp_path / "bad.pt").exists() and not (tmp_path / "bad.ckpt").exists()
