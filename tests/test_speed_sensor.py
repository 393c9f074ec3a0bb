"""The worked example of the sensor registry: SPEED, multirace's own speed sensor (DeepRacer's cars have none)."""
import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test

import multirace
from multirace.deepracer.export import ExportError, export_agent
from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import AgentController, AgentFileError, load_agent, make_metadata, save_agent
from multirace.racing.nets import TINY, CameraNet, add_vector_inputs, build_net
from multirace.racing.runner import RaceConfig, make_controller, run_race
from multirace.sensors.suite import SensorSuite, parse_sensors, race_suite

SPACE = load_action_space(None)
SPEED = ["FRONT_FACING_CAMERA", "SPEED"]


def test_speed_observations_are_the_cars_speed_in_the_race_state():
    env = multirace.parallel_env(num_cars=2, race="head_to_head", sensor=SPEED, obstacles=0)
    space = env.observation_space("car_0")
    assert set(space.spaces) == {"camera", "speed"} and space["speed"].shape == (1,)
    assert space["speed"].dtype == np.float32 and space["camera"].shape == (120, 160)
    obs, _ = env.reset(seed=3)
    assert obs["car_0"]["speed"].tolist() == [0.0]  # on the grid, at rest
    speeds = []
    for _ in range(12):
        obs, *_ = env.step({"car_0": 6, "car_1": 8})
        for i, agent in enumerate(env.possible_agents):
            reading = obs[agent]["speed"]
            assert reading.shape == (1,) and reading.dtype == np.float32 and space["speed"].contains(reading)
            assert reading[0] == np.float32(env.race_state.cars[i].speed)
        speeds.append(float(obs["car_0"]["speed"][0]))
    assert speeds[-1] > 0.3  # it drove off: the sensor follows the car
    env.close()


def test_speed_joins_a_lidar_in_one_observation_and_passes_the_api_test():
    env = multirace.parallel_env(num_cars=2, sensor=["STEREO_CAMERAS", "LIDAR", "SPEED"], max_steps=20)
    obs, _ = env.reset(seed=0)
    assert set(obs["car_0"]) == {"camera", "lidar", "speed"} and obs["car_0"]["lidar"].shape == (64,)
    assert env.sensors == SensorSuite("stereo", "lidar", ("speed",))
    parallel_api_test(env, num_cycles=5)
    env.close()


def test_speed_in_sensor_lists_and_races():
    assert parse_sensors(["SPEED", "FRONT_FACING_CAMERA"]).names == SPEED
    assert race_suite([SensorSuite(), parse_sensors(SPEED), SensorSuite("mono", "sector")]) == \
        SensorSuite("mono", "sector", ("speed",))
    with pytest.raises(ValueError, match="more than one"):
        parse_sensors(["FRONT_FACING_CAMERA", "SPEED", "SPEED"])


def test_an_unknown_sensor_is_an_error_naming_the_field(tmp_path):
    with pytest.raises(ValueError, match="sensor: unknown sensor 'SPEEDOMETER'.*SPEED"):
        multirace.parallel_env(sensor=["FRONT_FACING_CAMERA", "SPEEDOMETER"])
    net = CameraNet(TINY, (120, 160, 1), 10, vector_inputs={"speed": 1})
    path = save_agent(tmp_path / "speed.pt", net, make_metadata(SPACE, TINY, "speedy", sensor=SPEED))
    payload = torch.load(path, weights_only=True)
    payload["metadata"] = payload["metadata"].replace('"SPEED"', '"SPEEDOMETER"')
    torch.save(payload, tmp_path / "bad.pt")
    with pytest.raises(AgentFileError, match="bad.pt: metadata field 'sensor': unknown sensor 'SPEEDOMETER'"):
        load_agent(tmp_path / "bad.pt", step_budget=None)


