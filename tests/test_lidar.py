"""The optional LIDAR: what its beams see in a real PyBullet world, LIDAR agent files, races and training."""
import json
import math

import numpy as np
import pytest
import torch

import multirace
from multirace.racing.agentfile import AgentController, AgentFileError, load_agent, make_metadata, save_agent
from multirace.environment.actions import load_action_space
from multirace.sensors.lidar import LidarSpec
from multirace.racing.nets import SMALL, TINY, CameraNet, add_lidar_inputs, build_net
from multirace.racing.runner import RaceConfig, make_controller, run_race

SPACE = load_action_space(None)


def scan_with(others, lidar_env):
    """Noise-free ranges of car 0 at the origin facing +x, with the other cars at `others` [(x, y, yaw)]."""
    env = lidar_env
    env.world.place_car(0, 0.0, 0.0, 0.0)
    for i in range(1, env.total_cars):
        x, y, yaw = others[i - 1] if i - 1 < len(others) else (0.0, 20.0 + 3 * i, 0.0)  # far away
        env.world.place_car(i, x, y, yaw)
    return env.lidar.scan(env.world, [0])[0]


@pytest.fixture
def lidar_env():
    env = multirace.parallel_env(num_cars=3, race="head_to_head", lidar=True)
    env.reset(seed=1)
    yield env
    env.close()


def test_observations_are_camera_and_lidar_dicts_with_deepracer_ranges():
    env = multirace.parallel_env(num_cars=2, race="head_to_head", lidar=True)
    obs, _ = env.reset(seed=0)
    space = env.observation_space("car_0")
    assert set(space.spaces) == {"camera", "lidar"} and space["lidar"].shape == (64,)
    assert space["camera"].shape == (120, 160)  # the grey image as without a LIDAR: (H, W)
    for agent in env.possible_agents:
        assert space.contains(obs[agent])
    obs, *_ = env.step({a: 0 for a in env.agents})
    assert space.contains(obs["car_1"])
    env.close()
    plain = multirace.parallel_env(num_cars=1)
    assert isinstance(plain.reset(seed=0)[0]["car_0"], np.ndarray)  # the default stays a bare image
    plain.close()


def test_an_empty_scene_reads_max_range_and_the_own_body_is_never_seen(lidar_env):
    ranges = scan_with([], lidar_env)
    assert np.allclose(ranges, LidarSpec().max_range)


def test_a_car_ahead_and_a_car_alongside_are_seen_at_their_distance_and_bearing(lidar_env):
    spec, car = LidarSpec(), lidar_env.car_spec
    angles = spec.angles()
    # a car 0.6 m straight ahead: the beams either side of straight ahead meet its rear face
    ranges = scan_with([(0.6, 0.0, 0.0)], lidar_env)
    ahead = np.argsort(np.abs(angles))[:2]
    assert np.allclose(ranges[ahead], (0.6 - car.length / 2) / np.cos(angles[ahead]), atol=0.01)
    assert np.allclose(ranges[np.abs(angles) > math.radians(40)], spec.max_range)  # nothing to the sides
    # a car alongside on the left, 0.35 m centre to centre: the left beam reads the gap to its near side
    ranges = scan_with([(0.0, 0.35, 0.0)], lidar_env)
    left = int(np.argmin(np.abs(angles - math.pi / 2)))
    assert ranges[left] == pytest.approx((0.35 - car.width / 2) / math.sin(angles[left]), abs=0.01)
    assert np.allclose(ranges[angles < 0], spec.max_range)  # the right side is clear
    # right behind and beyond the 300-degree fan's back edge: a car 0.5 m straight behind is not seen
    assert np.allclose(scan_with([(-0.5, 0.0, 0.0)], lidar_env), spec.max_range)


def test_ranges_are_clipped_to_deepracers_band(lidar_env):
    ranges = scan_with([(0.0, 0.21, 0.0)], lidar_env)  # sides almost touching: 1 cm gap
    assert ranges.min() == pytest.approx(LidarSpec().min_range)


def test_add_lidar_inputs_keeps_the_camera_policy_unchanged():
    camera_only = build_net(TINY, (120, 160, 1), None, value_head=True)
    wide = add_lidar_inputs(camera_only, 64)
    images = torch.randint(0, 256, (4, 120, 160, 1), dtype=torch.uint8)
    ranges = torch.rand(4, 64)
    out, value = camera_only.forward_all(images)
    wide_out, wide_value = wide.forward_all({"camera": images, "lidar": ranges})
    assert torch.allclose(out, wide_out) and torch.allclose(value, wide_value)
    with pytest.raises(ValueError, match="lidar"):
        wide(images)  # a LIDAR net needs its scan


def save_lidar_agent(path, name="lidar_car"):
    net = CameraNet(SMALL, (120, 160, 1), 10, lidar_samples=64)
    return save_agent(path, net, make_metadata(SPACE, SMALL, name, lidar=True))


