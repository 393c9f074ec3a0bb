"""DAgger imitation: tiny real runs write loadable agent files."""
from __future__ import annotations

import json

import numpy as np
import pytest

from multirace.racing.agentfile import AgentController, load_agent
from multirace.cli import main as cli_main
from multirace.train.imitate import ImitationConfig, run_dagger

CONTINUOUS = {"action_space": {"steering_angle": {"low": -30.0, "high": 30.0}, "speed": {"low": 0.5, "high": 1.5}},
              "action_space_type": "continuous"}


def _tiny(tmp_path, stem, **overrides):
    config = dict(out=str(tmp_path / f"{stem}.pt"), tracks=("Oval_track",), both_directions=False, minutes=0.05,
                  rollout_steps=48, train_steps=4, batch_size=16, max_samples=600, progress=False, threads=1)
    config.update(overrides)
    return run_dagger(ImitationConfig(**config))


def test_tiny_dagger_writes_a_loadable_agent(tmp_path):
    summary = _tiny(tmp_path, "tiny", seed=3, name="tiny_dagger")
    assert summary["iterations"] >= 1 and summary["samples"] >= 1
    assert summary["history"][0]["beta"] == 1.0
    first = summary["history"][0]  # beta 1: the expert drove every step; no rate to show, not a nan
    assert first["learner_steps"] == 0 and first["learner_resets_per_1000_steps"] is None
    json.dumps(summary["history"], allow_nan=False)
    agent = load_agent(summary["out"])
    assert agent.name == "tiny_dagger"
    assert agent.metadata["training"]["method"] == "dagger"
    assert agent.metadata["training"]["tracks"] == ["Oval_track"]
    assert agent.metadata["action_space_type"] == "discrete" and len(agent.metadata["action_space"]) == 10
    controller = AgentController(summary["out"])
    steer, speed = controller.act(np.full((120, 160, 1), 90, np.uint8), {})
    assert -30 <= steer <= 30 and speed in (0.5, 1.0)


def test_dagger_in_traffic_records_the_passing_expert_and_rejects_a_bad_bot(tmp_path):
    summary = _tiny(tmp_path, "traffic", traffic=("follow@1.0",), expert_speed=2.0)
    training = load_agent(summary["out"]).metadata["training"]
    assert training["expert"] == "bot:pass@2" and training["traffic"] == ["bot:follow@1.0"]
    with pytest.raises(ValueError, match="zigzag"):
        _tiny(tmp_path, "bad", traffic=("zigzag@1.0",))
    assert not (tmp_path / "bad.pt").exists()


def test_dagger_with_lidar_writes_a_lidar_agent(tmp_path):
    summary = _tiny(tmp_path, "lidar", traffic=("follow@1.0",), lidar=True)
    agent = load_agent(summary["out"])
    assert agent.metadata["sensor"] == ["FRONT_FACING_CAMERA", "LIDAR"] and agent.metadata["training"]["lidar"]
    steer, speed = AgentController(summary["out"]).act(
        {"camera": np.zeros((120, 160, 1), np.uint8), "lidar": np.ones(64, np.float32)}, {})
    assert -30 <= steer <= 30 and speed in (0.5, 1.0)


def test_tiny_dagger_continuous_space(tmp_path):
    summary = _tiny(tmp_path, "cont", action_space=CONTINUOUS, expert_speed=1.0)
    agent = load_agent(summary["out"])
    assert agent.metadata["action_space_type"] == "continuous"
    assert np.isfinite(summary["final_loss"])
    steer, speed = AgentController(summary["out"]).act(np.zeros((120, 160, 1), np.uint8), {})
    assert -30 <= steer <= 30 and 0.5 <= speed <= 1.5


def test_cli_imitate(tmp_path, capsys):
    out = tmp_path / "cli.pt"
    code = cli_main(["imitate", "--out", str(out), "--tracks", "Bowtie_track", "--one-direction",
                     "--minutes", "0.02", "--seed", "1"])
    assert code == 0 and out.exists()
    assert "wrote" in capsys.readouterr().out
    assert cli_main(["agent", "inspect", "--json", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["valid"]
    assert info["metadata"]["training"]["command"].startswith("multirace imitate --out")


def test_dagger_of_the_racing_line_on_generated_tracks_under_randomisation(tmp_path):
    summary = _tiny(tmp_path, "racer", expert="racingline@0.9", randomize="mild", procedural_tracks=1,
                    action_space={**CONTINUOUS, "action_space": {**CONTINUOUS["action_space"],
                                                                 "speed": {"low": 0.5, "high": 4.0}}})
    training = load_agent(summary["out"]).metadata["training"]
    assert training["expert"] == "bot:racingline@0.9" and training["randomize"] == "mild"
    assert training["procedural_tracks"] == 1 and training["tracks"] == ["Oval_track"]
    with pytest.raises(ValueError, match="racingline"):
        _tiny(tmp_path, "bad", expert="racingline@fast")
    assert not (tmp_path / "bad.pt").exists()


def test_dagger_from_an_agent_file_keeps_its_net_and_its_lineage(tmp_path):
    from multirace.train.evaluate import trained_tracks

    first = _tiny(tmp_path, "first", tracks=("Mexico_track",), action_space=CONTINUOUS)["out"]
    second = _tiny(tmp_path, "second", init=first, lidar=True, traffic=("follow@1.0",))["out"]
    agent = load_agent(second)
    assert agent.metadata["action_space_type"] == "continuous"  # the init file's space, not the default
    assert agent.metadata["sensor"] == ["FRONT_FACING_CAMERA", "LIDAR"]
    init = agent.metadata["training"]["init"]
    assert init["file"] == "first.pt" and init["training"]["tracks"] == ["Mexico_track"]
    assert trained_tracks(second) == {"Oval_track", "Mexico_track"}


def test_dagger_from_an_agent_file_takes_a_new_action_space_its_net_fits(tmp_path):
    first = _tiny(tmp_path, "first", action_space=CONTINUOUS)["out"]
    crawl = {**CONTINUOUS, "action_space": {**CONTINUOUS["action_space"], "speed": {"low": 0.1, "high": 1.5}}}
    second = _tiny(tmp_path, "second", init=first, action_space=crawl)["out"]
    assert load_agent(second).metadata["action_space"]["speed"] == {"low": 0.1, "high": 1.5}
    with pytest.raises(ValueError, match="--action-space: does not fit the net of --init .*first.pt"):
        _tiny(tmp_path, "third", init=first, action_space={"action_space": [
            {"steering_angle": 0.0, "speed": 1.0}], "action_space_type": "discrete"})
    assert not (tmp_path / "third.pt").exists()


def test_traffic_share_puts_the_bots_in_that_share_of_the_envs_across_both_directions(tmp_path):
    from multirace.train.imitate import with_traffic

    for share in (0.25, 0.5, 0.75):
        chosen = [with_traffic(k, share) for k in range(80)]
        assert abs(sum(chosen) / 80 - share) < 0.05
        assert any(chosen[0::2]) and any(chosen[1::2])  # forward and reverse runs alike
    assert all(with_traffic(k, 1.0) for k in range(80)) and not any(with_traffic(k, 0.0) for k in range(80))
    summary = _tiny(tmp_path, "mixed", traffic=("follow@1.0",), traffic_share=0.5)
    assert load_agent(summary["out"]).metadata["training"]["traffic_share"] == 0.5
