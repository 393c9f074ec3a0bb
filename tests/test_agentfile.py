"""Agent files: round trip, refusal of unsafe pickles, validation errors, forfeits in real races."""
from __future__ import annotations

import copy
import gc
import json
import os
import pickle
import time
from pathlib import Path

import numpy as np

import multirace
import pytest
import torch

from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import (AgentController, AgentFileError, inspect_agent, load_agent, make_metadata,
                                 save_agent)
from multirace.cli import main as cli_main
from multirace.racing.nets import NETWORKS, SHALLOW, SMALL, TINY, CameraNet, build_net, channels_first
from multirace.racing.entrant import Forfeit
from multirace.racing.graphnet import GraphNet
from multirace.racing.runner import RaceConfig, make_controller, run_race
from helpers import overflow_on_camera_images, seeded_lidar_agent

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted((REPO / "agents").glob("*.pt"))
SPACE = load_action_space(None)


def _save(path, net=None, name="tester", **extra):
    torch.manual_seed(0)
    net = net or build_net(SMALL, (120, 160, 1), SPACE)
    return save_agent(path, net, make_metadata(SPACE, net.network, name, net.image_shape, **extra))


def _payload(path, metadata, state_dict):
    """Write a raw agent-file payload (bypassing save_agent's checks)."""
    torch.save({"format": "multirace-agent", "format_version": 1,
                "metadata": metadata if isinstance(metadata, str) else json.dumps(metadata),
                "state_dict": state_dict}, path)
    return path


@pytest.fixture
def good(tmp_path):
    return _save(tmp_path / "good.pt")


def test_round_trip(tmp_path):
    torch.manual_seed(1)
    net = build_net(SMALL, (120, 160, 1), SPACE, value_head=True)
    path = _save(tmp_path / "a.pt", net=net, name="round", training={"method": "test"})
    agent = load_agent(path)
    assert agent.name == "round"
    assert agent.metadata["neural_network"] == SMALL
    assert agent.metadata["action_space"] == SPACE.to_metadata()["action_space"]
    assert agent.metadata["image"] == {"height": 120, "width": 160, "channels": 1}
    assert agent.metadata["training"] == {"method": "test"}
    assert agent.net.has_value
    image = np.random.default_rng(0).integers(0, 256, (120, 160), dtype=np.uint8)  # a grey frame, as the env's
    net.eval()
    with torch.no_grad():
        expected = net(torch.from_numpy(image)).numpy()
        value = net.value(torch.from_numpy(image[None]))
    assert np.allclose(agent.outputs(agent.reads(image)), expected)
    assert value.shape == (1,)
    info = inspect_agent(path)
    assert info["valid"] and info["parameters"] == sum(p.numel() for p in net.parameters())
    assert len(info["sha256"]) == 64 and info["metadata"]["name"] == "round"
    assert path.stat().st_size < 2_000_000


def test_grey_agents_read_frames_with_or_without_the_channel_axis(good):
    agent = load_agent(good)
    frame = np.random.default_rng(2).integers(0, 256, (120, 160), dtype=np.uint8)
    pair = np.stack([frame, 255 - frame], axis=2)  # a stereo pair: the agent reads its left camera
    for observation in (frame, frame[:, :, None], pair):
        seen = agent.reads(observation)
        assert seen.shape == (120, 160) and np.array_equal(seen, frame)
    assert np.array_equal(agent.outputs(frame), agent.outputs(frame[:, :, None]))
    assert multirace.load_agent(good).command(frame[:, :, None]) == multirace.load_agent(good).command(frame)
    with pytest.raises(ValueError, match="120x160x1"):
        agent.reads(frame[:, :100])


