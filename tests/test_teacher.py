"""Learning by cheating: an RL teacher on the privileged state (train/teacher.py), its camera student by
DAgger in the vectorised envs (train/distill.py), and `imitate` with a teacher as the expert.

Iteration counts, not time budgets: the same learning on an idle and on a busy machine.
"""
from pathlib import Path

import numpy as np
import pytest

from multirace.environment.actions import Command
from multirace.racing.agentfile import AgentController, load_agent
from multirace.racing.runner import RaceConfig, run_race
from multirace.train.config import make_config
from multirace.train.distill import distill_student, milestones, student_config
from multirace.train.teacher import evaluate_teacher, train_teacher
from multirace.racing.teacher_net import load_teacher

SPACE = str(Path(__file__).parents[1] / "agents" / "action_space_racer.json")  # steering +-30 deg, 0.5-4 m/s


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    """A teacher after 24 PPO iterations on re:Invent 2018 (about 50 k agent-steps)."""
    out = tmp_path_factory.mktemp("teacher") / "t.teacher.pt"
    config = make_config("fast", tracks=("reinvent_base",), action_space=SPACE, max_iterations=24, seed=0,
                         eval_every=1e9, progress=False)
    summary = train_teacher(config, out, seconds=1e9, log=None)
    return out, summary


def test_teacher_learns_to_lap_from_the_reward(teacher):
    """From nothing to clean laps of re:Invent 2018 in 24 iterations, judged by the race rules."""
    out, summary = teacher
    assert summary["iterations"] == 24 and summary["agent_steps"] == 24 * 2 * 4 * 256
    net = load_teacher(out)
    row = evaluate_teacher(net, "reinvent_base", laps=2)
    assert row["laps"] == 2 and row["status"] == "finished"
    assert row["resets"] <= 1
    assert row["best_lap"] < 9.0, "faster than 2 m/s round the lap (the racing line laps in 4.9 s)"


def test_a_teachers_evaluation_in_traffic_counts_the_collisions_it_caused(teacher):
    """With `eval_bots` the teacher's evaluation is a head-to-head race: a collision it caused costs like an
    off-track in the row's resets (so the kept teacher is the one that stays on the road and off other cars)."""
    out, _ = teacher
    net = load_teacher(out)
    row = evaluate_teacher(net, "reinvent_base", laps=2, seed=1, bots=("follow@1.0", "lanes@1.0"))
    assert row["laps"] == 2 and row["position"] == 1
    assert row["resets"] == row["off_tracks"] + row["collisions_caused"]


def test_a_teachers_evaluation_can_race_agent_files(teacher):
    """`eval_bots` may name agents (rivals): they drive in the evaluation race from their own cameras."""
    out, _ = teacher
    from multirace.racing.runner import RaceConfig, run_race
    from multirace.racing.teacher_net import TeacherController, TeacherDriver
    from multirace.train.rivals import race_opponents

    config = RaceConfig(track="reinvent_base", laps=1, seed=1, race="head_to_head",
                        bots=race_opponents(("follow@1.0", "racer")))
    result = run_race([TeacherController(TeacherDriver(load_teacher(out), "teacher"))], config)
    racer = next(car for car in result["cars"] if car["name"] == "racer")
    assert racer["laps"] == 1 and racer["status"] == "finished"
    row = evaluate_teacher(load_teacher(out), "reinvent_base", laps=1, seed=1, bots=("follow@1.0", "racer"))
    assert row["laps"] == 1 and row["resets"] == row["off_tracks"] + row["collisions_caused"]


def test_teacher_file_is_checked(tmp_path):
    bad = tmp_path / "bad.teacher.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="bad.teacher.pt"):
        load_teacher(bad)


def test_teacher_refuses_a_discrete_space(tmp_path):
    config = make_config("tiny", tracks=("Oval_track",), max_iterations=1, progress=False)
    with pytest.raises(ValueError, match="continuous"):
        train_teacher(config, tmp_path / "x.pt", seconds=1e9, log=None)


