"""DeepRacer sim-trace CSV from a real race, and `multirace plot` on it."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import multirace
from multirace.cli import main
from multirace.deepracer.logs import EvaluationMetricsRecorder, TrainingLog
from multirace.environment.actions import default_metadata, load_action_space
from multirace.racing.entrant import BotController
from multirace.racing.runner import RaceConfig, run_race
from multirace.recording.plot import plot_simtrace
from multirace.recording.simtrace import SimTraceRecorder, SimTraceWriter, read_simtrace
from helpers import Wild

COLUMNS = ["episode", "steps", "X", "Y", "yaw", "steer", "throttle", "action", "reward", "done",
           "all_wheels_on_track", "progress", "closest_waypoint", "track_len", "tstamp", "episode_status",
           "pause_duration"]


class Capture:
    def start(self, env):
        self.rows = {}  # (car, step) -> (info, reward), while the car races and on the step it ends
        self.ended = [False] * len(env.races)

    def step(self, env, observations, rewards, infos):
        for i, agent in enumerate(env.possible_agents):
            if not self.ended[i]:
                self.rows[(i, env.steps)] = (infos[agent], rewards[agent])
                self.ended[i] = not env.races[i].racing

    def finish(self, env, result):
        self.result = result


@pytest.fixture(scope="module")
def trace(tmp_path_factory):
    path = tmp_path_factory.mktemp("simtrace") / "race.csv"
    capture = Capture()
    result = run_race([Wild("bot:follow@1.5"), BotController("bot:follow@1.0")],
                      RaceConfig(laps=1, race="time_trial", seed=3), recorders=[SimTraceRecorder(path), capture])
    return path, capture, result


def test_exact_columns(trace):
    path, _, _ = trace
    with open(path, newline="") as f:
        header = next(csv.reader(f))
    assert header == COLUMNS
    rows = read_simtrace(path)
    assert all(len(r) == len(COLUMNS) for r in rows)


def test_values_match_the_race(trace):
    path, capture, result = trace
    rows = read_simtrace(path)
    for car in (0, 1):
        mine = [r for r in rows if r["episode"] == car]
        steps = [int(r["steps"]) for r in mine]
        assert steps == list(range(1, len(mine) + 1)), "one row per step while the car races"
        truth = [capture.rows[(car, s)] for s in steps]
        np.testing.assert_allclose([r["X"] for r in mine], [t[0]["x"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["Y"] for r in mine], [t[0]["y"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["yaw"] for r in mine], [t[0]["heading"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["throttle"] for r in mine], [t[0]["speed"] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["reward"] for r in mine], [t[1] for t in truth], atol=1e-9)
        np.testing.assert_allclose([r["tstamp"] for r in mine], np.array(steps) / 15, atol=1e-5)
        # progress rises to 100 at the lap's end, which is the last row (done)
        assert mine[-1]["episode_status"] == "lap_complete" and mine[-1]["progress"] == 100.0
        assert mine[-1]["done"] and not any(r["done"] for r in mine[:-1])
        assert mine[0]["episode_status"] == "prepare"
        on_track = [r["progress"] for r in mine[:-1] if r["episode_status"] == "in_progress"]
        assert on_track[-1] > 95 and on_track[0] < 5
        assert sum(b < a - 1 for a, b in zip(on_track, on_track[1:])) <= 1  # no falling except a reset
        assert all(r["track_len"] == pytest.approx(17.709, abs=0.01) for r in mine)


def test_off_track_is_marked_with_its_penalty(trace):
    path, capture, result = trace
    rows = read_simtrace(path)
    wild = [r for r in rows if r["episode"] == 0]
    off = [r for r in wild if r["episode_status"] == "off_track"]
    expected = [s for (car, s), (info, _) in capture.rows.items() if car == 0 and "off_track" in info["events"]]
    assert off and [int(r["steps"]) for r in off] == sorted(expected)
    assert all(r["pause_duration"] == 2.0 and not r["all_wheels_on_track"] for r in off)
    assert sum(r["pause_duration"] for r in wild) == pytest.approx(2.0 * len(off))
    by_name = {car["name"]: car for car in result["cars"]}
    assert by_name["bot:follow@1.5"]["resets"] == len(off)
    assert all(r["episode_status"] != "off_track" for r in rows if r["episode"] == 1)


def test_writer_for_training_loops(tmp_path, trace):
    _, capture, _ = trace
    path = tmp_path / "0-iteration.csv"
    with SimTraceWriter(path) as log:
        for (car, step), (info, reward) in sorted(capture.rows.items()):
            if car == 0:
                log.write_step(info, reward=reward, episode=7, action=3)
    rows = read_simtrace(path)
    assert rows and {r["episode"] for r in rows} == {7} and {r["action"] for r in rows} == {"3"}


def test_plot_writes_a_png_of_the_track_and_path(trace, tmp_path, capsys):
    path, _, _ = trace
    out = tmp_path / "trace.png"
    assert main(["plot", str(path), "--out", str(out)]) == 0
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    non_white = (image < 240).any(axis=2).mean()
    assert non_white > 0.02  # lines and points drawn, not a blank canvas
    one = tmp_path / "one.png"  # a race's log has a row of panels per car, not one cloud of every car's points
    plot_simtrace(path, one, episodes=[0])
    assert image.shape[0] == 2 * cv2.imread(str(one)).shape[0]
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    assert (hsv[..., 1] > 100).sum() > 500  # coloured path points (speed / reward colour maps)


def _drfc_evaluation_folder(folder, metadata: dict, trace_csv) -> None:
    """A DeepRacer-for-Cloud model folder holding one evaluation sim-trace, as DRFC lays it out."""
    (folder / "model").mkdir(parents=True)
    (folder / "model" / "model_metadata.json").write_text(json.dumps(metadata))
    stream = folder / "evaluation-20260101000000" / "evaluation-simtrace"
    stream.mkdir(parents=True)
    (stream / "0-iteration.csv").write_bytes(trace_csv.read_bytes())


def test_race_simtrace_has_the_commanded_actions_deepracer_utils_breaks_down(tmp_path):
    """`multirace race --simtrace` writes the action index and its exact steer and throttle; deepracer-utils
    reads the trace as a DeepRacer-for-Cloud evaluation and lists only the actions the agent chose."""
    logs = pytest.importorskip("deepracer.logs")
    trace_csv = tmp_path / "race.csv"
    assert main(["race", "dagger_small", "bot:follow@1.0", "--laps", "1", "--max-steps", "120",
                 "--simtrace", str(trace_csv)]) == 0
    agent = multirace.load_agent("dagger_small")
    actions = agent.agent.action_space.actions
    _drfc_evaluation_folder(tmp_path / "model", agent.metadata, trace_csv)
    log = logs.DeepRacerLog(str(tmp_path / "model"))
    log.load_evaluation_trace()
    df = log.dataframe()
    mine = df[df["episode"] == 0]
    assert len(mine) == 120
    chosen = sorted(set(zip(mine["action"], mine["steering_angle"], mine["speed"])))
    assert all(actions[a] == (steer, speed) for a, steer, speed in chosen)  # the table's values, no noise
    assert (df[df["episode"] == 1]["action"] == -1).all()  # the bot has no action index
    names = logs.ActionBreakdownUtils.determine_action_names(mine)
    assert len(names) == len(chosen) <= len(actions)
    assert names == [f"A:{a} S:{speed}, T:{abs(steer)}{' LEFT' if steer > 0 else ' RIGHT' if steer < 0 else ''}"
                     for a, steer, speed in chosen]


def test_training_folder_is_read_as_deepracer_for_cloud_output(tmp_path):
    """TrainingLog from a real env's steps: deepracer-utils finds a DRFC model folder, its action space,
    hyperparameters and iterations, the exact action breakdown, and the training metrics."""
    logs = pytest.importorskip("deepracer.logs")
    metadata = json.loads(Path("/work/shared/formats/model_metadata-discrete.json").read_text()) \
        if Path("/work/shared/formats/model_metadata-discrete.json").exists() else default_metadata()
    space = load_action_space(metadata)
    env = multirace.parallel_env(num_cars=2, action_space=metadata, max_steps=30)
    rng = np.random.default_rng(0)
    used, episode = set(), 0
    with TrainingLog(tmp_path / "run", metadata, {"lr": 0.001}) as log:
        for iteration in range(2):
            log.start_iteration(iteration)
            for k in range(2):
                env.reset(seed=10 * iteration + k)
                ids = {agent: episode + i for i, agent in enumerate(env.possible_agents)}
                episode += len(ids)
                while env.agents:
                    actions = {agent: int(rng.integers(0, 4)) for agent in env.agents}
                    _, rewards, terminations, truncations, infos = env.step(actions)
                    for agent, action in actions.items():
                        log.write_step(infos[agent], reward=rewards[agent], episode=ids[agent], action=action,
                                       done=terminations[agent] or truncations[agent])
                        used.add(action)
    env.close()
    log_reader = logs.DeepRacerLog(str(tmp_path / "run"))
    assert log_reader.fh.type.name == "DRFC_MODEL_SINGLE_WORKERS"  # not UNKNOWN_FOLDER
    log_reader.load_training_trace()
    df = log_reader.dataframe()
    assert sorted(df["iteration"].unique()) == [0, 1] and df["unique_episode"].nunique() == 8
    assert log_reader.hyperparameters()["lr"] == 0.001 and log_reader.hyperparameters()["batch_size"] == 64
    assert log_reader.action_space() == metadata["action_space"]
    chosen = sorted(set(zip(df["action"], df["steering_angle"], df["speed"])))
    assert [a for a, _, _ in chosen] == sorted(used)
    assert all(space.actions[a] == (steer, speed) for a, steer, speed in chosen)
    assert len(logs.ActionBreakdownUtils.determine_action_names(df)) == len(used)
    metrics = logs.TrainingMetrics(None, fname=str(tmp_path / "run" / "metrics" / "TrainingMetrics.json"))
    training = metrics.getTraining()
    assert len(training) == 8 and sorted(training["iteration"].unique()) == [0, 1]
    assert (training["time"] == 2.0).all()  # 30 steps of 1/15 s


def test_evaluation_metrics_json_as_deepracer_writes_it(tmp_path):
    fixture = Path("/work/shared/deepracer-model/reInvent2019-TestModel/metrics/evaluation")
    path = tmp_path / "evaluation.json"
    result = run_race([BotController("bot:follow@2.0")], RaceConfig(laps=2, race="time_trial", seed=1),
                      recorders=[EvaluationMetricsRecorder(path)])
    trials = json.loads(path.read_text())["metrics"]
    if fixture.exists():
        real = json.loads(next(fixture.glob("*.json")).read_text())["metrics"][0]
        assert all(set(t) == set(real) for t in trials)
    lap_times = result["cars"][0]["lap_times"]
    assert [t["trial"] for t in trials] == [1, 2]
    assert all(t["episode_status"] == "Lap complete" and t["completion_percentage"] == 100 for t in trials)
    np.testing.assert_allclose([t["elapsed_time_in_milliseconds"] / 1000 for t in trials], lap_times, atol=1 / 15)
    assert trials[1]["start_time"] == trials[0]["metric_time"]


@pytest.mark.parametrize("action_space", [None, "agents/action_space_racer.json"])
def test_rows_formatted_in_a_training_worker_write_the_same_files_as_the_learners_own(tmp_path, action_space):
    """A TrainEnv with `deepracer_log` formats each car's row (`CarSimTrace`); `TrainingLog.write_text` of those
    rows gives byte for byte the sim-trace that `write_step` gives from the full infos, and the same metrics,
    across off-tracks (episodes that end and restart) and penalties, for a discrete and a continuous space."""
    from multirace.train.envs import TrainEnv

    space_file = None if action_space is None else str(Path(multirace.__file__).parent / "data" / action_space)
    env = TrainEnv([("reinvent_base", False)], num_cars=3, action_space=space_file, deepracer_log=True,
                   episode_steps=60)
    space = env.env_for(0).actions
    rng = np.random.default_rng(1)
    logs = [TrainingLog(tmp_path / name, space.to_metadata(), {}) for name in ("full", "worker")]
    episodes, next_episode, ends = list(range(3)), 3, 0
    try:
        env.reset(seed=5)
        full_infos = []
        inner_step = env.env.step
        env.env.step = lambda actions: full_infos.append(inner_step(actions)) or full_infos[-1]
        for log in logs:
            log.start_iteration(0)
        for _ in range(120):
            actions = {a: (int(rng.integers(space.space.n)) if space.discrete else
                           [float(rng.uniform(-30, 30)), float(rng.uniform(0.5, 4.0))]) for a in env.possible_agents}
            _, rewards, _, _, infos = env.step(actions)
            full = full_infos[-1][4]
            for i, agent in enumerate(env.possible_agents):
                reward, done = float(np.float32(rewards[agent])), infos[agent]["train_done"]
                logs[0].write_step(full[agent], reward=reward, episode=episodes[i], action=actions[agent], done=done)
                logs[1].write_text(infos[agent]["deepracer"], reward=reward, episode=episodes[i], done=done)
                if done:
                    episodes[i], next_episode, ends = next_episode, next_episode + 1, ends + 1
            if not env.agents:
                env.reset()
                env.env.step = lambda actions: full_infos.append(inner_step(actions)) or full_infos[-1]
    finally:
        for log in logs:
            log.close()
        env.close()
    assert ends >= 6  # off-tracks and the step limit ended episodes along the way
    full, worker = ((tmp_path / name / "training-simtrace" / "0-iteration.csv").read_bytes() for name in ("full", "worker"))
    assert full == worker and full.count(b"\n") == 1 + 360
    rows = read_simtrace(tmp_path / "full" / "training-simtrace" / "0-iteration.csv")
    assert max(float(row["pause_duration"]) for row in rows) > 0  # off-track penalties were logged
    wall = ("start_time", "metric_time")
    metrics = [[{k: v for k, v in m.items() if k not in wall} for m in log.metrics] for log in logs]
    assert metrics[0] == metrics[1] and len(metrics[0]) == ends