def test_lidar_agent_file_round_trips_and_races_camera_only_agents(tmp_path):
    path = save_lidar_agent(tmp_path / "lidar.pt")
    agent = load_agent(path, step_budget=None)
    assert agent.metadata["sensor"] == ["FRONT_FACING_CAMERA", "LIDAR"] and agent.lidar_samples == 64
    camera_only = tmp_path / "camera.pt"
    save_agent(camera_only, CameraNet(SMALL, (120, 160, 1), 10), make_metadata(SPACE, SMALL, "camera_car"))
    controllers = [make_controller(str(path)), make_controller(str(camera_only)), make_controller("bot:follow@1.0")]
    result = run_race(controllers, RaceConfig(race="head_to_head", laps=1, max_steps=30, seed=2))
    statuses = {car["name"]: car["status"] for car in result["cars"]}
    assert statuses == {"lidar_car": "not_finished", "camera_car": "not_finished",
                        "bot:follow@1.0": "not_finished"}  # all drove to the step limit, nobody forfeited


def test_a_lidar_agent_in_a_camera_only_env_forfeits_with_the_reason(tmp_path):
    controller = AgentController(save_lidar_agent(tmp_path / "lidar.pt"))
    env = multirace.parallel_env(num_cars=1, action_space=None)
    obs, infos = env.reset(seed=0)
    controller.reset(env, 0)
    with pytest.raises(Exception, match="LIDAR observation"):
        controller.act(obs["car_0"], infos["car_0"])
    env.close()


@pytest.mark.parametrize("sensor, message", [
    (["LIDAR"], "'sensor'.*FRONT_FACING_CAMERA"),
    (["FRONT_FACING_CAMERA", "SECTOR_LIDAR"], "8 SECTOR_LIDAR sectors \\(metadata field 'sensor'\\).*lidar.0.weight"),
])
def test_bad_sensor_lists_are_refused_naming_the_field(tmp_path, sensor, message):
    path = save_lidar_agent(tmp_path / "lidar.pt")
    payload = torch.load(path, weights_only=True)
    payload["metadata"] = json.dumps({**json.loads(payload["metadata"]), "sensor": sensor})
    torch.save(payload, tmp_path / "bad.pt")
    with pytest.raises(AgentFileError, match=message) as err:
        load_agent(tmp_path / "bad.pt", step_budget=None)
    assert str(tmp_path / "bad.pt") in str(err.value)


def test_camera_only_weights_under_a_lidar_sensor_are_refused(tmp_path):
    path = tmp_path / "camera.pt"
    save_agent(path, CameraNet(SMALL, (120, 160, 1), 10), make_metadata(SPACE, SMALL, "camera_car"))
    payload = torch.load(path, weights_only=True)
    payload["metadata"] = json.dumps({**json.loads(payload["metadata"]), "sensor": ["FRONT_FACING_CAMERA", "LIDAR"]})
    torch.save(payload, tmp_path / "mislabelled.pt")
    with pytest.raises(AgentFileError, match="64 LIDAR ranges"):
        load_agent(tmp_path / "mislabelled.pt", step_budget=None)


def test_save_refuses_metadata_that_disagrees_with_the_net(tmp_path):
    net = CameraNet(SMALL, (120, 160, 1), 10, lidar_samples=64)
    with pytest.raises(AgentFileError, match="sensor"):
        save_agent(tmp_path / "x.pt", net, make_metadata(SPACE, SMALL, "x"))


def test_training_with_lidar_from_a_camera_agent_writes_a_lidar_agent_that_races(tmp_path):
    from multirace.train.config import make_config
    from multirace.train.ppo import train

    init = tmp_path / "camera.pt"
    save_agent(init, CameraNet(TINY, (120, 160, 1), 10), make_metadata(SPACE, TINY, "camera_car"))
    config = make_config("tiny", tracks=("Oval_track",), minutes=0.1, seed=1, progress=False, lidar=True,
                         bots=("follow@0.5",))
    out = tmp_path / "lidar_ppo.pt"
    summary = train(config, out, init=init)
    assert summary["agent_steps"] > 0
    agent = load_agent(out, step_budget=None)
    assert agent.lidar_samples == 64 and agent.metadata["sensor"][-1] == "LIDAR"
    assert agent.metadata["training"]["init"]["name"] == "camera_car"  # what it started from travels with it
    result = run_race([AgentController(out, step_budget=0.5)],
                      RaceConfig(track="Oval_track", race="time_trial", laps=1, max_steps=30))
    assert result["cars"][0]["status"] == "not_finished"  # drove to the step limit from camera and LIDAR


def test_scanning_the_lidar_changes_no_other_random_draw():
    """The same seed gives the same race with or without a LIDAR (its noise has its own stream)."""
    poses = []
    for lidar in (False, True):
        env = multirace.parallel_env(num_cars=2, race="head_to_head", lidar=lidar)
        env.reset(seed=4)
        for _ in range(20):
            env.step({"car_0": 5, "car_1": 3})
        poses.append(env.world.poses.copy())
        env.close()
    assert np.array_equal(poses[0], poses[1])


