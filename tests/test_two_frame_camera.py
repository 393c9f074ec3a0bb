"""FRONT_FACING_CAMERA_TWO_FRAMES: one grey camera read twice, this step's image and the previous one's."""
import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test

import multirace
from multirace.deepracer.export import ExportError, export_agent
from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import AgentController, AgentFileError, load_agent, make_metadata, save_agent
from multirace.racing.nets import TINY, CameraNet, build_net
from multirace.racing.runner import RaceConfig, make_controller, run_race
from multirace.sensors.suite import SensorSuite, parse_sensors, race_suite
from multirace.train.warmstart import load_init_agent

SPACE = load_action_space(None)
FRAMES = ["FRONT_FACING_CAMERA_TWO_FRAMES"]
ACTIONS = [{"car_0": 6, "car_1": 8}, {"car_0": 4, "car_1": 8}, {"car_0": 9, "car_1": 2}] * 4


def _drive(sensor):
    """The observations of a 2-car race driven by ACTIONS from seed 5, reset included."""
    env = multirace.parallel_env(num_cars=2, race="head_to_head", sensor=sensor, obstacles=0)
    seen = [env.reset(seed=5)[0]]
    seen += [env.step(actions)[0] for actions in ACTIONS]
    return env, seen


def test_the_frames_are_the_single_cameras_image_now_and_a_step_before():
    env, frames = _drive(FRAMES)
    assert env.observation_space("car_0").shape == (120, 160, 2) and env.sensors == SensorSuite("frames")
    _, single = _drive(None)
    for step, (pair, image) in enumerate(zip(frames, single)):
        for agent in ("car_0", "car_1"):
            assert pair[agent].dtype == np.uint8 and np.array_equal(pair[agent][..., 0], image[agent])
            before = single[max(step - 1, 0)][agent]  # on the grid the image is paired with itself
            assert np.array_equal(pair[agent][..., 1], before)
    assert not np.array_equal(frames[-1]["car_0"][..., 0], frames[-1]["car_0"][..., 1])  # the car moved
    again, _ = env.reset(seed=6)
    assert all(np.array_equal(again[a][..., 0], again[a][..., 1]) for a in again)  # a reset forgets the last
    env.close()


def test_a_car_put_somewhere_else_starts_its_frames_afresh_and_the_env_passes_the_api_test():
    env = multirace.parallel_env(num_cars=2, sensor=FRAMES, obstacles=0, max_steps=20)
    env.reset(seed=1)
    env.step({"car_0": 6, "car_1": 6})
    moved = env.move_cars({0: (5.0, 0.0)})
    assert np.array_equal(moved["car_0"][..., 0], moved["car_0"][..., 1])
    assert not np.array_equal(moved["car_1"][..., 0], moved["car_1"][..., 1])  # car_1 was not moved
    parallel_api_test(multirace.parallel_env(num_cars=2, sensor=FRAMES, max_steps=20), num_cycles=5)
    env.close()


def test_a_single_camera_agent_starts_a_two_frame_net_that_drives_as_it_did(tmp_path):
    single = build_net(TINY, (120, 160, 1), SPACE)
    path = save_agent(tmp_path / "single.pt", single, make_metadata(SPACE, TINY, "single"))
    frames = CameraNet(TINY, (120, 160, 2), single.num_outputs, value_head=True)
    load_init_agent(path, frames)
    images = torch.randint(0, 256, (3, 120, 160, 2), dtype=torch.uint8)
    with torch.no_grad():
        assert torch.allclose(frames(images), single(images[..., 0]), atol=1e-6)
    stereo_agent = save_agent(tmp_path / "pair.pt", build_net(TINY, (120, 160, 2), SPACE),
                              make_metadata(SPACE, TINY, "pair", (120, 160, 2), sensor=["STEREO_CAMERAS"]))
    with pytest.raises(ValueError, match="pair.pt: the agent reads 2-channel images, the net 3"):
        load_init_agent(stereo_agent, CameraNet(TINY, (120, 160, 3), single.num_outputs))


def test_a_two_frame_agent_races_beside_single_camera_agents_and_does_not_export(tmp_path):
    net = build_net(TINY, (120, 160, 2), SPACE)
    path = save_agent(tmp_path / "frames.pt", net, make_metadata(SPACE, TINY, "framer", (120, 160, 2), sensor=FRAMES))
    agent = load_agent(path, step_budget=None)
    assert agent.metadata["sensor"] == FRAMES and agent.sensors == SensorSuite("frames")
    pair = np.random.default_rng(0).integers(0, 256, (120, 160, 2), dtype=np.uint8)
    assert np.array_equal(agent.reads(pair), pair)
    with pytest.raises(ValueError, match="does not match the 120x160x2"):
        agent.reads(pair[..., 0])  # a single camera's race gives it one frame
    with pytest.raises(ExportError, match="FRONT_FACING_CAMERA_TWO_FRAMES.*DeepRacer's cars do not have"):
        export_agent(path, tmp_path / "frames.tar.gz")
    single = save_agent(tmp_path / "single.pt", CameraNet(TINY, (120, 160, 1), 10),
                        make_metadata(SPACE, TINY, "single"))
    assert race_suite([SensorSuite(), parse_sensors(FRAMES), SensorSuite("mono", "lidar")]) == \
        SensorSuite("frames", "lidar")
    with pytest.raises(ValueError, match="race them apart"):
        race_suite([parse_sensors(FRAMES), parse_sensors(["STEREO_CAMERAS"])])
    controllers = [AgentController(path, step_budget=0.5), make_controller(str(single)),
                   make_controller("bot:follow@1.0")]
    result = run_race(controllers, RaceConfig(race="head_to_head", laps=1, max_steps=30, seed=2))
    assert {car["name"]: car["status"] for car in result["cars"]} == {
        "framer": "not_finished", "single": "not_finished", "bot:follow@1.0": "not_finished"}


def test_an_image_of_the_wrong_channels_for_two_frames_is_refused_naming_the_file(tmp_path):
    net = build_net(TINY, (120, 160, 1), SPACE)
    with pytest.raises(AgentFileError, match="one.pt: .*the net reads 1-channel images; "
                                             "FRONT_FACING_CAMERA_TWO_FRAMES gives 2"):
        save_agent(tmp_path / "one.pt", net, make_metadata(SPACE, TINY, "one", sensor=FRAMES))


def test_ppo_trains_a_two_frame_agent_through_the_worker_envs(tmp_path):
    from multirace.cli import main as cli_main

    out = tmp_path / "ppo_frames.pt"
    assert cli_main(["train", "--config", "tiny", "--minutes", "0.05", "--no-progress", "--envs", "1", "--cars", "1",
                     "--set", f'sensor=["{FRAMES[0]}"]', "--out", str(out)]) == 0
    agent = load_agent(out)
    assert agent.metadata["sensor"] == FRAMES and agent.image_shape == (120, 160, 2)
