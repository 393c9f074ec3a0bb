"""`multirace bench --profile`: the per-stage split of an env step, and the env left as it was; the bench's
racing workload races."""
import pytest

from multirace.tools.bench import (_floor_stepper, _interleaved_rates, _racing, _random_driving, _replayed_random,
                                   _same_steps_costs, run_profile)
from multirace.tools.profile import STAGES, format_profile, profile_floor, profile_step


def test_the_profile_splits_the_step_into_its_stages_and_leaves_the_env_untouched():
    env, step = _random_driving(2)
    try:
        step()
        split = profile_step(step, env, 20)
        assert set(split) == set(STAGES) | {"total"}
        for stage in ("commands", "dynamics", "contacts", "rules", "params", "reward", "render"):
            assert split[stage] > 0, stage
        assert sum(split[stage] for stage in STAGES) == pytest.approx(split["total"], abs=0.5)
        # the wrappers are gone: the class's own methods again
        assert "_observe" not in vars(env) and "step" not in vars(env.world) and "_pushes" not in vars(env.world)
        assert "rewards" not in vars(env.reward_function)
    finally:
        env.close()


@pytest.mark.parametrize("racing", [False, True])
def test_run_profile_reports_every_stage_and_the_renderer_alone(racing):
    profile = run_profile(num_cars=2, steps=30, progress=lambda line: None, racing=racing)
    assert profile["workload"] == ("racing" if racing else "random")
    labels = [label for label, _ in format_profile(profile)]
    assert labels[:len(STAGES)] == list(STAGES)
    assert profile["renderer_frames_per_s"] > 0 and 0 <= profile["pybullet_step_share"] <= 1
    floor = profile["floor_us_per_step"]  # the floor's own split: its physics and its camera warps
    assert floor["physics"] > 0 and floor["warps"] > 0
    assert any(label.startswith("floor: physics") for label in labels)


def test_the_floor_profile_times_the_worlds_steps_and_leaves_the_world_untouched():
    step, close = _floor_stepper(2, steps=60, racing=True)
    try:
        world = step.world
        steps_before = world.action_steps
        floor = profile_floor(step, world, 40)
        assert world.action_steps - steps_before == 40  # every floor step stepped the world once, timed
        assert "step" not in vars(world)  # the World's own method again
        assert 0 < floor["physics"] < floor["total"] and floor["warps"] > 0
    finally:
        close()



def test_the_racing_workload_laps_without_contact_so_pybullet_is_seldom_stepped():
    env, step = _racing(4, steps=450)  # 30 s at 1.0-2.2 m/s round re:Invent 2018 (17.7 m a lap)
    try:
        for _ in range(450):
            step()
        world, cars = env.world, env.race_state.cars
        assert [car.race.laps >= 1 for car in cars] == [True] * 4 and not any(car.race.collisions for car in cars)
        assert world.bullet_steps <= 0.05 * world.action_steps  # the cars keep apart: the contact shortcut moves them
        step()  # the recording starts over: the grid again
        assert env.race_state.step == 1 and all(car.race.laps == 0 for car in env.race_state.cars)
    finally:
        env.close()


def test_the_replay_cost_runs_the_same_race_with_and_without_a_replay_in_turns(tmp_path):
    from multirace.racing.runner import RaceConfig, make_controller, run_race
    from multirace.recording.replay import ReplayRecorder
    from multirace.recording.replay_reader import replay_summary
    from multirace.tools.replay_cost import BOTS, _race_pair, replay_cost

    config = RaceConfig(track="reinvent_base", race="reset_rule", laps=1000, seed=0, max_steps=40)
    plain, recorded = _race_pair(config, tmp_path / "pair.rrd", 5, turn_steps=7, first=1)
    assert plain.result == recorded.result == run_race([make_controller(b) for b in BOTS], config)
    assert plain.seconds > 0 and recorded.seconds > 0 and recorded.inner.seconds > 0
    assert replay_summary(tmp_path / "pair.rrd")["steps"] == 40  # every step, in turns

    cost = replay_cost(seconds=3, path=tmp_path / "cost.rrd", repeats=2, turn_steps=9)
    assert cost["steps"] == 45 and len(cost["pairs"]) == 2 and cost["replay_mb"] > 0
    assert cost["race_wall_s"] > 0 and cost["recorder_s"] > 0
    # the writer stopped during the plain race's turns was left running: the next replay is written
    run_race([make_controller(b) for b in BOTS], config, recorders=[ReplayRecorder(tmp_path / "next.rrd")])
    assert replay_summary(tmp_path / "next.rrd")["steps"] == 40


def test_a_replay_cost_pair_whose_races_cannot_start_raises_their_error_rather_than_waiting(tmp_path):
    from multirace.racing.runner import RaceConfig
    from multirace.tools.replay_cost import _race_pair

    with pytest.raises(ValueError, match="no_such_track"):
        _race_pair(RaceConfig(track="no_such_track", race="reset_rule", max_steps=40), tmp_path / "x.rrd", 5,
                   turn_steps=7, first=0)


def test_a_replay_cost_pair_whose_recording_fails_names_the_file_and_the_plain_race_still_ends(tmp_path):
    from multirace.atomic import OutputError
    from multirace.racing.runner import RaceConfig
    from multirace.tools.replay_cost import _race_pair

    (tmp_path / "a_file").write_text("not a folder")
    with pytest.raises(OutputError, match="a_file"):
        _race_pair(RaceConfig(track="reinvent_base", race="reset_rule", max_steps=40),
                   tmp_path / "a_file" / "x.rrd", 5, turn_steps=7, first=1)


def test_the_same_steps_figure_drives_one_recorded_run_the_same_every_time():
    env, run = _replayed_random(2, steps=120)
    try:
        ends = []
        for _ in range(2):
            assert run() == 240  # two cars, 120 steps
            ends.append((env.world.poses.copy(), [race.distance for race in env.races], env.world.bullet_steps))
        (poses_a, distances_a, bullet_a), (poses_b, distances_b, bullet_b) = ends
        assert (poses_a == poses_b).all() and distances_a == distances_b  # the same run, bit for bit
        assert bullet_b > bullet_a  # (the random drivers touch: PyBullet stepped in the second run too)
    finally:
        env.close()
    costs = _same_steps_costs(car_counts=(1, 2), runs=1)
    assert set(costs) == {1, 2} and all(0 < us < 1e5 for us in costs.values())


def test_the_windows_report_the_share_of_pybullet_steps_in_each_workloads_best_window():
    racing, every_step = _racing(2, steps=90), _random_driving(2, shortcut=False)
    try:
        workloads = {"racing": (racing[1], 2), "every_step": (every_step[1], 2)}
        worlds = {"racing": racing[0].world, "every_step": every_step[0].world}
        rates, best_share = _interleaved_rates(workloads, seconds=0.3, windows=3, worlds=worlds)
        assert set(rates) == set(workloads) and all(wall > 0 and cpu > 0 for wall, cpu in rates.values())
        assert best_share["every_step"] == 1.0  # without the shortcut PyBullet steps every step
        assert best_share["racing"] < 0.1  # cars that keep their gaps: the shortcut moves them
    finally:
        racing[0].close()
        every_step[0].close()
