"""Stereo and sector-LIDAR agents: made by `multirace imitate` and `multirace train`, raced against camera and
LIDAR agents, exported to the car (real OpenVINO), and refused when their metadata disagrees with itself."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import multirace
from multirace.cli import main as cli_main
from multirace.deepracer.export import input_name
from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import AgentFileError, load_agent, make_metadata, save_agent
from multirace.racing.nets import TINY, build_net
from multirace.racing.runner import RaceConfig, make_controller, resolve_agent_path, run_race
from multirace.sensors.lidar import sector_lidar
from helpers import car_input, seeded_lidar_agent
from test_export import openvino_policy, unpack

STEREO = ["STEREO_CAMERAS"]
SECTOR = ["FRONT_FACING_CAMERA", "SECTOR_LIDAR"]
SENSORS = {"stereo": STEREO, "sector": SECTOR}
SPACE = load_action_space(None)


def _make_agents(folder, prefix: str, command) -> dict:
    """{kind: agent file} for each sensor list, written by the CLI arguments `command(out, sensor)`."""
    paths = {kind: folder / f"{prefix}{kind}.pt" for kind in SENSORS}
    for kind, sensor in SENSORS.items():
        assert cli_main(command(str(paths[kind]), sensor)) == 0
    return paths


@pytest.fixture(scope="module")
def imitated(tmp_path_factory):
    """A stereo and a sector-LIDAR agent from tiny `multirace imitate` runs."""
    return _make_agents(tmp_path_factory.mktemp("imitate"), "", lambda out, sensor: [
        "imitate", "--out", out, "--tracks", "reinvent_base", "--one-direction", "--minutes", "0.05",
        "--max-samples", "2000", "--threads", "1", "--sensor", *sensor])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A stereo and a sector-LIDAR agent from a few seconds of `multirace train --config tiny`."""
    return _make_agents(tmp_path_factory.mktemp("train"), "ppo_", lambda out, sensor: [
        "train", "--config", "tiny", "--minutes", "0.05", "--no-progress", "--envs", "1", "--cars", "1",
        "--set", f"sensor={json.dumps(sensor)}", "--out", out])


@pytest.fixture(scope="module")
def lidar_path(tmp_path_factory):
    """A camera + LIDAR agent file (seeded random weights)."""
    return seeded_lidar_agent(tmp_path_factory.mktemp("lidar") / "lidar.pt")


@pytest.fixture(scope="module")
def stereo_lidar_frames():
    """Observations of a race env that gives a stereo pair and the full LIDAR scan, a bot close ahead."""
    env = multirace.parallel_env(num_cars=1, race="head_to_head", bots=("follow@0.3",), obstacles=0,
                                 sensor=["STEREO_CAMERAS", "LIDAR"])
    env.reset(seed=0)
    observations = env.move_cars({0: (1.0, 0.0), 1: (1.5, 0.0)})  # the bot's tail 0.3 m ahead of the LIDAR
    shots = [observations["car_0"]]
    for step in range(12):
        observations, *_ = env.step({"car_0": 6})
        if step % 4 == 3:
            shots.append(observations["car_0"])
    env.close()
    return shots


@pytest.mark.parametrize("kind, channels, inputs", [("stereo", 2, 0), ("sector", 1, 8)])
def test_imitate_and_train_write_agents_that_declare_their_sensors(imitated, trained, kind, channels, inputs):
    for path, algorithm in ((imitated[kind], "dagger"), (trained[kind], "clipped_ppo")):
        agent = load_agent(path, step_budget=None)
        assert agent.metadata["sensor"] == SENSORS[kind] and agent.metadata["training_algorithm"] == algorithm
        assert agent.image_shape == (120, 160, channels) and agent.lidar_samples == inputs
        assert multirace.load_agent(path).sensor == SENSORS[kind]
    command = load_agent(imitated[kind], step_budget=None).metadata["training"]["command"]
    assert command.endswith("--sensor " + " ".join(SENSORS[kind]))


def test_each_agent_takes_what_it_reads_from_the_race_observation(imitated, stereo_lidar_frames, lidar_path):
    obs = stereo_lidar_frames[0]
    mono = load_agent(resolve_agent_path("dagger_small"), step_budget=None)
    lidar = load_agent(lidar_path, step_budget=None)
    stereo, sector = (load_agent(imitated[k], step_budget=None) for k in ("stereo", "sector"))
    left = obs["camera"][:, :, 0]  # a single-camera agent reads the left camera, as the env gives one: (H, W)
    assert np.array_equal(mono.reads(obs), left)
    assert np.array_equal(stereo.reads(obs), obs["camera"])
    assert np.array_equal(lidar.reads(obs)["camera"], left) and np.array_equal(lidar.reads(obs)["lidar"], obs["lidar"])
    assert np.array_equal(sector.reads(obs)["lidar"], sector_lidar(obs["lidar"]))
    assert sector.reads(obs)["lidar"].max() == 1.0  # the bot ahead is within half a metre of a sector
    for path in (imitated["stereo"], imitated["sector"], "dagger_small", str(lidar_path)):
        steer, speed = multirace.load_agent(path).command(obs)
        assert -30 <= steer <= 30 and 0.1 <= speed <= 4.0
    with pytest.raises(ValueError, match="LIDAR observation"):
        sector.reads(obs["camera"])  # no scan at all


