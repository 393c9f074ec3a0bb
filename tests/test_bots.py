"""Scripted bots: names, parsing errors and traffic manners."""
import pytest

import multirace
from multirace.environment.bots import parse_bot
from multirace.racing.runner import RaceConfig, make_controller, run_race


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


def test_pass_bot_overtakes_a_slower_car_wide_where_a_follow_bot_stays_behind():
    slow = make_controller("bot:follow@1.0")  # on pole, on the centre line
    passing = run_race([slow, make_controller("bot:pass@2.0")],
                       RaceConfig(track="reinvent_base", race="head_to_head", laps=2, seed=0))
    following = run_race([make_controller("bot:follow@1.0"), make_controller("bot:follow@2.0")],
                         RaceConfig(track="reinvent_base", race="head_to_head", laps=2, seed=0))
    by_name = {car["name"]: car for car in passing["cars"]}
    assert by_name["bot:pass@2.0"]["position"] == 1 and by_name["bot:pass@2.0"]["status"] == "finished"
    assert all(car["collisions"] == 0 for car in passing["cars"])
    assert {car["name"]: car["position"] for car in following["cars"]}["bot:follow@2.0"] == 2


def test_passing_line_steers_round_a_slower_car_on_the_side_it_is_on():
    from multirace.environment.bots import PASS_GAP, RETURN_STEP, passing_line
    from multirace.sim.car import CarSpec
    from multirace.sim.tracks import load_track

    track, spec = load_track("reinvent_base"), CarSpec()
    here = track.project(*track.point_at(2.0, 0.05)[:2])  # a little left of the centre line
    assert passing_line(track, spec, here, [], 2.0) == (0.0, 2.0)
    target, speed = passing_line(track, spec, here, [(2.0, -0.05, 1.0)], 2.0)  # slower car on the centre line
    assert target >= spec.width + PASS_GAP - 1e-6 and speed == 2.0  # passes on the left, at full speed
    target, speed = passing_line(track, spec, here, [(0.4, -0.05, 1.0)], 2.0)  # right behind it, still in its way
    assert target > 0.0 and speed < 1.0  # moves over and holds back meanwhile
    assert passing_line(track, spec, here, [(2.0, -0.05, 2.0)], 2.0) == (0.0, 2.0)  # not slower: no pass
    out_wide = track.project(*track.point_at(2.0, 0.34)[:2])  # out wider than a passing line
    target, speed = passing_line(track, spec, out_wide, [(1.0, -0.34, 1.0)], 2.0)  # slower car on the centre line
    assert target == pytest.approx(out_wide.lateral) and speed == 2.0  # clear of it already: holds the line
    target, speed = passing_line(track, spec, out_wide, [], 2.0)  # past it
    assert target == pytest.approx(0.34 - RETURN_STEP, abs=1e-3) and speed == 2.0  # drifts back, does not cut in


def test_racing_line_does_not_steer_for_its_line_into_a_car_beside_it():
    # reInvent 2018's back straight: the line runs 0.13 m left of the centre; a racing-line car held up wide
    # (0.34 m left) beside a car on the centre line must not steer back to its line through that car's side
    from multirace.sim.car import CarSpec
    from multirace.sim.tracks import load_track

    track, spec, bot = load_track("reinvent_base"), CarSpec(), parse_bot("racingline@0.9")
    x, y, heading = track.point_at(10.73, 0.34)
    steer_free, _ = bot.command(track, spec, (x, y, heading), 0.0)
    assert steer_free < -2.0  # nothing beside it: back to the line, to the right
    steer, speed = bot.command(track, spec, (x, y, heading), 0.0, traffic=[(0.27, -0.3, 1.0)])
    assert steer >= 0.0 and speed == spec.min_speed  # beside a car: away from it (or straight on), not into it
    steer, _ = bot.command(track, spec, (x, y, heading), 0.0, traffic=[(0.27, 0.3, 1.0)])  # on the other side
    assert steer == steer_free