def test_a_speed_agent_saves_loads_and_races(tmp_path):
    net = build_net(TINY, (120, 160, 1), SPACE, vector_inputs=parse_sensors(SPEED).vector_inputs)
    path = save_agent(tmp_path / "speed.pt", net, make_metadata(SPACE, TINY, "speedy", sensor=SPEED))
    agent = load_agent(path, step_budget=None)
    assert agent.metadata["sensor"] == SPEED and agent.net.vector_inputs == {"speed": 1}
    image = np.zeros((120, 160), np.uint8)
    seen = agent.reads({"camera": image, "speed": np.array([1.5], np.float32)})
    with torch.no_grad():
        assert np.allclose(agent.outputs(seen), net({"camera": torch.from_numpy(image),
                                                     "speed": torch.tensor([1.5])}).numpy())
    with pytest.raises(ValueError, match="SPEED observation"):
        agent.reads(image)  # a camera-only race gives it no speed
    with pytest.raises(ExportError, match="SPEED.*DeepRacer's cars do not have"):
        export_agent(path, tmp_path / "speed.tar.gz")
    camera_only = save_agent(tmp_path / "camera.pt", CameraNet(TINY, (120, 160, 1), 10),
                             make_metadata(SPACE, TINY, "camera_car"))
    controllers = [AgentController(path, step_budget=0.5), make_controller(str(camera_only)),
                   make_controller("bot:follow@1.0")]
    result = run_race(controllers, RaceConfig(race="head_to_head", laps=1, max_steps=30, seed=2))
    statuses = {car["name"]: car["status"] for car in result["cars"]}
    assert statuses == {"speedy": "not_finished", "camera_car": "not_finished", "bot:follow@1.0": "not_finished"}


def test_adding_speed_to_a_net_keeps_its_policy():
    net = build_net(TINY, (120, 160, 1), SPACE, value_head=True, lidar_samples=64)
    wide = add_vector_inputs(net, {"speed": 1})
    images = torch.randint(0, 256, (3, 120, 160), dtype=torch.uint8)
    ranges = torch.rand(3, 64)
    out, value = net.forward_all({"camera": images, "lidar": ranges})
    wide_out, wide_value = wide.forward_all({"camera": images, "lidar": ranges, "speed": torch.rand(3, 1)})
    assert torch.allclose(out, wide_out) and torch.allclose(value, wide_value)
    with pytest.raises(ValueError, match="'speed'"):
        wide({"camera": images, "lidar": ranges})


def test_dagger_trains_a_speed_agent_from_a_camera_agent(tmp_path):
    from multirace.train.imitate import ImitationConfig, run_dagger

    init = save_agent(tmp_path / "camera.pt", CameraNet(TINY, (120, 160, 1), 10),
                      make_metadata(SPACE, TINY, "camera_car"))
    summary = run_dagger(ImitationConfig(out=str(tmp_path / "speedy.pt"), tracks=("Oval_track",), both_directions=False,
                                         minutes=0.05, rollout_steps=48, train_steps=4, batch_size=16,
                                         max_samples=600, progress=False, threads=1, sensor=SPEED, init=str(init)))
    agent = load_agent(summary["out"], step_budget=None)
    assert agent.metadata["sensor"] == SPEED and agent.net.vector_inputs == {"speed": 1}
    assert agent.metadata["training"]["init"]["name"] == "camera_car"


def test_ppo_trains_an_agent_that_reads_speed_through_the_worker_envs(tmp_path):
    from multirace.cli import main as cli_main

    out = tmp_path / "ppo_speed.pt"
    assert cli_main(["train", "--config", "tiny", "--minutes", "0.05", "--no-progress", "--envs", "1", "--cars", "1",
                     "--set", 'sensor=["FRONT_FACING_CAMERA", "SPEED"]', "--out", str(out)]) == 0
    agent = load_agent(out)
    assert agent.metadata["sensor"] == ["FRONT_FACING_CAMERA", "SPEED"] and agent.net.vector_inputs == {"speed": 1}