def test_channels_first_takes_single_images_and_batches_with_or_without_the_grey_axis():
    frames = torch.randint(0, 256, (2, 120, 160), dtype=torch.uint8)
    for images in (frames, frames[..., None]):
        assert torch.equal(channels_first(images, (120, 160, 1)), frames[:, None])
        assert torch.equal(channels_first(images[0], (120, 160, 1)), frames[:1, None])
    colour = torch.randint(0, 256, (2, 120, 160, 3), dtype=torch.uint8)
    assert torch.equal(channels_first(colour, (120, 160, 3)), colour.permute(0, 3, 1, 2))
    assert torch.equal(channels_first(colour[1], (120, 160, 3)), colour[1:].permute(0, 3, 1, 2))
    for wrong, shape in ((frames, (120, 160, 3)), (frames[:, None], (120, 160, 1)), (colour, (120, 160, 1))):
        with pytest.raises(ValueError, match="the net reads"):
            channels_first(wrong, shape)


def test_networks_and_continuous_outputs():
    for network in NETWORKS:
        net = CameraNet(network, (120, 160, 1), 4)
        assert net(torch.zeros(2, 120, 160, dtype=torch.uint8)).shape == (2, 4)
        assert net(torch.zeros(2, 120, 160, 1, dtype=torch.uint8)).shape == (2, 4)
    shallow = CameraNet(SHALLOW, (120, 160, 1), 10)
    assert [m.kernel_size for m in shallow.conv if isinstance(m, torch.nn.Conv2d)] == [(8, 8), (4, 4), (3, 3)]
    assert shallow.fc[0].out_features == 512
    with pytest.raises(ValueError, match="unknown network"):
        CameraNet("NOPE", (120, 160, 1), 10)


@pytest.mark.parametrize("network", [SMALL, TINY])
def test_pooling_nets_compute_what_torch_average_pooling_does(network):
    """The pooled trunks run a faster pool; a net must still give what it gave with nn.AvgPool2d (shipped agents)."""
    net = CameraNet(network, (120, 160, 3), 10)
    reference = copy.deepcopy(net)
    reference.conv[0] = torch.nn.AvgPool2d(net.conv[0].kernel_size)
    images = torch.randint(0, 256, (5, 120, 160, 3), dtype=torch.uint8)
    with torch.no_grad():
        assert torch.allclose(net(images), reference(images), atol=1e-6)


def test_continuous_agent_acts(tmp_path):
    space = load_action_space("/work/shared/formats/model_metadata-continuous.json"
                              if Path("/work/shared/formats/model_metadata-continuous.json").exists() else
                              {"action_space": {"steering_angle": {"low": -30, "high": 30},
                                                "speed": {"low": 1, "high": 2}},
                               "action_space_type": "continuous"})
    net = build_net(SMALL, (120, 160, 1), space)
    path = save_agent(tmp_path / "c.pt", net, make_metadata(space, SMALL, "cont"))
    controller = AgentController(path)
    assert controller.agent is not None, controller.error
    steer, speed = controller.act(np.zeros((120, 160), np.uint8), {})
    assert -30 <= steer <= 30 and 1 <= speed <= 2


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.mark.parametrize("how", ["torch_save", "raw_pickle"])
def test_malicious_pickle_is_refused(tmp_path, how):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pt"
    evil = {"format": "multirace-agent", "format_version": 1, "metadata": "{}", "state_dict": _Evil(marker)}
    if how == "torch_save":
        torch.save(evil, path)
    else:
        path.write_bytes(pickle.dumps(_Evil(marker), protocol=2))
    with pytest.raises(AgentFileError, match="refused") as err:
        load_agent(path)
    assert str(path) in str(err.value)
    assert not marker.exists()
    controller = AgentController(path)  # in a race: forfeits, does not run the payload
    with pytest.raises(Forfeit, match="refused"):
        controller.act(np.zeros((120, 160, 1), np.uint8), {})
    assert not marker.exists()


def test_truncated_and_garbage_files(tmp_path, good):
    data = good.read_bytes()
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(AgentFileError, match="truncated") as err:
        load_agent(truncated)
    assert str(truncated) in str(err.value)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not an agent")
    with pytest.raises(AgentFileError, match="unreadable"):
        load_agent(garbage)
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(AgentFileError, match=str(empty)):
        load_agent(empty)
    with pytest.raises(FileNotFoundError):
        load_agent(tmp_path / "missing.pt")


def _good_metadata():
    return make_metadata(SPACE, SMALL, "meta")


