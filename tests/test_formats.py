"""The race-format registry and its worked example, `lap_count`: real races of bots."""
import dataclasses

import pytest

from multirace.cli import build_parser
from multirace.environment.formats import FORMATS, REGISTRY, league_stages, make_rules
from multirace.environment.formats.lap_count import LapCount
from multirace.environment.race_env import RaceEnv
from multirace.environment.rules import CarRace, RaceRules
from multirace.racing.runner import RaceConfig, make_controller, run_race


class Clock:
    """A race recorder that notes the race's last step and sim time."""

    def start(self, env):
        self.steps, self.time = 0, 0.0

    def step(self, env, observations, rewards, infos):
        self.steps, self.time = env.steps, env.sim_time

    def finish(self, env, result):
        pass


def test_every_registered_format_is_a_race_rules_named_as_registered():
    assert FORMATS == tuple(REGISTRY) and "lap_count" in FORMATS
    for name, rules in REGISTRY.items():
        assert issubclass(rules, RaceRules) and make_rules(name).name == name


def test_unknown_format_names_the_registry():
    for make in (lambda: make_rules("drift"), lambda: RaceEnv(race="drift", num_cars=1)):
        with pytest.raises(ValueError, match="race: unknown format 'drift'; choose one of ") as error:
            make()
        assert all(name in str(error.value) for name in REGISTRY)


def test_the_race_command_offers_the_registry_formats():
    args = build_parser().parse_args(["race", "bot:follow@1.0", "--race", "lap_count"])
    assert args.format == "lap_count"
    assert build_parser().parse_args(["race", "bot:follow@1.0", "--format", "reset_rule"]).format == "reset_rule"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["race", "bot:follow@1.0", "--race", "drift"])


def test_league_stages_come_from_the_formats():
    stages = league_stages()
    assert {stage: rules.name for stage, rules in stages.items()} == {"time_trial": "reset_rule",
                                                                       "head_to_head": "head_to_head"}
    assert stages["time_trial"].solo and not stages["head_to_head"].solo


def test_lap_count_defaults_and_ranking():
    rules = make_rules("lap_count")
    assert isinstance(rules, LapCount) and rules.time_limit == 120.0 and rules.penalise_striker
    assert make_rules("lap_count", time_limit=30.0).time_limit == 30.0
    more = CarRace("more", laps=3, lap_start_time=100.0, distance=61.0)
    fewer_earlier = CarRace("fewer", laps=2, lap_start_time=40.0, distance=80.0)
    same_later = CarRace("later", laps=3, lap_start_time=101.0, distance=70.0)
    assert rules.ranking([fewer_earlier, same_later, more], 20.0) == [2, 1, 0]
    assert not rules.finished(more)  # laps are no finish line
    assert rules.window_end()[0] == "finished"


def test_a_lap_count_race_of_bots_runs_the_window_and_ranks_by_laps():
    clock = Clock()
    result = run_race([make_controller("bot:follow@1.0"), make_controller("bot:pass@2.0")],
                      RaceConfig(track="Oval_track", race="lap_count", laps=3, seed=0), recorders=[clock])
    assert clock.time == pytest.approx(120.0) and clock.steps == 1800  # the window, whatever `laps` says
    cars = result["cars"]
    assert [c["position"] for c in cars] == [1, 2]
    assert all(c["status"] == "finished" and c["reason"] == "120 s window ended" for c in cars)
    assert cars[0]["name"] == "bot:pass@2.0" and cars[0]["laps"] > cars[1]["laps"] > 3  # lapping on past `laps`
    keys = [(-c["laps"], sum(c["lap_times"])) for c in cars]
    assert keys == sorted(keys)


def test_a_format_is_a_dataclass_of_its_defaults():
    fields = {f.name: f.default for f in dataclasses.fields(make_rules("reset_rule"))}
    assert fields["max_resets"] == 3 and fields["time_limit"] == 240.0 and fields["off_track_penalty"] == 0.0
    assert make_rules("object_avoidance").obstacles == 3 and make_rules("object_avoidance").crash_resets