def test_they_race_camera_and_lidar_agents_and_nobody_forfeits(imitated, trained, lidar_path, tmp_path, capsys):
    entrants = [make_controller(str(imitated["stereo"])), make_controller(str(imitated["sector"])),
                make_controller("dagger_small"), make_controller(str(lidar_path))]
    result = run_race(entrants, RaceConfig(race="head_to_head", laps=1, max_steps=30, seed=1))
    assert [c["status"] for c in result["cars"]] == ["not_finished"] * 4, result["cars"]
    # on the command line, with a replay: no full-LIDAR entrant, so the race scans the 8 sectors
    args = ["race", str(trained["stereo"]), str(trained["sector"]), "dagger_small", "--laps", "1", "--max-steps",
            "20", "--json", str(tmp_path / "race.json"), "--replay", str(tmp_path / "race.rrd")]
    assert cli_main(args) == 0
    capsys.readouterr()
    cars = json.loads((tmp_path / "race.json").read_text())["cars"]
    assert sorted(c["name"] for c in cars) == ["dagger_small", "ppo_sector", "ppo_stereo"]
    assert all(c["status"] == "not_finished" for c in cars), cars
    from multirace.recording.replay_reader import replay_summary

    assert all(car["images"] > 0 for car in replay_summary(tmp_path / "race.rrd", poses=False)["cars"])


@pytest.mark.parametrize("kind", ["stereo", "sector"])
def test_export_runs_in_openvino_like_the_torch_policy(imitated, stereo_lidar_frames, tmp_path, kind):
    assert cli_main(["agent", "export", str(imitated[kind]), "--out", str(tmp_path / "model.tar.gz")]) == 0
    folder = unpack(tmp_path / "model.tar.gz", tmp_path / "car")
    assert json.loads((folder / "model_metadata.json").read_text())["sensor"] == SENSORS[kind]
    inputs = ({input_name("STEREO_CAMERAS"): [1, 120, 160, 2]} if kind == "stereo" else
              {input_name("FRONT_FACING_CAMERA"): [1, 120, 160, 1], input_name("SECTOR_LIDAR"): [1, 8]})
    _, compiled = openvino_policy(folder / "agent" / "model.pb", inputs)
    agent = load_agent(imitated[kind], step_budget=None)
    for obs in stereo_lidar_frames:
        seen = agent.reads(obs)
        if kind == "stereo":
            feed = {input_name("STEREO_CAMERAS") + ":0": car_input(seen)}  # raw 0-255 pixels
        else:
            feed = {input_name("FRONT_FACING_CAMERA") + ":0": car_input(seen["camera"]),
                    input_name("SECTOR_LIDAR") + ":0": seen["lidar"][None]}
        expected = torch.softmax(torch.from_numpy(agent.outputs(seen)[0]), 0).numpy()
        np.testing.assert_allclose(compiled(feed)[0][0], expected, atol=1e-5)


def _raw_agent_file(path, metadata: dict, net) -> None:
    """An agent file as a hand-edited one would be (no save_agent checks)."""
    torch.save({"format": "multirace-agent", "format_version": 1, "metadata": json.dumps(metadata),
                "state_dict": net.state_dict()}, path)


@pytest.mark.parametrize("sensor, channels, message", [
    (STEREO, 1, "'image' has 1 channel\\(s\\) but field 'sensor' \\['STEREO_CAMERAS'\\] declares STEREO_CAMERAS"),
    (["FRONT_FACING_CAMERA"], 2, "'image' has 2 channel\\(s\\) but field 'sensor'.*2 channels are "
                                 "STEREO_CAMERAS or FRONT_FACING_CAMERA_TWO_FRAMES"),
    (["STEREO_CAMERAS", "RADAR"], 2, "metadata field 'sensor': unknown sensor 'RADAR'"),
])
def test_metadata_whose_sensor_and_image_disagree_is_refused_naming_the_file(tmp_path, sensor, channels, message):
    net = build_net(TINY, (120, 160, channels), SPACE)
    path = tmp_path / "bad.pt"
    _raw_agent_file(path, {**make_metadata(SPACE, TINY, "bad", (120, 160, channels)), "sensor": sensor}, net)
    with pytest.raises(AgentFileError, match=message) as err:
        load_agent(path, step_budget=None)
    assert str(err.value).startswith(f"{path}: ")
    controller = make_controller(str(path))  # in a race it forfeits with that reason
    assert controller.agent is None and controller.error == str(err.value)


def test_save_agent_refuses_a_sensor_list_the_net_does_not_read(tmp_path):
    stereo = build_net(TINY, (120, 160, 2), SPACE)
    with pytest.raises(AgentFileError, match="x.pt: metadata field 'sensor'.*does not match the net, which reads "
                                             "\\['STEREO_CAMERAS'\\]"):
        save_agent(tmp_path / "x.pt", stereo, make_metadata(SPACE, TINY, "x", (120, 160, 2),
                                                             sensor=["STEREO_CAMERAS", "SECTOR_LIDAR"]))
    path = save_agent(tmp_path / "y.pt", stereo, make_metadata(SPACE, TINY, "y", (120, 160, 2), sensor=STEREO))
    assert load_agent(path, step_budget=None).sensors.names == STEREO


def test_unknown_sensor_on_the_command_line_is_refused_before_training(tmp_path, capsys):
    out = tmp_path / "never.pt"
    assert cli_main(["imitate", "--out", str(out), "--sensor", "FRONT_FACING_CAMERA", "RADAR"]) == 2
    assert "--sensor: unknown sensor 'RADAR'" in capsys.readouterr().err
    assert cli_main(["train", "--set", 'sensor=["SONAR"]', "--out", str(out), "--config", "tiny"]) == 2
    assert "sensor: unknown sensor 'SONAR'" in capsys.readouterr().err
    assert not out.exists()