@pytest.mark.parametrize("change, message", [
    (lambda m: None, "'metadata' is missing"),
    (lambda m: "{not json", "not valid JSON"),
    (lambda m: {k: v for k, v in m.items() if k != "sensor"}, "'sensor' is missing"),
    (lambda m: {**m, "sensor": ["LIDAR"]}, "'sensor'"),
    (lambda m: {**m, "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_HUGE"}, "'neural_network'"),
    (lambda m: {k: v for k, v in m.items() if k != "image"}, "'image'"),
    (lambda m: {**m, "image": {"height": 120, "width": 160, "channels": 2}}, "'image'"),
    (lambda m: {k: v for k, v in m.items() if k != "action_space"}, "'action_space' is missing"),
    (lambda m: {**m, "action_space": [{"steering_angle": 45, "speed": 1.0}] * 10}, "steering_angle 45"),
    (lambda m: {**m, "action_space_type": "hybrid"}, "action_space_type"),
])
def test_wrong_metadata(tmp_path, change, message):
    torch.manual_seed(0)
    state = build_net(SMALL, (120, 160, 1), SPACE).state_dict()
    metadata = change(_good_metadata())
    path = tmp_path / "meta.pt"
    if metadata is None:
        torch.save({"format": "multirace-agent", "format_version": 1, "state_dict": state}, path)
    else:
        _payload(path, metadata, state)
    with pytest.raises(AgentFileError, match=message) as err:
        load_agent(path)
    assert str(path) in str(err.value)


def test_not_an_agent_dict(tmp_path):
    path = tmp_path / "weights_only.pt"
    torch.save(build_net().state_dict(), path)  # plain state dict: safe but not an agent file
    with pytest.raises(AgentFileError, match="'format'"):
        load_agent(path)


def test_wrong_output_shape(tmp_path):
    net7 = CameraNet(SMALL, (120, 160, 1), 7)
    path = _payload(tmp_path / "seven.pt", _good_metadata(), net7.state_dict())
    with pytest.raises(AgentFileError, match="output shape.*7.*needs 10"):
        load_agent(path)
    with pytest.raises(AgentFileError, match="outputs"):  # save_agent checks too
        save_agent(tmp_path / "x.pt", net7, _good_metadata())


def test_weights_not_matching_architecture(tmp_path):
    state = build_net(SMALL, (120, 160, 1), SPACE).state_dict()
    del state["fc.0.weight"]
    path = _payload(tmp_path / "missing_key.pt", _good_metadata(), state)
    with pytest.raises(AgentFileError, match="weights do not match.*fc.0.weight"):
        load_agent(path)
    shallow = CameraNet(SHALLOW, (120, 160, 1), 10).state_dict()
    path = _payload(tmp_path / "other_net.pt", _good_metadata(), shallow)
    with pytest.raises(AgentFileError, match="weights do not match"):
        load_agent(path)


def test_nan_weights_fail_smoke_inference(tmp_path):
    net = build_net(SMALL, (120, 160, 1), SPACE)
    with torch.no_grad():
        net.head.bias.fill_(float("nan"))
    path = _payload(tmp_path / "nan.pt", _good_metadata(), net.state_dict())
    with pytest.raises(AgentFileError, match="non-finite"):
        load_agent(path)


def test_tiny_budget_fails_smoke_inference(good):
    with pytest.raises(AgentFileError, match="step budget"):
        load_agent(good, step_budget=1e-9)


def _nan_on_real_images(path):
    """A net that is finite on the blank smoke-test image but overflows to NaN on camera images."""
    torch.manual_seed(0)
    net = build_net(SMALL, (120, 160, 1), SPACE)
    overflow_on_camera_images(net)
    return save_agent(path, net, _good_metadata())


