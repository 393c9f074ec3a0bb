"""Agents to the DeepRacer car and back: the archive, real OpenVINO on the frozen graph, import round trips."""
from __future__ import annotations

import json
import tarfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

import multirace
from multirace.cli import main as cli_main
from multirace.deepracer.export import OUTPUT, export_agent, input_name
from multirace.deepracer.importer import ModelImportError, import_model
from multirace.deepracer.tfgraph import DT_FLOAT, DT_INT32, GraphBuilder
from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import load_agent, make_metadata, save_agent
from multirace.racing.nets import SHALLOW, TINY, build_net

ov = pytest.importorskip("openvino")
FIXTURES = Path("/work/shared/deepracer-model")
needs_fixtures = pytest.mark.skipif(not FIXTURES.exists(), reason="the DeepRacer model fixtures are not here")
CONTINUOUS = {"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 1.0, "high": 3.0}},
              "action_space_type": "continuous"}


@pytest.fixture(scope="module")
def frames():
    """Camera frames (and LIDAR scans) rendered by the real env while a car drives the track."""
    env = multirace.parallel_env(num_cars=1, sensor=["FRONT_FACING_CAMERA", "LIDAR"])
    observations, _ = env.reset(seed=4)
    shots = []
    for step in range(24):
        observations, *_ = env.step({"car_0": 6 if step % 3 else 3})
        if step % 4 == 0 and observations:
            shots.append(observations["car_0"])
    env.close()
    return shots


def openvino_policy(pb: Path, inputs: dict):
    """The .pb converted by OpenVINO with the car's input names and shapes and its policy output, run in f32."""
    model = ov.convert_model(str(pb), input=[(name + ":0", shape) for name, shape in inputs.items()],
                             output=OUTPUT + ":0")
    return model, ov.Core().compile_model(model, "CPU", {"INFERENCE_PRECISION_HINT": "f32"})


def unpack(archive: Path, folder: Path) -> Path:
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    return folder


def test_archive_is_what_the_car_loads(tmp_path):
    out = export_agent("dagger_fast", tmp_path / "dagger fast.tar.gz")
    with tarfile.open(out) as tar:
        names = sorted(m.name for m in tar.getmembers() if m.isfile())
    assert names == ["agent/model.pb", "model_metadata.json"]  # exactly one .pb; the metadata at the root
    metadata = json.loads((unpack(out, tmp_path / "x") / "model_metadata.json").read_text())
    assert metadata["sensor"] == ["FRONT_FACING_CAMERA"] and metadata["training_algorithm"] == "clipped_ppo"
    assert metadata["action_space_type"] == "discrete"
    agent = load_agent(multirace.racing.runner.resolve_agent_path("dagger_fast"), step_budget=None)
    assert [(a["steering_angle"], a["speed"]) for a in metadata["action_space"]] == agent.action_space.actions
    with pytest.raises(ValueError, match="tar.gz"):
        export_agent("dagger_fast", tmp_path / "model.zip")