class DefenderWatch:
    """A recorder of car 0's road position each step: (lateral, racing-line offset there, followed, inside side)."""

    def __init__(self):
        self.rows = []

    def start(self, env):
        pass

    def step(self, env, observations, rewards, infos):
        import math

        from multirace.sim.racingline import plan_racing_line

        state = env.race_state
        me, track = state.cars[0], state.track
        if not me.located:
            return
        line = plan_racing_line(track, state.car_spec)
        followed = any(-1.5 < track.wrap_ds(ahead) < 0.0 for ahead, _, _ in state.traffic(0))
        turn = track.point_at(me.s + 3.0)[2] - track.point_at(me.s)[2]
        turn = math.atan2(math.sin(turn), math.cos(turn))  # the road's turn over the next 3 m, + left
        inside = 0 if abs(turn) < 0.35 else (1 if turn > 0 else -1)
        self.rows.append((me.lateral, float(line.offsets[line.index_at(me.s)]), followed, inside))

    def finish(self, env, result):
        pass


def test_defend_bot_covers_the_inside_when_followed_and_keeps_the_racing_line_alone():
    import numpy as np

    chased, alone = DefenderWatch(), DefenderWatch()
    result = run_race([make_controller("bot:defend@1.2"), make_controller("bot:follow@2.0")],
                      RaceConfig(race="head_to_head", laps=1, seed=0), recorders=[chased])
    run_race([make_controller("bot:defend@1.2")], RaceConfig(laps=1, seed=0), recorders=[alone])
    assert all(car["collisions"] == 0 and car["status"] == "finished" for car in result["cars"])
    covering = [(lateral, line, inside) for lateral, line, followed, inside in chased.rows if followed and inside]
    assert len(covering) > 50  # the faster car sits behind it into most corners
    # followed into a corner: on the inside half of the road, well inside its racing line
    assert np.mean([inside * lateral for lateral, _, inside in covering]) > 0.1
    assert np.mean([inside * (lateral - line) for lateral, line, inside in covering]) > 0.1
    assert not any(followed for _, _, followed, _ in alone.rows)
    assert np.mean([abs(lateral - line) for lateral, line, _, _ in alone.rows]) < 0.08  # alone: on the line


def test_defend_bot_does_not_move_across_a_car_that_overlaps_it():
    # reInvent 2018 at 2 m: a left-hander ahead. Followed, the defender moves left to cover its inside; with a
    # car already beside it on the left it keeps side room to that car instead of moving across it
    from multirace.sim.car import CarSpec
    from multirace.sim.tracks import load_track

    track, spec, bot = load_track("reinvent_base"), CarSpec(), parse_bot("defend@1.2")
    pose = track.point_at(2.0)
    behind = (-1.0, 0.0, 1.5)  # a car a metre behind, on its line
    steer_alone, _ = bot.command(track, spec, pose, 0.0)
    steer_followed, _ = bot.command(track, spec, pose, 0.0, traffic=[behind])
    steer_beside, _ = bot.command(track, spec, pose, 0.0, traffic=[behind, (0.1, 0.25, 1.2)])
    assert steer_followed > steer_alone + 3.0  # across to the inside (left)
    assert steer_beside < 0.0  # not into the car beside it: away from it
    assert parse_bot("bot:defend@1.2").name == "bot:defend@1.2"


def test_weave_bot_drifts_across_the_road_and_dips_its_speed_but_stays_on_track():
    from multirace.environment.bots.weave import weave_command
    from multirace.environment.bots import Situation
    from multirace.sim.car import CarSpec
    from multirace.sim.tracks import load_track

    track, spec = load_track("reinvent_base"), CarSpec()
    pose = track.point_at(2.0, 0.0)
    proj = track.project(*pose[:2])
    commands = [weave_command(Situation(track, spec, pose, proj, None, t / 15, []), 2.0) for t in range(150)]
    steers, speeds = [c[0] for c in commands], [c[1] for c in commands]
    assert min(steers) < -3.0 and max(steers) > 3.0  # on a straight it steers to both sides
    assert max(speeds) == pytest.approx(2.0, abs=0.01) and min(speeds) < 1.0  # full speed, and dips well below it
    result = run_race([make_controller("bot:weave@2.0")],
                      RaceConfig(track="2022_april_open", race="time_trial", laps=1, seed=0))
    car = result["cars"][0]
    assert car["status"] == "finished" and car["off_tracks"] == 0