def test_student_distils_the_teacher_into_a_camera_agent(teacher, tmp_path):
    """Two DAgger iterations: the student is an agent file that races, named for its RL teacher."""
    teacher_path, _ = teacher
    base = make_config("tiny", tracks=("reinvent_base",), action_space=SPACE, max_iterations=2, seed=0,
                       progress=False, eval_every=0)
    config = student_config(base, teacher_path, seconds=1e9)
    config.rollout_steps, config.distill_steps, config.distill_batch = 32, 4, 16
    summary = distill_student(config, tmp_path / "student.pt", log=None)
    assert summary["iterations"] == 2 and summary["agent_steps"] == 2 * 32 * 4
    agent = load_agent(tmp_path / "student.pt", step_budget=None)
    training = agent.metadata["training"]
    # the default margin; the teacher by file name (a file carries no folder of the machine that wrote it)
    assert training["method"] == "dagger" and training["expert"] == f"teacher:{teacher_path.name}@0.8"
    assert agent.metadata["sensor"] == ["FRONT_FACING_CAMERA"], "the student reads the camera only"
    result = run_race([AgentController(tmp_path / "student.pt", step_budget=0.5)],
                      RaceConfig(track="reinvent_base", race="time_trial", laps=1, max_steps=30))
    assert result["cars"][0]["status"] != "forfeit"


@pytest.mark.parametrize("anneal", [False, True])
def test_the_students_learning_rate_falls_over_its_budget_only_when_asked(teacher, tmp_path, anneal):
    teacher_path, _ = teacher
    base = make_config("tiny", tracks=("reinvent_base",), action_space=SPACE, max_iterations=4, seed=0,
                       progress=False, eval_every=0, distill_anneal_lr=anneal)
    config = student_config(base, teacher_path, seconds=1e9)  # the iterations are the budget
    config.rollout_steps, config.distill_steps, config.distill_batch = 16, 2, 16
    summary = distill_student(config, tmp_path / "s.pt", log=None)
    rates = [row["lr"] for row in summary["history"]]
    if anneal:  # 1e-3 x (1 - iterations done / 4), to a floor of 10 %
        assert rates == pytest.approx([1e-3, 7.5e-4, 5e-4, 2.5e-4])
    else:
        assert rates == [1e-3] * 4


def test_student_can_start_from_an_imitation_agent(teacher, tmp_path):
    """`--init`: the student is the init file's net (its network, image and weights) and records that lineage;
    with no DAgger step its weights are the init file's."""
    import torch

    from multirace.racing.agentfile import read_payload

    teacher_path, _ = teacher
    racer = Path(__file__).parents[1] / "agents" / "racer.pt"
    base = make_config("tiny", tracks=("reinvent_base",), max_iterations=1, seed=0, progress=False, eval_every=0)
    config = student_config(base, teacher_path, seconds=1e9, init=racer)
    assert config.network == "MULTIRACE_SMALL_CNN" and config.camera == (120, 160)
    config.rollout_steps, config.distill_steps, config.distill_batch, config.distill_lr = 16, 1, 8, 0.0
    distill_student(config, tmp_path / "s.pt", log=None, init=racer)
    agent = load_agent(tmp_path / "s.pt", step_budget=None)
    assert agent.metadata["training"]["init"]["file"] == "racer.pt"
    before, after = read_payload(racer)["state_dict"], read_payload(tmp_path / "s.pt")["state_dict"]
    for key, value in before.items():
        if not key.startswith("value_head."):
            assert torch.equal(value, after[key]), key


@pytest.mark.parametrize("share", [1.0, 0.6])
def test_the_shipped_student_blends_in_the_init_agents_weights_when_asked(teacher, tmp_path, share):
    """`init_blend`: the student evaluated and shipped is share x the trained weights + (1 - share) x the init
    agent's (1.0: the trained ones). One iteration from the racer, against the same run unblended."""
    import torch

    from multirace.racing.agentfile import read_payload

    teacher_path, _ = teacher
    racer = Path(__file__).parents[1] / "agents" / "racer.pt"

    def student(blend):
        base = make_config("tiny", tracks=("reinvent_base",), max_iterations=1, seed=0, progress=False,
                           eval_every=0, init_blend=blend)
        config = student_config(base, teacher_path, seconds=1e9, init=racer)
        config.rollout_steps, config.distill_steps, config.distill_batch = 16, 3, 8
        return config

    raw = tmp_path / "raw.pt"
    distill_student(student(1.0), raw, log=None, init=racer)
    distill_student(student(share), tmp_path / "s.pt", log=None, init=racer)
    before = read_payload(racer)["state_dict"]
    learnt, shipped = read_payload(raw)["state_dict"], read_payload(tmp_path / "s.pt")["state_dict"]
    moved = 0
    for key, value in before.items():
        if key.startswith("value_head.") or not value.is_floating_point():
            continue
        expected = share * learnt[key] + (1 - share) * value
        assert torch.allclose(shipped[key], expected, atol=1e-6), key
        moved += not torch.equal(learnt[key], value)
    assert moved, "the trained student moved from the racer"
    training = load_agent(tmp_path / "s.pt", step_budget=None).metadata["training"]
    assert training.get("init_blend") == (share if share < 1 else None)  # the file says what it is