@pytest.mark.parametrize("agent", ["dagger_fast", "selfplay_lidar"])
def test_openvino_runs_the_graph_like_the_torch_policy(tmp_path, frames, agent):
    policy = multirace.load_agent(agent)
    folder = unpack(export_agent(agent, tmp_path / "model.tar.gz"), tmp_path / "car")
    inputs = {input_name("FRONT_FACING_CAMERA"): [1, 120, 160, 1]}
    if policy.agent.lidar_samples:
        inputs[input_name("LIDAR")] = [1, policy.agent.lidar_samples]
    model, compiled = openvino_policy(folder / "agent" / "model.pb", inputs)
    assert len(model.outputs) == 1 and model.outputs[0].get_any_name() == OUTPUT + ":0"
    # with no hints, OpenVINO finds the same inputs and the policy as the graph's only output (the car's way)
    plain = ov.convert_model(str(folder / "agent" / "model.pb"))
    assert [o.get_any_name() for o in plain.outputs] == [OUTPUT + ":0"]
    assert sorted(i.get_any_name() for i in plain.inputs) == sorted(n + ":0" for n in inputs)
    for obs in frames:
        image = obs["camera"]
        feed = {input_name("FRONT_FACING_CAMERA") + ":0": image[None].astype(np.float32)}  # raw 0-255 pixels
        torch_obs = image
        if policy.agent.lidar_samples:
            feed[input_name("LIDAR") + ":0"] = obs["lidar"][None].astype(np.float32)
            torch_obs = obs
        car = compiled(feed)[0][0]
        expected = torch.softmax(torch.from_numpy(policy.agent.outputs(torch_obs)[0]), 0).numpy()
        np.testing.assert_allclose(car, expected, atol=1e-5)
        assert policy.agent.action_space.actions[int(np.argmax(car))] == policy.command(obs if
                                                                                       policy.agent.lidar_samples
                                                                                       else image)


def test_continuous_shallow_head_gives_the_cars_minus_one_to_one(tmp_path, frames):
    space = load_action_space(CONTINUOUS)
    torch.manual_seed(1)
    net = build_net(SHALLOW, (120, 160, 1), CONTINUOUS)
    path = save_agent(tmp_path / "cont.pt", net, make_metadata(space, SHALLOW, "cont"))
    folder = unpack(export_agent(path, tmp_path / "cont.tar.gz"), tmp_path / "car")
    metadata = json.loads((folder / "model_metadata.json").read_text())
    assert metadata["action_space"] == {"steering_angle": {"low": -30.0, "high": 30.0},
                                        "speed": {"low": 1.0, "high": 3.0}}
    _, compiled = openvino_policy(folder / "agent" / "model.pb", {input_name("FRONT_FACING_CAMERA"): [1, 120, 160, 1]})
    agent = load_agent(path, step_budget=None)
    for obs in frames[:3]:
        v = compiled(obs["camera"][None].astype(np.float32))[0][0]
        mean = agent.outputs(obs["camera"])[0][:2]
        # the car maps v linearly onto low..high: steering 30 v, speed 2 + v
        np.testing.assert_allclose([30 * v[0], 2 + v[1]], mean, atol=1e-4)


@needs_fixtures
def test_shallow_export_converts_like_the_cars_real_model(tmp_path):
    """Our shallow graph, converted by OpenVINO, has the layer chain of the IR the car made from a real model."""
    space = load_action_space(FIXTURES / "Sample_single_cam" / "model_metadata.json")
    net = build_net(SHALLOW, (120, 160, 1), space)
    path = save_agent(tmp_path / "shallow.pt", net, make_metadata(space, SHALLOW, "shallow"))
    folder = unpack(export_agent(path, tmp_path / "s.tar.gz"), tmp_path / "car")
    model, _ = openvino_policy(folder / "agent" / "model.pb", {input_name("FRONT_FACING_CAMERA"): [1, 120, 160, 1]})
    ours = [op.get_type_name().lower() for op in model.get_ordered_ops()]
    layers = ET.parse(FIXTURES / "Sample_single_cam" / "model.xml").getroot().find("layers")
    real = [layer.get("type").lower() for layer in layers]  # (OpenVINO 2021's SoftMax is today's Softmax)
    for kind in ("convolution", "matmul", "softmax", "parameter", "result"):
        assert ours.count(kind) == real.count(kind), kind
    names = {layer.get("name") for layer in layers}
    assert "main_level/agent/main/online/network_1/ppo_head_0/policy" in names  # the car's output name is ours


