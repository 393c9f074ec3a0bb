"""`multirace train --engine rllib`: a tiny real Ray RLlib run (skipped where RLlib is not installed)."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from multirace.cli import main


def test_missing_ray_names_the_install_command(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    code = main(["train", "--engine", "rllib", "--out", str(tmp_path / "a.pt"), "--minutes", "0.01"])
    assert code != 0
    err = capsys.readouterr().err
    assert 'pip install -e ".[rllib]"' in err and "--engine local" in err


@pytest.mark.rllib
@pytest.mark.parametrize("setting, refused", [("lidar=true", "lidar=true"),
                                              ('sensor=["STEREO_CAMERAS"]', "sensor=['STEREO_CAMERAS']")])
def test_other_sensors_under_rllib_are_refused_before_ray_starts(tmp_path, capsys, setting, refused):
    pytest.importorskip("ray.rllib")
    code = main(["train", "--engine", "rllib", "--set", setting, "--out", str(tmp_path / "a.pt"),
                 "--minutes", "0.01"])
    assert code != 0
    assert f"{refused} is a local-engine option" in capsys.readouterr().err
    assert not (tmp_path / "a.pt").exists()

@pytest.mark.rllib
def test_tiny_rllib_run_writes_checkpoint_and_racing_agent_file(tmp_path, capsys):
    pytest.importorskip("ray.rllib")
    import torch
    from ray.rllib.core.rl_module.rl_module import RLModule

    from multirace.racing.agentfile import load_agent
    from multirace.train.rllib import MODULE_ID, net_state_from_module

    out = tmp_path / "r.pt"
    code = main(["train", "--engine", "rllib", "--config", "tiny", "--track", "Oval_track", "--envs", "1",
                 "--cars", "2", "--set", "rollout_steps=64", "--set", "episode_steps=100",
                 "--set", "max_iterations=4", "--minutes", "30", "--seed", "1", "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "rllib iter" in printed and "agent-steps/s" in printed

    summary = json.loads(out.with_suffix(".train.json").read_text())
    assert summary["engine"] == "rllib" and summary["iterations"] == 4  # max_iterations, not the minutes
    # rollout_steps env steps x 2 cars per iteration, plus about one agent-step per off-track (RLlib's count
    # of an ended car agent and the new agent id it drives on under)
    assert summary["iterations"] * 64 * 2 <= summary["agent_steps"] <= summary["iterations"] * 64 * 4
    assert summary["car_return_last"] is not None  # env episodes (100 steps) finished and were logged

    # the RLlib checkpoint holds the shared module; its weights are exactly the agent file's
    ckpt = out.with_name("r.rllib")
    assert (ckpt / "rllib_checkpoint.json").exists()
    module = RLModule.from_checkpoint(ckpt / "learner_group" / "learner" / "rl_module" / MODULE_ID)
    agent = load_agent(out, step_budget=None)
    assert agent.net.network == "MULTIRACE_TINY_CNN" and agent.image_shape == (120, 160, 1)
    module_state = net_state_from_module(module.get_state())
    for key, value in agent.net.state_dict().items():
        assert torch.equal(module_state[key], value), key
    # the module and the agent file choose the same greedy action
    image = np.random.default_rng(0).integers(0, 255, (3, 120, 160, 1), dtype=np.uint8)
    with torch.no_grad():
        logits = module.forward_inference({"obs": torch.from_numpy(image)})["action_dist_inputs"].numpy()
        ours = agent.net(torch.from_numpy(image)).numpy()
    assert np.array_equal(logits.argmax(1), ours.argmax(1))

    # and it races under `multirace race` rules (a generous step budget: CI machines are busy). Four
    # iterations do not make a driver, so whether it completes the lap is luck: it must race, not forfeit,
    # and drive forward (every speed of its action space is forward)
    from multirace.train.run import evaluate_time_trial

    row = evaluate_time_trial(out, "Oval_track", laps=1, seed=0)
    assert row["status"] != "forfeit", row["reason"]
    assert row["progress"] > 0