def test_the_overlapped_fit_trains_on_every_label_one_rollout_behind():
    """`distill_overlap`: the fit of rollout k's labels runs while rollout k+1 is gathered; that rollout's
    labels join the dataset only when the fit ends, the driver then takes the fitted weights, and every fit
    runs its `distill_steps` (Adam's step count)."""
    import torch

    from multirace.environment.actions import load_action_space
    from multirace.racing.nets import build_net
    from multirace.train.distill import StudentFit
    from multirace.train.imitate import Dataset, imitation_loss

    space = load_action_space(SPACE)
    config = make_config("tiny", distill_overlap=True, distill_steps=3, distill_batch=4)
    net = build_net(config.student_network, (120, 160, 1), space)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-2)
    rng = np.random.default_rng(0)
    data = Dataset(100, (120, 160, 1), (2,), np.float32, rng)
    fit = StudentFit(net, optimiser, imitation_loss(space), data, config, pooled=False)

    def gather(n):
        for _ in range(n):
            fit.add(torch.from_numpy(rng.integers(0, 255, (120, 160, 1), dtype=np.uint8)),
                    np.array([rng.uniform(-30, 30), rng.uniform(0.5, 4)], np.float32))

    fit.begin(1e-2)  # nothing gathered yet: no fit beside the first rollout
    gather(10)
    assert data.size == 0
    assert np.isfinite(fit.finish(1e-2)) and data.size == 10  # the first rollout's fit runs at its end
    before = {key: value.clone() for key, value in net.state_dict().items()}
    fit.begin(1e-2)
    gather(10)  # while the fit runs on the first 10
    loss = fit.finish(1e-2)
    assert np.isfinite(loss) and data.size == 20
    assert any(not torch.equal(before[key], value) for key, value in net.state_dict().items())
    for key, value in net.state_dict().items():
        assert torch.equal(fit.driver.state_dict()[key], value), key
    steps = {int(state["step"]) for state in optimiser.state_dict()["state"].values()}
    assert steps == {6}
    fit.close()


def test_an_overlapped_student_run_records_a_fit_per_iteration(teacher, tmp_path):
    teacher_path, _ = teacher
    base = make_config("tiny", tracks=("reinvent_base",), action_space=SPACE, max_iterations=3, seed=0,
                       progress=False, eval_every=0, distill_overlap=True)
    config = student_config(base, teacher_path, seconds=1e9)
    config.rollout_steps, config.distill_steps, config.distill_batch = 16, 2, 16
    summary = distill_student(config, tmp_path / "s.pt", log=None)
    assert [np.isfinite(row["expert_loss"]) for row in summary["history"]] == [True] * 3
    assert load_agent(tmp_path / "s.pt", step_budget=None).metadata["training"]["method"] == "dagger"


def test_a_blend_needs_an_init_agent(teacher, tmp_path):
    teacher_path, _ = teacher
    base = make_config("tiny", tracks=("reinvent_base",), max_iterations=1, progress=False, init_blend=0.5)
    with pytest.raises(ValueError, match="init_blend: needs --init"):
        distill_student(student_config(base, teacher_path, seconds=1e9), tmp_path / "s.pt", log=None)


def test_a_discrete_init_agent_is_refused_for_a_student(teacher):
    teacher_path, _ = teacher
    base = make_config("tiny", tracks=("reinvent_base",), progress=False)
    with pytest.raises(ValueError, match="dagger_fast.pt: a discrete-action agent"):
        student_config(base, teacher_path, 60.0, init=Path(__file__).parents[1] / "agents" / "dagger_fast.pt")


def test_train_reuses_a_teacher_with_the_cli(teacher, tmp_path, capsys):
    """`multirace train --teacher FILE`: no teacher stage; the student learns from that file's policy."""
    from multirace.cli import main

    teacher_path, _ = teacher
    code = main(["train", "--teacher", str(teacher_path), "--track", "reinvent_base", "--out",
                 str(tmp_path / "c.pt"), "--config", "tiny", "--set", "max_iterations=1", "--set", "eval_every=0",
                 "--set", "rollout_steps=16", "--set", "distill_steps=1", "--action-space", SPACE, "--no-progress"])
    assert code == 0
    out = capsys.readouterr().out
    assert "teacher 0.0 s, 0 agent-steps" in out
    assert f"(from the teacher {teacher_path})" in out and "(teacher) in" not in out  # it wrote no teacher file
    agent = load_agent(tmp_path / "c.pt", step_budget=None)
    assert agent.metadata["training"]["expert"] == f"teacher:{teacher_path.name}@0.8"
    assert not (tmp_path / "c.teacher.pt").exists()