@pytest.mark.parametrize("agent", ["dagger_fast", "selfplay_lidar"])
def test_import_round_trips_an_exported_archive(tmp_path, frames, agent):
    archive = export_agent(agent, tmp_path / "model.tar.gz")
    assert cli_main(["agent", "import", str(archive), "--out", str(tmp_path / "back.pt")]) == 0
    before, after = multirace.load_agent(agent), multirace.load_agent(tmp_path / "back.pt")
    for obs in frames:
        observation = obs if before.agent.lidar_samples else obs["camera"]
        assert after.command(observation) == before.command(observation)
    assert after.metadata["training"]["imported_from"] == "model.tar.gz"


def test_import_round_trips_a_continuous_tiny_net(tmp_path, frames):
    space = load_action_space(CONTINUOUS)
    torch.manual_seed(2)
    net = build_net(TINY, (120, 160, 1), CONTINUOUS)
    path = save_agent(tmp_path / "tiny.pt", net, make_metadata(space, TINY, "tiny"))
    assert cli_main(["agent", "export", str(path), "--out", str(tmp_path / "tiny.tar.gz")]) == 0
    unpack(tmp_path / "tiny.tar.gz", tmp_path / "car")
    import_model(tmp_path / "car" / "agent" / "model.pb", tmp_path / "back.pt")  # a .pb with the metadata above it
    before, after = multirace.load_agent(path), multirace.load_agent(tmp_path / "back.pt")
    for obs in frames:
        np.testing.assert_allclose(after.command(obs["camera"]), before.command(obs["camera"]), atol=1e-4)


def deepracer_shallow_graph(weights, actions: int) -> bytes:
    """A frozen graph as DeepRacer's simapp writes a shallow PPO model (the `observation` input of
    Sample_single_cam, network_0's placeholder, the gradient rescaler between middleware and head)."""
    g = GraphBuilder()
    root = "main_level/agent/main/online"
    placeholder = f"{root}/network_0/observation/observation"
    g.node(placeholder, "Placeholder", dtype=("type", DT_FLOAT), shape=("shape", [-1, 120, 160, 1]))
    scope = f"{root}/network_1/observation"
    x = g.op(f"{scope}/truediv", "RealDiv", [placeholder, g.const(f"{scope}/truediv/y", np.float32(255))])
    x = g.op(f"{scope}/sub", "Sub", [x, g.const(f"{scope}/sub/y", np.float32(0))])
    for k, (kernel, bias, stride) in enumerate(weights["convs"]):
        x = g.op(f"{scope}/Conv2d_{2 * k}/Conv2D", "Conv2D", [x, g.const(f"{scope}/Conv2d_{2 * k}/kernel", kernel)],
                 strides=("ints", [1, stride, stride, 1]), padding="VALID", data_format="NHWC")
        x = g.op(f"{scope}/Conv2d_{2 * k}/BiasAdd", "BiasAdd", [x, g.const(f"{scope}/Conv2d_{2 * k}/bias", bias)])
        x = g.op(f"{scope}/BatchnormActivationDropout_{2 * k + 1}_activation", "Relu", [x])
    shape = g.const(f"{scope}/Flatten/flatten/Reshape/shape", np.array([-1, 11264], np.int32))
    x = g.node(f"{scope}/Flatten/flatten/Reshape", "Reshape", [x, shape], T=("type", DT_FLOAT),
               Tshape=("type", DT_INT32))
    mid = f"{root}/network_1/middleware_fc_embedder"
    x = g.op(f"{mid}/Dense_0/MatMul", "MatMul", [x, g.const(f"{mid}/Dense_0/kernel", weights["dense"][0])])
    x = g.op(f"{mid}/Dense_0/BiasAdd", "BiasAdd", [x, g.const(f"{mid}/Dense_0/bias", weights["dense"][1])])
    x = g.op(f"{mid}/BatchnormActivationDropout_1_activation", "Relu", [x])
    r = g.const(f"{root}/network_1/gradients_from_head_0-0_rescalers", np.ones(1, np.float32))
    r = g.node(f"{root}/network_1/strided_slice", "StridedSlice",
               [r, *(g.const(f"{root}/network_1/strided_slice/{n}", np.array([v], np.int32))
                     for n, v in (("begin", 0), ("end", 1), ("strides", 1)))],
               T=("type", DT_FLOAT), Index=("type", DT_INT32), shrink_axis_mask=1)
    one_minus = g.op(f"{root}/network_1/sub", "Sub", [g.const(f"{root}/network_1/sub/x", np.float32(1)), r])
    stopped = g.op(f"{root}/network_1/StopGradient", "StopGradient", [x])
    a = g.op(f"{root}/network_1/mul", "Mul", [one_minus, stopped])
    b = g.op(f"{root}/network_1/mul_1", "Mul", [r, x])
    x = g.op(f"{root}/network_1/add", "AddV2", [a, b])
    head = f"{root}/network_1/ppo_head_0/policy_fc"
    x = g.op(f"{head}/MatMul", "MatMul", [x, g.const(f"{head}/kernel", weights["head"][0])])
    x = g.op(f"{head}/BiasAdd", "BiasAdd", [x, g.const(f"{head}/bias", weights["head"][1])])
    g.op(OUTPUT, "Softmax", [x])
    return g.to_bytes()