def test_replays_record_the_lidar_echoes_and_read_them_back(tmp_path):
    from multirace.recording.replay import ReplayRecorder
    from multirace.recording.replay_reader import replay_summary

    agent = save_lidar_agent(tmp_path / "lidar.pt")
    run_race([make_controller(str(agent)), make_controller("bot:follow@1.0")],
             RaceConfig(race="head_to_head", laps=1, max_steps=40, seed=1),
             recorders=[ReplayRecorder(tmp_path / "race.rrd")])
    car = replay_summary(tmp_path / "race.rrd", poses=False)["cars"][0]
    assert car["lidar_scans"] == car["images"] > 0  # one scan with each camera frame
    assert car["lidar_echoes"] > 0  # the bot on the staggered grid is within a metre at the start


def test_the_robustness_report_races_a_lidar_agent_in_traffic_and_under_perturbations(tmp_path):
    from multirace.train.evaluate import race_agent

    row = race_agent(save_lidar_agent(tmp_path / "lidar.pt"), laps=1, bots=("follow@1.0",), race="head_to_head",
                     randomize="mild", max_steps=20)
    assert row["status"] == "not_finished" and row["reason"].startswith("step limit")  # drove, did not forfeit


def _inside_any(points, boxes):
    """Whether each point (M, 2) lies inside one of the rectangles (B, 5) of (x, y, yaw, half length, half width)."""
    inside = np.zeros(len(points), bool)
    for x, y, yaw, half_l, half_w in boxes:
        rx, ry = points[:, 0] - x, points[:, 1] - y
        along, across = rx * math.cos(yaw) + ry * math.sin(yaw), -rx * math.sin(yaw) + ry * math.cos(yaw)
        inside |= (np.abs(along) <= half_l + 1e-6) & (np.abs(across) <= half_w + 1e-6)
    return inside


def test_the_beams_read_what_pybullets_rays_read():
    """The compiled beams against PyBullet's `rayTestBatch` in crowded scenes: the same hit fractions to
    rounding on 98 % of the beams; PyBullet's ray cast is iterative and stops within about a millimetre of a
    side, mostly before it, so each of its hits lies between ours on boxes grown by 1.5 mm and ours plus 1 mm
    (a beam that grazes a corner can meet PyBullet's box and miss ours).
    Beams that start inside another body are left out (PyBullet's rays answer those either way)."""
    from multirace.sensors.beams import beam_fractions, scene_boxes

    env = multirace.parallel_env(num_cars=4, obstacles=3, race="head_to_head", lidar=True)
    env.reset(seed=2)
    world, lidar, rng = env.world, env.lidar, np.random.default_rng(5)
    compared = hits = exact = 0
    for _ in range(30):
        for i in range(4):  # the cars within a metre of the first box, any way round
            bx, by, _ = world.obstacle_poses[0]
            world.place_car(i, bx + rng.uniform(-0.8, 0.8), by + rng.uniform(-0.8, 0.8), rng.uniform(-math.pi, math.pi))
        poses = world.poses[:4]
        headings = poses[:, 2:3] + lidar.angles
        directions = np.stack([np.cos(headings), np.sin(headings)], axis=-1)
        starts = (poses[:, None, :2] + directions * lidar.start[None, :, None]).reshape(-1, 2)
        ends = (poses[:, None, :2] + directions * lidar.spec.max_range).reshape(-1, 2)
        height = np.full((len(starts), 1), lidar.height)
        theirs = world.cast_rays(np.hstack([starts, height]), np.hstack([ends, height]))
        boxes = scene_boxes(world)
        grown = boxes + np.array([0, 0, 0, 0.0015, 0.0015])
        ours, ours_grown = beam_fractions(starts, ends, boxes), beam_fractions(starts, ends, grown)
        outside = ~_inside_any(starts, boxes)
        assert np.all(ours_grown[outside] <= theirs[outside] + 1e-9)
        assert np.all(theirs[outside] <= ours[outside] + 1e-3 / 0.85)
        exact += (np.abs(ours[outside] - theirs[outside]) < 1e-9).sum()
        compared += outside.sum()
        hits += (theirs[outside] < 1).sum()
    assert compared > 5000 and hits > 500  # crowded: many beams met something
    assert exact >= 0.98 * compared


def test_a_beam_from_inside_a_body_meets_it_heading_in_and_not_heading_out():
    from multirace.sensors.beams import beam_fractions

    box = np.array([[0.0, 0.0, 0.0, 0.15, 0.15]])  # a 0.3 m box at the origin
    starts = np.array([[0.14, 0.0], [0.14, 0.0], [-1.0, 0.0]])  # 1 cm inside its +x side (twice); outside
    ends = np.array([[-0.5, 0.0], [1.0, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(beam_fractions(starts, ends, box), [0.0, 1.0, 0.85])