def test_imitate_takes_a_teacher_as_expert(teacher, tmp_path):
    from multirace.train.imitate import ImitationConfig, run_dagger

    teacher_path, _ = teacher
    summary = run_dagger(ImitationConfig(out=str(tmp_path / "i.pt"), tracks=("reinvent_base",),
                                         both_directions=False, minutes=0.02, action_space=SPACE,
                                         teacher=str(teacher_path), rollout_steps=20, train_steps=2, progress=False,
                                         threads=1))
    assert summary["expert"] == f"teacher:{teacher_path.name}"
    assert summary["samples"] >= 20


def test_milestones_read_the_first_clean_and_fast_evaluations():
    evals = [{"laps": 3, "target": 3, "resets": 2, "best_lap": 5.0, "elapsed": 10, "agent_steps": 100},
             {"laps": 3, "target": 3, "resets": 0, "best_lap": 6.5, "elapsed": 20, "agent_steps": 200},
             {"laps": 3, "target": 3, "resets": 0, "best_lap": 5.5, "elapsed": 30, "agent_steps": 300}]
    found = milestones(evals, reference=5.0, offset=100)
    assert found["clean"] == {"seconds": 120, "agent_steps": 200}
    assert found["within_1.25x"] == found["within_1.15x"] == {"seconds": 130, "agent_steps": 300}
    assert "within_1.15x" not in milestones(evals, reference=4.5)


def test_a_teacher_expert_can_ask_for_a_share_of_its_speed(teacher):
    """``teacher:PATH@0.9`` (the student's `distill_speed_scale`): the same steering, 0.9x the speed (never below
    the action space's lowest); a scale outside (0, 1] is refused naming the expert."""
    from multirace.environment.race_env import RaceEnv
    from multirace.train.experts import expert_command, make_expert, teacher_spec

    out, _ = teacher
    assert teacher_spec(f"teacher:{out}@0.9") == (str(out), 0.9)
    assert teacher_spec("teacher:/runs/a@b/t.teacher.pt") == ("/runs/a@b/t.teacher.pt", 1.0)
    full, slower = make_expert(f"teacher:{out}", 1.0), make_expert(f"teacher:{out}@0.9", 1.0)
    env = RaceEnv(track="reinvent_base", num_cars=1, action_space=SPACE, observation="state")
    try:
        env.reset(seed=0)
        for _ in range(20):
            env.step({"car_0": [0.0, 2.0]})
        steer, speed = expert_command(full, env)
        steer_slow, speed_slow = expert_command(slower, env)
        assert steer_slow == steer and speed_slow == pytest.approx(max(0.5, 0.9 * speed), rel=1e-6)
    finally:
        env.close()
    with pytest.raises(ValueError, match="speed scale"):
        make_expert(f"teacher:{out}@1.5", 1.0)
    with pytest.raises(ValueError, match="distill_speed_scale"):
        make_config("fast", distill_speed_scale=0.0)


def test_a_free_road_teacher_labels_the_cars_with_no_traffic_near(teacher):
    """`distill_free_teacher`: the run's teacher labels a car with a car near it (a bot 1.5 m ahead), the free-road
    teacher a car whose road is clear (the bot 6 m ahead); a file that is not a teacher is refused naming the
    setting."""
    from multirace.train.distill import train_privileged
    from multirace.train.envs import TrainEnv, env_settings
    from multirace.train.experts import expert_commands, make_expert

    out, _ = teacher
    traffic, free = f"teacher:{out}@0.5", f"teacher:{out}"  # one net, two speeds: which labelled shows in the speed
    for ahead, labeller in ((1.5, traffic), (6.0, free)):
        env = TrainEnv([("reinvent_base", False)], num_cars=1, bots=("follow@1.0",), bots_ahead=ahead,
                       action_space=SPACE, camera=(30, 40), expert_labels=True, expert=traffic, free_expert=free)
        try:
            _, infos = env.reset(seed=0)
            expected = env.env.actions.nearest(*expert_commands(make_expert(labeller, 1.0), env.env, [0])[0])
            assert infos["car_0"]["expert_action"] == pytest.approx([float(v) for v in expected])
        finally:
            env.close()
    config = make_config("fast", tracks=("reinvent_base",), action_space=SPACE, distill_free_teacher=str(SPACE))
    assert env_settings(config)["free_expert"] == f"teacher:{SPACE}"
    with pytest.raises(ValueError, match="distill_free_teacher: teacher file .*action_space_racer.json"):
        train_privileged(config, Path("never.pt"), log=None)
    with pytest.raises(ValueError, match="distill_free_teacher: .*speed scale"):
        train_privileged(make_config("fast", distill_free_teacher=f"{out}@1.5"), Path("never.pt"), log=None)