@needs_fixtures
def test_import_a_deepracer_shallow_model(tmp_path, frames):
    """A model laid out as DeepRacer writes it (names, input `observation`, rescaler) imports; the torch net
    chooses as OpenVINO running the .pb chooses."""
    rng = np.random.default_rng(0)

    def rand(*shape, scale):
        return (rng.standard_normal(shape) * scale).astype(np.float32)

    weights = {"convs": [(rand(8, 8, 1, 32, scale=0.05), rand(32, scale=0.01), 4),
                         (rand(4, 4, 32, 64, scale=0.05), rand(64, scale=0.01), 2),
                         (rand(3, 3, 64, 64, scale=0.05), rand(64, scale=0.01), 1)],
               "dense": (rand(11264, 512, scale=0.02), rand(512, scale=0.01)),
               "head": (rand(512, 15, scale=0.1), rand(15, scale=0.01))}
    model = tmp_path / "model"
    (model / "agent").mkdir(parents=True)
    (model / "agent" / "model.pb").write_bytes(deepracer_shallow_graph(weights, 15))
    (model / "model_metadata.json").write_bytes((FIXTURES / "Sample_single_cam" / "model_metadata.json").read_bytes())
    import_model(model, tmp_path / "imported.pt")
    policy = multirace.load_agent(tmp_path / "imported.pt")
    assert policy.agent.net.network == SHALLOW and policy.sensor == ["FRONT_FACING_CAMERA"]
    placeholder = "main_level/agent/main/online/network_0/observation/observation"
    _, compiled = openvino_policy(model / "agent" / "model.pb", {placeholder: [1, 120, 160, 1]})
    for obs in frames:
        car = compiled(obs["camera"][None].astype(np.float32))[0][0]
        mine = torch.softmax(torch.from_numpy(policy.agent.outputs(obs["camera"])[0]), 0).numpy()
        np.testing.assert_allclose(mine, car, atol=1e-5)
        assert policy.command(obs["camera"]) == policy.agent.action_space.actions[int(np.argmax(car))]


def test_import_names_what_it_cannot_read(tmp_path):
    (tmp_path / "model_metadata.json").write_text(json.dumps({"action_space": CONTINUOUS["action_space"]}))
    (tmp_path / "model.pb").write_bytes(b"\x00not a graph")
    with pytest.raises(ModelImportError, match="model.pb"):
        import_model(tmp_path / "model.pb", tmp_path / "x.pt")
    with tarfile.open(tmp_path / "two.tar.gz", "w:gz") as tar:
        tar.add(tmp_path / "model.pb", "a/model.pb")
        tar.add(tmp_path / "model.pb", "b/model.pb")
    with pytest.raises(ModelImportError, match="2 .pb files"):
        import_model(tmp_path / "two.tar.gz", tmp_path / "x.pt")