def test_bad_agents_forfeit_in_a_real_race(tmp_path, good):
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:1000])
    wrong_meta = _payload(tmp_path / "wrong_meta.pt", {**_good_metadata(), "name": "wrongmeta",
                                                       "neural_network": "NOPE"},
                          build_net().state_dict())
    small_images = save_agent(tmp_path / "small_images.pt", CameraNet(SMALL, (96, 128, 1), 10),
                              make_metadata(SPACE, SMALL, "small_images", (96, 128, 1)))
    nan = _nan_on_real_images(tmp_path / "nan_runtime.pt")
    slow = make_controller(str(good))
    slow.name = "slow"
    slow.step_budget = 1e-7  # every real inference is over this budget
    controllers = [make_controller(str(good)), make_controller(str(truncated)), make_controller(str(wrong_meta)),
                   make_controller(str(small_images)), make_controller(str(nan)), slow,
                   make_controller("bot:follow@1.0")]
    assert controllers[0].agent is not None and controllers[4].agent is not None  # NaN only on real images
    result = run_race(controllers, RaceConfig(track="reinvent_base", race="head_to_head", laps=1, max_steps=40))
    cars = {car["name"]: car for car in result["cars"]}
    assert len(result["cars"]) == 7
    expected = {
        "truncated": "truncated",
        "wrongmeta": "neural_network",
        "small_images": "observation",
        "meta": "non-finite",
        "slow": "budget",
    }
    for name, reason in expected.items():
        assert cars[name]["status"] == "forfeit", (name, cars[name])
        assert reason in cars[name]["reason"], (name, cars[name]["reason"])
    assert cars["tester"]["status"] == "not_finished"
    assert cars["bot:follow@1.0"]["status"] == "not_finished"
    assert cars["tester"]["file_sha256"] == cars["slow"]["file_sha256"] and len(cars["tester"]["file_sha256"]) == 64
    assert all(car["position"] >= 3 for car in result["cars"] if car["status"] == "forfeit")


def test_a_slow_garbage_collection_is_not_the_agents_inference_time(good):
    """A collection of the process's heap (long in a league worker or a test run) that an allocation inside
    the inference would set off is held until after the timed call, so it forfeits nobody."""
    controller = AgentController(good)
    infer = controller.agent.outputs
    inside = [False]

    def allocating_inference(obs):  # the agent's own inference, plus enough new lists to reach gc's threshold
        inside[0] = True
        try:
            [[] for _ in range(5 * gc.get_threshold()[0])]  # (their allocation sets the collector off)
            return infer(obs)
        finally:
            inside[0] = False

    def slow_collection(phase, info):
        if phase == "start" and inside[0]:
            end = time.thread_time() + 0.2  # CPU time of this thread, as the budget counts
            while time.thread_time() < end:
                pass

    controller.agent.outputs = allocating_inference
    gc.callbacks.append(slow_collection)
    try:
        commands = [controller.drive(None, 0, {"camera": np.zeros((120, 160, 1), np.uint8)}) for _ in range(6)]
    finally:
        gc.callbacks.remove(slow_collection)
    assert len(commands) == 6 and all(np.isfinite(commands).ravel())
    assert max(controller.step_times) < controller.step_budget