def test_a_teacher_labels_every_car_of_an_env_in_one_pass_as_it_labels_each_alone(teacher):
    """`expert_commands` runs the teacher's net once for all the cars (a worker labels every image it sends): the
    commands are each car's own, as `expert_command` gives them one car at a time."""
    from multirace.environment.race_env import RaceEnv
    from multirace.train.experts import expert_command, expert_commands, make_expert

    out, _ = teacher
    expert = make_expert(f"teacher:{out}@0.8", 1.0)
    env = RaceEnv(track="reinvent_base", num_cars=4, action_space=SPACE, observation="state")
    try:
        env.reset(seed=1)
        for step in range(15):
            env.step({f"car_{i}": [10.0 * (i - 1.5), 1.0 + 0.2 * i + 0.05 * step] for i in range(4)})
        together = expert_commands(expert, env, range(4))
        alone = [expert_command(expert, env, i) for i in range(4)]
        assert len({command for command in alone}) == 4  # four different places, four different commands
        assert np.abs(np.array(together) - np.array(alone)).max() < 1e-5
    finally:
        env.close()


def test_a_teacher_races_as_an_entrant(teacher):
    """`teacher:PATH` is an entrant like an agent file or a bot: it drives its car from its privileged state
    in a head-to-head race, under its file's name and hash."""
    from multirace.racing.entrant import file_sha256
    from multirace.racing.runner import make_controller

    out, _ = teacher
    result = run_race([make_controller(f"teacher:{out}"), make_controller("bot:follow@1.0")],
                      RaceConfig(track="reinvent_base", race="head_to_head", laps=1, seed=1))
    car = next(c for c in result["cars"] if c["car"] == "car_0")
    assert car["name"] == "teacher:t.teacher.pt" and car["file_sha256"] == file_sha256(out)
    assert car["laps"] == 1 and car["status"] == "finished" and car["position"] == 1, "it passes a 1 m/s car"


