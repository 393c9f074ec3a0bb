"""`multirace agent blend`: weight-space blends of two agent files, and refusals of files that cannot blend."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from multirace.cli import main as cli_main
from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import AgentFileError, agent_summary, load_agent, make_metadata, save_agent
from multirace.racing.blend import blend_agents
from multirace.racing.nets import SMALL, TINY, build_net

REPO = Path(__file__).resolve().parents[1]
SPACE = load_action_space(None)


def _agent(path, seed, network=SMALL, space=SPACE, training=None):
    torch.manual_seed(seed)
    net = build_net(network, (120, 160, 1), space)
    extra = {"training": training} if training else {}
    return save_agent(path, net, make_metadata(space, network, path.stem, net.image_shape, **extra))


def _outputs(path, images):
    agent = load_agent(path, step_budget=None)
    return np.concatenate([agent.outputs(image) for image in images])


def test_a_blend_is_the_share_of_each_agents_weights_and_its_file_says_so(tmp_path):
    first, second = _agent(tmp_path / "fast.pt", 1), _agent(tmp_path / "careful.pt", 2)
    images = np.random.default_rng(0).integers(0, 256, (3, 120, 160), dtype=np.uint8)
    for share, same_as in ((1.0, first), (0.0, second)):
        out = blend_agents(first, second, share, tmp_path / f"b{share}.pt")
        np.testing.assert_allclose(_outputs(out, images), _outputs(same_as, images), rtol=1e-5, atol=1e-6)
    assert cli_main(["agent", "blend", str(first), str(second), "--share", "0.25", "--out",
                     str(tmp_path / "quarter.pt"), "--name", "quarter"]) == 0
    blend, a, b = (load_agent(path, step_budget=None) for path in (tmp_path / "quarter.pt", first, second))
    for key, value in blend.net.state_dict().items():
        if value.is_floating_point():
            expected = 0.25 * a.net.state_dict()[key] + 0.75 * b.net.state_dict()[key]
            torch.testing.assert_close(value, expected)
    assert blend.name == "quarter"
    assert agent_summary(tmp_path / "quarter.pt")["made_by"] == "weight blend (WiSE-FT), 0.25 fast + 0.75 careful"
    training = blend.metadata["training"]
    assert training["share_of_first"] == 0.25
    assert [part["sha256"] for part in training["blended"]] == [a.sha256, b.sha256]
    outputs = _outputs(tmp_path / "quarter.pt", images)
    assert not np.allclose(outputs, _outputs(first, images)) and not np.allclose(outputs, _outputs(second, images))


def test_agents_that_cannot_blend_are_refused_naming_the_file_and_field(tmp_path, capsys):
    first = _agent(tmp_path / "small.pt", 1)
    tiny = _agent(tmp_path / "tiny.pt", 2, network=TINY)
    with pytest.raises(AgentFileError, match=r"tiny\.pt: model_metadata field 'neural_network'"):
        blend_agents(first, tiny, 0.5, tmp_path / "out.pt")
    discrete = _agent(tmp_path / "discrete.pt", 3, space=load_action_space(REPO / "agents" / "action_space_fast.json"))
    with pytest.raises(AgentFileError, match=r"discrete\.pt: model_metadata field 'action_space'"):
        blend_agents(first, discrete, 0.5, tmp_path / "out.pt")
    assert not (tmp_path / "out.pt").exists()
    assert cli_main(["agent", "blend", str(first), str(first), "--share", "1.5", "--out", str(tmp_path / "out.pt")]) == 2
    assert "argument --share: must be at least 0 and at most 1" in capsys.readouterr().err


def test_a_blend_has_trained_on_every_track_of_both_lineages(tmp_path):
    from multirace.train.evaluate import trained_tracks

    start = {"expert": "bot:racingline@0.9", "tracks": ["Oval_track"]}
    first = _agent(tmp_path / "fast.pt", 1, training={"expert": "teacher:t.teacher.pt", "tracks": ["Mexico_track"],
                                                      "init": {"file": "start.pt", "training": start}})
    second = _agent(tmp_path / "careful.pt", 2, training={"expert": "teacher:t.teacher.pt", "tracks": ["Aragon"]})
    blend = blend_agents(first, second, 0.75, tmp_path / "blend.pt")
    # evaluate's held-out split leaves out what either blended file, or a file it started from, trained on
    assert trained_tracks(blend) == {"Mexico_track", "Oval_track", "Aragon"}
    odd = _agent(tmp_path / "odd.pt", 3, training={"tracks": ["Aragon"], "blended": 7, "init": "b.pt"})
    assert trained_tracks(odd) == {"Aragon"}  # a malformed lineage is read as far as it goes