def test_cli_agent_inspect(tmp_path, good, capsys):
    assert cli_main(["agent", "inspect", str(good)]) == 0
    out = capsys.readouterr().out
    assert "MULTIRACE_SMALL_CNN" in out and "sha256" in out
    assert cli_main(["agent", "inspect", "--json", str(good)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["valid"] and info["metadata"]["name"] == "tester"
    bad = tmp_path / "bad.pt"
    bad.write_bytes(good.read_bytes()[:500])
    assert cli_main(["agent", "inspect", str(bad)]) == 1
    assert "truncated" in capsys.readouterr().out


@pytest.mark.skipif(not SHIPPED, reason="no shipped agents yet")
@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_shipped_agent_laps_reinvent_base(path):
    controller = make_controller(str(path))
    assert controller.agent is not None, controller.error
    assert path.stat().st_size <= 5_000_000
    result = run_race([controller], RaceConfig(track="reinvent_base", race="time_trial", laps=1))
    car = result["cars"][0]
    assert car["status"] == "finished", car
    assert car["laps"] == 1 and car["resets"] <= 3, car


def test_load_agent_gives_a_policy_that_drives_from_one_observation(tmp_path):
    policy = multirace.load_agent("dagger_fast")  # a shipped agent, by name
    env = multirace.parallel_env(num_cars=1, sensor=policy.sensor)
    observations, _ = env.reset(seed=0)
    steer, speed = policy.command(observations["car_0"])
    assert -30.0 <= steer <= 30.0 and 0.1 <= speed <= 4.0
    assert (steer, speed) in [tuple(a) for a in AgentController(policy.agent.path).agent.action_space.actions]
    with pytest.raises(ValueError, match="reads"):
        policy.command(np.zeros((60, 80, 1), np.uint8))
    lidar = multirace.load_agent(seeded_lidar_agent(tmp_path / "lidar.pt"))
    env = multirace.parallel_env(num_cars=1, sensor=lidar.sensor)
    observations, _ = env.reset(seed=0)
    assert -30.0 <= lidar.command(observations["car_0"])[0] <= 30.0


GRAPH_SPEC = {"inputs": {"FRONT_FACING_CAMERA": {"shape": [120, 160, 1], "layers": [
    {"type": "scale", "scale": 1 / 255, "shift": 0.0}, {"type": "pool", "k": 8}, {"type": "flatten"},
    {"type": "dense", "in": 300, "out": 10}]}}, "layers": [], "output": "softmax"}


@pytest.mark.parametrize("change, message", [
    (lambda m: m, None),
    (lambda m: {**m, "deepracer_graph": {"inputs": {}}}, "'deepracer_graph' is not a network spec"),
    (lambda m: {**m, "deepracer_graph": {**GRAPH_SPEC, "layers": [{"type": "dense", "in": 10, "out": 10**8}]}},
     "over the limit"),
    (lambda m: {**m, "image": {"height": 60, "width": 80, "channels": 1}}, "'deepracer_graph' reads"),
    (lambda m: {**m, "sensor": ["FRONT_FACING_CAMERA", "LIDAR"]}, "'deepracer_graph' has inputs"),
])
def test_imported_deepracer_layers_load_or_name_the_field(tmp_path, change, message):
    """An agent file holding DeepRacer's own layers (metadata field 'deepracer_graph', as `agent import` writes
    for 5-layer, deep and SAC networks) loads as a GraphNet; a spec that does not fit is refused by field,
    a huge one before anything is allocated."""
    torch.manual_seed(0)
    net = GraphNet(GRAPH_SPEC, SPACE)
    metadata = {**make_metadata(SPACE, "DEEP_CONVOLUTIONAL_NETWORK", "imported"), "deepracer_graph": GRAPH_SPEC}
    path = _payload(tmp_path / "graph.pt", change(metadata), net.state_dict())
    if message is None:
        agent = load_agent(path)
        assert isinstance(agent.net, GraphNet)
        assert agent.decide(agent.outputs(np.zeros((120, 160, 1), np.uint8))) in range(10)
        return
    with pytest.raises(AgentFileError, match=message) as err:
        load_agent(path)
    assert str(path) in str(err.value)


def test_no_build_machine_folders_reach_inspect_or_a_written_file(tmp_path):
    command = "multirace imitate --action-space /home/me/work/agents/space.json --init C:\\runs\\a.pt --out x.pt"
    path = _save(tmp_path / "a.pt", training={"command": command, "init": {"file": "/srv/runs/b.pt"},
                                              "expert": "teacher:/srv/runs/t.teacher.pt@0.95"})
    stored = json.loads(torch.load(path, weights_only=True)["metadata"])  # written without the folders
    assert stored["training"] == {"command": "multirace imitate --action-space space.json --init a.pt --out x.pt",
                                  "init": {"file": "b.pt"}, "expert": "teacher:t.teacher.pt@0.95"}
    for shipped in SHIPPED:  # the shipped files were written on a build machine: what users see has no folder
        shown = json.dumps(inspect_agent(shipped)["metadata"])
        assert "/work/" not in shown and "/home/" not in shown, shipped.name
    racer = inspect_agent(REPO / "agents" / "racer.pt")["metadata"]["training"]["command"]
    assert "--action-space action_space_racer.json" in racer
