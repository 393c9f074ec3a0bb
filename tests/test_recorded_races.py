"""The same seeds give the same races: results recorded before the race core was rebuilt, compared field by field.

The record (tests/recorded/races.json) holds each race's full result record: positions, laps, lap times,
resets, off-tracks, penalties, collisions and collisions caused. Bots race bit for bit on one machine; on
another CPU the maths library may round a sine or an arc tangent the other way in its last bit, which can move
a time (kept to 0.1 ms) by one digit, so times are compared within `TIME_TOLERANCE`. The agent races run torch
networks, whose float rounding differs between CPUs (AVX2 against AVX-512 kernels, say): on a CPU that rounds
them as the recording one did (the agents' raw outputs for one image equal `torch_numerics.json`) their times
must hold to 2 ms; on another, the last bits of every action differ and the race drifts apart over hundreds of
steps, so only its outline must hold: the same cars, each to the same end, in about the same time.
Re-record (only for a change that is meant to change races, and say why in the commit):
``MULTIRACE_RECORD=1 python -m pytest tests/test_recorded_races.py``.
"""
from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import pytest

from multirace.racing.runner import RaceConfig, make_controller, run_race

RECORD = Path(__file__).parent / "recorded" / "races.json"
NUMERICS = Path(__file__).parent / "recorded" / "torch_numerics.json"
TORCH_AGENTS = ("racer", "dagger_fast")  # the networks the agent races run

RACES = {
    "time_trial_racingline": (["bot:racingline"], RaceConfig(laps=2, seed=0)),
    "head_to_head_four_bots": (["bot:follow@1.2", "bot:racingline@0.9", "bot:lanes@1.0", "bot:pass@1.3"],
                               RaceConfig(race="head_to_head", laps=2, seed=1)),
    "object_avoidance_randomized": (["bot:pass@1.0", "bot:lanes@0.8"],
                                    RaceConfig(track="2022_april_open", race="object_avoidance", laps=1, seed=2,
                                               randomize="mild")),
    "reset_rule_with_env_bots": (["bot:follow@1.5"], RaceConfig(race="reset_rule", laps=1, seed=3,
                                                               bots=("racingline@1.0", "follow@0.8"))),
    "head_to_head_contacts": (["bot:racingline@1.0", "bot:follow@0.6"],
                              RaceConfig(race="head_to_head", laps=3, seed=6, bots=("lanes@0.5",))),
    "agents_head_to_head": (["racer", "dagger_fast", "bot:follow@1.0"],
                            RaceConfig(track="2022_april_open", race="head_to_head", laps=1, seed=4)),
    "agent_in_traffic": (["racer", "bot:follow@0.8", "bot:lanes@0.7"], RaceConfig(race="head_to_head", laps=2, seed=4)),
}
TORCH_RACES = {"agents_head_to_head", "agent_in_traffic"}
TIME_TOLERANCE = 2e-4  # s: one digit of a time kept to 0.1 ms, either way


def _same(result, recorded) -> bool:
    """Whether a result equals its record, times (floats) within `TIME_TOLERANCE`, everything else exactly."""
    if isinstance(recorded, float) and isinstance(result, float):
        return abs(result - recorded) <= TIME_TOLERANCE
    if isinstance(recorded, dict) and isinstance(result, dict):
        return result.keys() == recorded.keys() and all(_same(result[k], recorded[k]) for k in recorded)
    if isinstance(recorded, list) and isinstance(result, list):
        return len(result) == len(recorded) and all(_same(a, b) for a, b in zip(result, recorded))
    return result == recorded


def _run(name: str) -> dict:
    specs, config = RACES[name]
    return run_race([make_controller(spec) for spec in specs], config)


@functools.lru_cache(maxsize=1)
def _torch_numerics() -> dict:
    """{agent: its raw network outputs for the first camera image of re:Invent 2018, seed 0} of `TORCH_AGENTS`:
    equal on two machines only if their CPUs round the networks' float maths alike (the image is bit for bit)."""
    from multirace.environment.race_env import RaceEnv
    from multirace.racing.policy import load_policy

    env = RaceEnv(num_cars=1)
    observations, _ = env.reset(seed=0)
    env.close()
    agents = [load_policy(name).agent for name in TORCH_AGENTS]
    return {name: agent.outputs(agent.reads(observations["car_0"]))[0].tolist()
            for name, agent in zip(TORCH_AGENTS, agents)}


def test_record_covers_every_race():
    if os.environ.get("MULTIRACE_RECORD"):
        RECORD.write_text(json.dumps({name: _run(name) for name in RACES}, indent=1) + "\n")
        NUMERICS.write_text(json.dumps(_torch_numerics(), indent=1) + "\n")
    assert sorted(json.loads(RECORD.read_text())) == sorted(RACES)
    assert sorted(json.loads(NUMERICS.read_text())) == sorted(TORCH_AGENTS)


@pytest.mark.parametrize("name", sorted(RACES))
def test_race_matches_its_record(name):
    recorded = json.loads(RECORD.read_text())[name]
    result = json.loads(json.dumps(_run(name)))  # tuples as lists, as in the file
    if name not in TORCH_RACES:
        assert _same(result, recorded), (result, recorded)
        return
    assert len(result["cars"]) == len(recorded["cars"])
    if _torch_numerics() == json.loads(NUMERICS.read_text()):  # this CPU rounds the networks as the recording one
        for car, old in zip(result["cars"], recorded["cars"]):
            for key in ("name", "position", "laps", "resets", "off_tracks", "penalties", "collisions", "status"):
                assert car[key] == old[key], (car["name"], key)
            assert car["lap_times"] == pytest.approx(old["lap_times"], abs=2e-3)
        return
    for car, old in zip(result["cars"], recorded["cars"]):  # another CPU's rounding: the race's outline
        for key in ("name", "laps", "status"):
            assert car[key] == old[key], (car["name"], key)
        assert car["total_time"] == pytest.approx(old["total_time"], rel=0.1), car["name"]