def test_evaluate_reports_a_teacher_on_tracks_it_never_saw(teacher, tmp_path):
    """`multirace evaluate teacher:PATH` (a real subprocess): the teacher's training tracks are read from its
    file, so they are labelled trained-on; a missing teacher file is refused by name before any race."""
    import json
    import subprocess
    import sys

    out, _ = teacher
    report = tmp_path / "t.json"
    cli = [sys.executable, "-m", "multirace.cli", "evaluate"]
    run = subprocess.run(cli + [f"teacher:{out}", "--tracks", "Oval_track", "--parts", "held-out", "--directions",
                                "both", "--laps", "1", "--json", str(report)], capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = json.loads(report.read_text())
    assert rows["trained_on"] == ["reinvent_base"]
    assert [(r["track"], r["reverse"]) for r in rows["held_out"]] == [("Oval_track", False), ("Oval_track", True)]
    assert all(r["laps"] + r["resets"] >= 1 for r in rows["held_out"])
    missing = subprocess.run(cli + ["teacher:nowhere.teacher.pt"], capture_output=True, text=True, cwd=tmp_path)
    assert missing.returncode == 2 and "teacher:nowhere.teacher.pt: no such teacher file" in missing.stderr


def test_a_teacher_can_start_from_another_teachers_weights(teacher, tmp_path):
    """`teacher_init`: an RL fine-tune (in traffic, say) starts from a teacher file, not from nothing; its file
    records where it started; a teacher of another action space is refused by name before any env starts."""
    start, _ = teacher
    config = make_config("fast", tracks=("reinvent_base",), action_space=SPACE, max_iterations=1, seed=3,
                         eval_every=1e9, progress=False, teacher_init=str(start), teacher_lr=1e-5)
    train_teacher(config, tmp_path / "t2.teacher.pt", seconds=1e9, log=None)
    before, after = load_teacher(start), load_teacher(tmp_path / "t2.teacher.pt")
    moved = (after.trunk[0].weight - before.trunk[0].weight).abs().max().item()
    assert 0 < moved < 0.01, "one small step from the file's weights, not a fresh net"
    assert after.training_notes["teacher_init"] == str(start)
    other = tmp_path / "other.json"
    other.write_text('{"action_space": {"steering_angle": {"low": -20, "high": 20}, "speed": {"low": 0.5, "high": 2}},'
                     ' "action_space_type": "continuous"}')
    config = make_config("fast", tracks=("reinvent_base",), action_space=str(other), max_iterations=1,
                         teacher_init=str(start), progress=False)
    with pytest.raises(ValueError, match="teacher_init .*t.teacher.pt"):
        train_teacher(config, tmp_path / "t3.teacher.pt", seconds=1e9, log=None)


def test_steering_balance_draws_hard_turns_in_proportion_to_their_weight():
    """`distill_balance`: a label's draw weight is 1 + balance x |steering| / 30 deg, for continuous and
    discrete spaces; at 0 the draws are the uniform ones of before (same seed, same indices)."""
    from multirace.environment.actions import load_action_space
    from multirace.train.distill import steering_weight
    from multirace.train.imitate import Dataset

    space = load_action_space(SPACE)
    assert steering_weight(space, 0.0) is None
    weight = steering_weight(space, 4.0)
    assert weight(np.array([0.0, 3.0])) == 1.0 and weight(np.array([-30.0, 1.0])) == 5.0
    assert weight(np.array([15.0, 2.0])) == pytest.approx(3.0)
    data = Dataset(1000, (2, 2, 1), (2,), np.float32, np.random.default_rng(0), weight=weight)
    for k in range(1000):  # one label in ten a full-lock turn, the rest straight
        data.add(np.full((2, 2, 1), k % 10, np.uint8), np.array([30.0 if k % 10 == 0 else 0.0, 2.0], np.float32))
    _, labels = data.batch(20_000)
    assert abs(float((labels[:, 0] == 30.0).float().mean()) - 5 / 14) < 0.02  # 100 x 5 of 900 + 100 x 5
    uniform = Dataset(1000, (2, 2, 1), (2,), np.float32, np.random.default_rng(0))
    for k in range(1000):
        uniform.add(np.zeros((2, 2, 1), np.uint8), np.array([float(k), 2.0], np.float32))
    _, labels = uniform.batch(8)
    assert labels[:, 0].tolist() == np.random.default_rng(0).integers(1000, size=8).astype(float).tolist()

    discrete = load_action_space(str(Path(SPACE).with_name("action_space_fast.json")))
    per_action = steering_weight(discrete, 2.0)
    for index, (steer, _) in enumerate(discrete.actions):
        assert per_action(index) == pytest.approx(1.0 + 2.0 * abs(steer) / 30.0)


def test_traffic_labels_are_drawn_more_often_when_asked():
    """`distill_traffic`: a label whose car had another car or box less than `distill_traffic_gap` metres ahead
    is drawn (1 + distill_traffic) times as often as one in free air; steering balance multiplies in."""
    from multirace.environment.actions import load_action_space
    from multirace.train.distill import steering_weight, traffic_factors
    from multirace.train.imitate import Dataset

    config = make_config("fast", distill_traffic=3.0, distill_traffic_gap=2.0)
    infos = [[{"gap_ahead": 1.5}, {"gap_ahead": 2.5}], [{"gap_ahead": float("inf")}, {}]]
    assert traffic_factors(infos, config).tolist() == [4.0, 1.0, 1.0, 1.0]
    data = Dataset(1000, (2, 2, 1), (2,), np.float32, np.random.default_rng(0), weighted=True)
    for k in range(1000):  # one label in ten behind a car
        near = k % 10 == 0
        data.add(np.zeros((2, 2, 1), np.uint8), np.array([1.0 if near else 0.0, 2.0], np.float32),
                 4.0 if near else 1.0)
    _, labels = data.batch(20_000)
    assert abs(float((labels[:, 0] == 1.0).float().mean()) - 4 / 13) < 0.02  # 100 x 4 of 900 + 100 x 4
    both = Dataset(10, (2, 2, 1), (2,), np.float32, np.random.default_rng(0),
                   weight=steering_weight(load_action_space(SPACE), 4.0), weighted=True)
    both.add(np.zeros((2, 2, 1), np.uint8), np.array([-30.0, 1.0], np.float32), 4.0)
    assert both.weights[0] == 20.0


def test_a_camera_view_teacher_keeps_its_view_in_its_file_and_labels_from_it(teacher, tmp_path):
    """``teacher_view="camera"``: the teacher trains on the traffic its front camera shows, its file says so, and
    as DAgger's expert it labels a student's car from that view (a car alongside, out of the camera's field, is
    not in it); older files, without a view, read every car near them; a view that does not exist is refused."""
    from multirace.environment.race_env import RaceEnv
    from multirace.train.experts import expert_commands, make_expert

    start, _ = teacher
    config = make_config("fast", tracks=("reinvent_base",), action_space=SPACE, max_iterations=1, seed=3,
                         eval_every=1e9, progress=False, teacher_init=str(start), teacher_view="camera")
    out = tmp_path / "cam.teacher.pt"
    train_teacher(config, out, seconds=1e9, log=None)
    assert load_teacher(out).view == "camera" and load_teacher(start).view == "all"
    import torch

    older = torch.load(start, weights_only=True)
    del older["view"]
    torch.save(older, tmp_path / "older.teacher.pt")
    assert load_teacher(tmp_path / "older.teacher.pt").view == "all"
    expert = make_expert(f"teacher:{out}", 1.0)
    env = RaceEnv(track="reinvent_base", num_cars=2, action_space=SPACE, observation="state")
    try:
        env.reset(seed=0)
        env.move_cars({0: (5.0, 0.0), 1: (5.05, 0.3)}, clear=False)
        label = expert_commands(expert, env, [0])[0]
        assert label == expert.drive_many(env.car_state(0, "camera")[None])[0]
        assert label != expert.drive_many(env.car_state(0, "all")[None])[0]
    finally:
        env.close()
    with pytest.raises(ValueError, match="teacher_view"):
        make_config("fast", teacher_view="lidar")


def test_a_teacher_can_label_as_if_the_cars_ahead_drove_no_faster_than_a_speed(teacher):
    """`distill_ahead_speed`: the traffic teacher's state lists the bot ahead closing as if it drove at that speed
    (where it drives faster; the car behind and everything else as they are), and its label is the teacher's
    command from that state; the setting is checked and reaches the env."""
    from multirace.environment.state import CAR_FEATURES, MAX_SPEED, slowed_ahead
    from multirace.train.envs import TrainEnv, env_settings
    from multirace.train.experts import expert_commands, make_expert

    out, _ = teacher
    expert = f"teacher:{out}"
    env = TrainEnv([("reinvent_base", False)], num_cars=1, bots=("follow@1.5",), bots_ahead=1.5, action_space=SPACE,
                   camera=(30, 40), expert_labels=True, expert=expert, expert_ahead_speed=0.0)
    try:
        env.reset(seed=0)
        for _ in range(10):  # both cars under way, the bot ahead faster than the learner
            _, _, _, _, infos = env.step({"car_0": [0.0, 0.8]})
        race_env = env.env
        own, bot = race_env.race_state.cars[0].speed, race_env.race_state.cars[1].speed
        assert bot > own > 0.3
        state = race_env.car_state(0)
        first = CAR_FEATURES - 12  # the traffic rows: two ahead, one behind, four values each
        assert state[first] == 1.0 and state[first + 3] == pytest.approx((bot - own) / MAX_SPEED, abs=1e-6)
        slowed = slowed_ahead(state[None], 0.0)[0]
        assert slowed[first + 3] == pytest.approx(-own / MAX_SPEED, abs=1e-6)  # the bot taken to stand still
        assert np.array_equal(np.delete(slowed, first + 3), np.delete(state, first + 3))
        assert slowed_ahead(state[None], 9.0)[0][first + 3] == state[first + 3]  # no faster than it is
        label = race_env.actions.nearest(*make_expert(expert, 1.0).drive_many(slowed[None])[0])
        assert infos["car_0"]["expert_action"] == pytest.approx([float(v) for v in label])
        assert expert_commands(make_expert(expert, 1.0), race_env, [0], 0.0) != \
            expert_commands(make_expert(expert, 1.0), race_env, [0])
    finally:
        env.close()
    assert env_settings(make_config("fast", distill_ahead_speed=1.0))["expert_ahead_speed"] == 1.0
    with pytest.raises(ValueError, match="distill_ahead_speed"):
        make_config("fast", distill_ahead_speed=-1.0)


def test_with_ahead_seen_only_the_cars_ahead_the_camera_shows_are_taken_that_slow(teacher):
    """`distill_ahead_seen`: a car alongside, just ahead of the learner's centre but behind its camera, keeps its
    own speed in the teacher's state; the car straight ahead, which the camera shows, is slowed."""
    from multirace.environment.race_env import RaceEnv
    from multirace.environment.state import CAR_FEATURES, ahead_in_camera, slowed_ahead
    from multirace.train.experts import expert_commands, make_expert

    out, _ = teacher
    expert = make_expert(f"teacher:{out}", 1.0)
    env = RaceEnv(num_cars=3, obstacles=0, race="head_to_head", camera=(30, 40))
    try:
        env.reset(seed=0)
        env.move_cars({0: (10.0, 0.0), 1: (10.8, 0.0), 2: (10.15, -0.3)}, clear=False)
        for _ in range(6):  # all three under way, the two ahead faster than the learner
            env.step({"car_0": Command((0.0, 0.6)), "car_1": Command((0.0, 1.5)), "car_2": Command((0.0, 1.5))})
        state = env.car_state(0)
        first = CAR_FEATURES - 12  # the traffic rows: two ahead, one behind, four values each
        assert state[first] == state[first + 4] == 1.0 and state[first + 3] > 0 and state[first + 7] > 0
        shown = ahead_in_camera(env, 0)
        assert sorted(shown) == [False, True]  # the car straight ahead is shown, the one alongside is not
        seen_only = slowed_ahead(state[None], 0.0, [shown])[0]
        hidden, seen = first + 4 * shown.index(False) + 3, first + 4 * shown.index(True) + 3
        assert seen_only[hidden] == state[hidden] and seen_only[seen] < 0  # only the car shown is slowed
        assert np.array_equal(slowed_ahead(state[None], 0.0, [[True, True]]), slowed_ahead(state[None], 0.0))
        assert expert_commands(expert, env, [0], 0.0, ahead_seen=True) == expert.drive_many(seen_only[None])
    finally:
        env.close()
    with pytest.raises(ValueError, match="distill_ahead_seen: needs --set distill_ahead_speed"):
        make_config("fast", distill_ahead_seen=True)


@pytest.mark.parametrize("bound_coef", [0.0, 1.0])
def test_the_bound_loss_brings_a_speed_mean_past_the_top_speed_back_into_the_box(bound_coef):
    """`bound_coef`: a teacher whose speed mean sits past the action box's top speed (it commands the top speed
    whatever its samples, so PPO's advantages cannot move it; trd3 in traffic) has it pulled back to the top
    speed by PPO updates with no advantage to follow; without the loss it stays out there. Means inside the box
    are left alone."""
    import torch

    from multirace.environment.actions import load_action_space
    from multirace.racing.teacher_net import StatePolicyNet
    from multirace.train.policy import Policy
    from multirace.train.ppo import beyond_box, ppo_update

    torch.manual_seed(0)
    space = load_action_space(SPACE)  # speed 0.5-4 m/s
    net, policy = StatePolicyNet(space), Policy(space)
    with torch.no_grad():
        net.mean.bias[1] = 1.6  # speed mean = 2.25 + 1.75 x 1.6 = 5.05 m/s; steering inside the box
    obs = torch.randn(256, net.features)
    with torch.no_grad():
        out = net(obs)
        act, logp = policy.sample(out)
    assert out[:, 1].min() > 4.5 and beyond_box(out, space) > 0.1
    batch = {"obs": obs, "act": act, "logp": logp, "adv": torch.zeros(256), "val": torch.zeros(256),
             "ret": torch.zeros(256)}
    config = make_config("fast", minibatch_size=64, epochs=10, bound_coef=bound_coef, ent_coef=0.0,
                         norm_adv=False)
    ppo_update(net, policy, torch.optim.SGD(net.parameters(), lr=0.1), batch, config, space, value_only=False)
    with torch.no_grad():
        speed = net(obs)[:, 1]
    if bound_coef:
        assert speed.max() < 4.25 and speed.mean() > 3.5  # back at the edge (from 5.05), not pushed far in
    else:
        assert speed.min() > 4.5
    assert beyond_box(torch.tensor([[29.0, 3.9, 0.0, 0.0]]), space) == 0.0
    with pytest.raises(ValueError, match="bound_coef"):
        make_config("fast", bound_coef=-1.0)


def test_a_teachers_entropy_bonus_widens_its_exploration(teacher, tmp_path):
    """`teacher_ent_coef`: with an entropy bonus the teacher's speed noise grows over an update (so some of
    its samples brake); without one (the default) PPO alone moves it, and less. (Steering is left out: the
    fixture's steering std sits at the policy's cap, where no loss moves it.)"""
    start, _ = teacher
    widened = {}
    for bonus in (0.0, 1.0):
        config = make_config("fast", tracks=("reinvent_base",), action_space=SPACE, max_iterations=1, seed=3,
                             eval_every=1e9, progress=False, teacher_init=str(start), teacher_lr=1e-3,
                             teacher_ent_coef=bonus)
        out = tmp_path / f"ent{bonus}.teacher.pt"
        train_teacher(config, out, seconds=1e9, log=None)
        widened[bonus] = (load_teacher(out).log_std[1] - load_teacher(start).log_std[1]).detach().item()
    assert widened[1.0] > 0 and widened[1.0] > widened[0.0] + 1e-3, widened
