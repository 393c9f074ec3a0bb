"""Agents to the DeepRacer car and back: the archive, real OpenVINO on the frozen graph, import round trips."""
from __future__ import annotations

import json
import sqlite3
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
from multirace.racing.graphnet import GraphNet
from multirace.racing.nets import SHALLOW, TINY, CameraNet, build_net

from helpers import car_input, seeded_lidar_agent

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


@pytest.mark.parametrize("agent", ["dagger_fast", "lidar"])
def test_openvino_runs_the_graph_like_the_torch_policy(tmp_path, frames, agent):
    if agent == "lidar":  # a camera + LIDAR agent
        agent = str(seeded_lidar_agent(tmp_path / "lidar.pt"))
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
        feed = {input_name("FRONT_FACING_CAMERA") + ":0": car_input(image)}  # raw 0-255 pixels
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


@pytest.mark.slow
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
        v = compiled(car_input(obs["camera"]))[0][0]
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


@pytest.mark.parametrize("agent", ["dagger_fast", "lidar"])
def test_import_round_trips_an_exported_archive(tmp_path, frames, agent):
    if agent == "lidar":
        agent = str(seeded_lidar_agent(tmp_path / "lidar.pt"))
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


SHALLOW_CONVS = [(8, 32, 4), (4, 64, 2), (3, 64, 1)]  # (kernel, filters, stride)
FIVE_LAYER_CONVS = [(5, 32, 2), (3, 32, 1), (3, 64, 2), (3, 64, 1)]
DEEP_CONVS = [(8, 32, 4), (4, 32, 2), (4, 64, 2), (3, 64, 1)]


def deepracer_graph(rng, *, convs, outputs, embedder_dense=(), middleware=(512,), head_hidden=(),
                    algorithm="clipped_ppo", discrete=True, camera="observation", channels=1, lidar=0) -> bytes:
    """A frozen policy graph laid out as DeepRacer's simapp writes one, with random weights: its names,
    the placeholder in network_0 (PPO) or the policy network (SAC), /255 in the graph, interleaved
    activation names, embeddings concatenated in sorted sensor order, the gradient rescaler between
    middleware and head, and the `policy` output."""
    g = GraphBuilder()
    sac = algorithm == "sac"
    root = f"main_level/agent/{'policy' if sac else 'main'}/online"
    net = f"{root}/network_0" if sac else f"{root}/network_1"

    def dense(scope, x, n_in, n_out, relu_name=None):
        x = g.op(f"{scope}/MatMul", "MatMul", [x, g.const(f"{scope}/kernel", rand(n_in, n_out, fan=n_in))])
        x = g.op(f"{scope}/BiasAdd", "BiasAdd", [x, g.const(f"{scope}/bias", rand(n_out, fan=100))])
        return g.op(relu_name, "Relu", [x]) if relu_name else x

    def rand(*shape, fan):
        return (rng.standard_normal(shape) / np.sqrt(fan)).astype(np.float32)

    embeddings = {}
    placeholder = f"{root}/network_0/{camera}/{camera}"
    g.node(placeholder, "Placeholder", dtype=("type", DT_FLOAT), shape=("shape", [-1, 120, 160, channels]))
    scope = f"{net}/{camera}"
    x = g.op(f"{scope}/truediv", "RealDiv", [placeholder, g.const(f"{scope}/truediv/y", np.float32(255))])
    x = g.op(f"{scope}/sub", "Sub", [x, g.const(f"{scope}/sub/y", np.float32(0))])
    size, depth = np.array([120, 160]), channels
    for k, (kernel, filters, stride) in enumerate(convs):
        name = f"{scope}/Conv2d_{2 * k}"
        x = g.op(f"{name}/Conv2D", "Conv2D", [x, g.const(f"{name}/kernel", rand(kernel, kernel, depth, filters,
                                                                                     fan=kernel * kernel * depth))],
                 strides=("ints", [1, stride, stride, 1]), padding="VALID", data_format="NHWC")
        x = g.op(f"{name}/BiasAdd", "BiasAdd", [x, g.const(f"{name}/bias", rand(filters, fan=100))])
        x = g.op(f"{scope}/BatchnormActivationDropout_{2 * k + 1}_activation", "Relu", [x])
        size, depth = (size - kernel) // stride + 1, filters
    width = int(size.prod() * depth)
    x = g.node(f"{scope}/Flatten/flatten/Reshape", "Reshape",
               [x, g.const(f"{scope}/Flatten/flatten/Reshape/shape", np.array([-1, width], np.int32))],
               T=("type", DT_FLOAT), Tshape=("type", DT_INT32))
    for k, n in enumerate(embedder_dense):
        x = dense(f"{scope}/Dense_{2 * len(convs) + 2 * k}", x, width, n,
                  f"{scope}/BatchnormActivationDropout_{2 * len(convs) + 2 * k + 1}_activation")
        width = n
    embeddings[camera] = (x, width)
    if lidar:
        lidar_in = f"{root}/network_0/LIDAR/LIDAR"
        g.node(lidar_in, "Placeholder", dtype=("type", DT_FLOAT), shape=("shape", [-1, lidar]))
        y = dense(f"{net}/LIDAR/Dense_0", lidar_in, lidar, 256, f"{net}/LIDAR/BatchnormActivationDropout_1_activation")
        y = dense(f"{net}/LIDAR/Dense_2", y, 256, 256, f"{net}/LIDAR/BatchnormActivationDropout_3_activation")
        embeddings["LIDAR"] = (y, 256)
    if len(embeddings) > 1:
        parts = [embeddings[name] for name in sorted(embeddings)]
        x = g.node(f"{net}/concat", "ConcatV2", [p for p, _ in parts] + [g.const(f"{net}/concat/axis", np.int32(1))],
                   N=len(parts), T=("type", DT_FLOAT), Tidx=("type", DT_INT32))
        width = sum(w for _, w in parts)
    for k, n in enumerate(middleware):
        x = dense(f"{net}/middleware_fc_embedder/Dense_{2 * k}", x, width, n,
                  f"{net}/middleware_fc_embedder/BatchnormActivationDropout_{2 * k + 1}_activation")
        width = n
    # the gradient rescaler as in the real checkpoint graph (11_Step-38428.ckpt.meta): x packed into a new
    # axis, (1 - r) * stop_gradient(x) + r * x, then the head's strided_slice takes [0]
    r = g.const(f"{net}/gradients_from_head_0-0_rescalers", np.ones(1, np.float32))
    one_minus = g.op(f"{net}/sub", "Sub", [g.const(f"{net}/sub/x", np.float32(1)), r])
    packed = [g.node(f"{net}/{name}", "Pack", [x], N=1, axis=0, T=("type", DT_FLOAT))
              for name in ("StopGradient/input", "mul_1/y")]
    a = g.op(f"{net}/mul", "Mul", [one_minus, g.op(f"{net}/StopGradient", "StopGradient", [packed[0]])])
    x = g.op(f"{net}/add", "Add", [a, g.op(f"{net}/mul_1", "Mul", [r, packed[1]])])
    head = f"{net}/{'sac_policy_head_0' if sac else 'ppo_head_0'}"
    x = g.node(f"{head}/strided_slice", "StridedSlice",
               [x, *(g.const(f"{head}/strided_slice/{n}", np.array([v], np.int32))
                     for n, v in (("stack", 0), ("stack_1", 1), ("stack_2", 1)))],
               T=("type", DT_FLOAT), Index=("type", DT_INT32), shrink_axis_mask=1)
    for k, n in enumerate(head_hidden):
        x = dense(f"{head}/dense_{k}", x, width, n, f"{head}/dense_{k}/Relu")
        width = n
    if discrete:
        g.op(f"{head}/policy", "Softmax", [dense(f"{head}/policy_fc", x, width, outputs)])
    else:
        g.op(f"{head}/policy", "Identity", [dense(f"{head}/policy_mean", x, width, 2)])
    return g.to_bytes()


def import_and_compare(tmp_path, frames, graph: bytes, metadata: dict, feeds, expect):
    """Import the graph (a folder with agent/model.pb), then compare the policy with OpenVINO running the .pb:
    `expect(openvino_output)` gives what the torch outputs should be."""
    model = tmp_path / "model"
    (model / "agent").mkdir(parents=True)
    (model / "agent" / "model.pb").write_bytes(graph)
    (model / "model_metadata.json").write_text(json.dumps(metadata))
    assert cli_main(["agent", "import", str(model), "--out", str(tmp_path / "imported.pt")]) == 0
    policy = multirace.load_agent(tmp_path / "imported.pt")
    compiled = ov.Core().compile_model(ov.convert_model(str(model / "agent" / "model.pb")), "CPU",
                                       {"INFERENCE_PRECISION_HINT": "f32"})
    for obs in frames:
        feed, observation = feeds(obs)
        car = compiled(feed)[0][0]
        mine = policy.agent.outputs(observation)[0]
        np.testing.assert_allclose(expect(car, mine), mine[:len(expect(car, mine))], atol=1e-4)
        policy.command(observation)
    return policy


def camera_feed(obs):
    return {"main_level/agent/main/online/network_0/observation/observation:0":
            car_input(obs["camera"])}, obs["camera"]


def softmax_of(car, mine):
    return np.log(car) - np.log(car)[0] + mine[0]  # the logits up to a constant, anchored on the first


@needs_fixtures
def test_import_a_deepracer_shallow_model(tmp_path, frames):
    """A shallow PPO model laid out as DeepRacer writes it (Sample_single_cam's metadata: no `sensor`, input
    `observation`, 15 actions) imports as multirace's shallow CameraNet that chooses as OpenVINO does."""
    metadata = json.loads((FIXTURES / "Sample_single_cam" / "model_metadata.json").read_text())
    graph = deepracer_graph(np.random.default_rng(0), convs=SHALLOW_CONVS, outputs=15)
    policy = import_and_compare(tmp_path, frames, graph, metadata, camera_feed, softmax_of)
    assert policy.agent.net.network == SHALLOW and policy.sensor == ["FRONT_FACING_CAMERA"]
    assert isinstance(policy.agent.net, CameraNet)  # so races and leagues load it too


@pytest.mark.slow
def test_import_a_deepracer_five_layer_discrete_model(tmp_path, frames):
    metadata = {"action_space": [{"steering_angle": s, "speed": 1.5} for s in (-30, -15, 0, 15, 30)],
                "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK"}
    graph = deepracer_graph(np.random.default_rng(1), convs=FIVE_LAYER_CONVS, embedder_dense=(64,), outputs=5,
                            camera="FRONT_FACING_CAMERA")

    def feed(obs):
        return {input_name("FRONT_FACING_CAMERA") + ":0": car_input(obs["camera"])}, obs["camera"]

    policy = import_and_compare(tmp_path, frames, graph, metadata, feed, softmax_of)
    assert isinstance(policy.agent.net, GraphNet) and policy.metadata["neural_network"] == "DEEP_CONVOLUTIONAL_NETWORK"


@pytest.mark.slow
def test_import_a_deepracer_deep_continuous_ppo_model(tmp_path, frames):
    metadata = {**CONTINUOUS, "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_DEEP"}
    graph = deepracer_graph(np.random.default_rng(2), convs=DEEP_CONVS, embedder_dense=(512, 512),
                            middleware=(256, 128), outputs=2, discrete=False, camera="FRONT_FACING_CAMERA")

    def feed(obs):
        return {input_name("FRONT_FACING_CAMERA") + ":0": car_input(obs["camera"])}, obs["camera"]

    # the car's linear map of [-1, 1] onto steering -30..30 and speed 1..3
    import_and_compare(tmp_path, frames, graph, metadata, feed, lambda car, mine: [30 * car[0], 2 + car[1]])


@pytest.mark.slow
def test_import_a_deepracer_sac_camera_lidar_model(tmp_path, frames):
    metadata = {**CONTINUOUS, "sensor": ["FRONT_FACING_CAMERA", "LIDAR"], "training_algorithm": "sac",
                "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"}
    graph = deepracer_graph(np.random.default_rng(3), convs=SHALLOW_CONVS, head_hidden=(256,), outputs=2,
                            discrete=False, algorithm="sac", camera="FRONT_FACING_CAMERA", lidar=64)
    root = "main_level/agent/policy/online/network_0"

    def feed(obs):
        return ({f"{root}/FRONT_FACING_CAMERA/FRONT_FACING_CAMERA:0": car_input(obs["camera"]),
                 f"{root}/LIDAR/LIDAR:0": obs["lidar"][None].astype(np.float32)}, obs)

    # SAC's policy output is the pre-tanh mean; DeepRacer's simulator squashes it with tanh
    policy = import_and_compare(tmp_path, frames, graph, metadata, feed,
                                lambda car, mine: [30 * np.tanh(car[0]), 2 + np.tanh(car[1])])
    assert policy.sensor == ["FRONT_FACING_CAMERA", "LIDAR"]


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


def test_a_graph_declaring_a_huge_constant_is_refused_unallocated(tmp_path):
    g = GraphBuilder()
    g.node("big", "Const", dtype=("type", DT_FLOAT), value=np.zeros(1, np.float32))
    graph = g.graph
    graph.node[0].attr["value"].tensor.tensor_shape.dim[0].size = 10**12  # declared, not stored
    g.op(OUTPUT, "Softmax", ["big"])
    (tmp_path / "model.pb").write_bytes(g.to_bytes())
    (tmp_path / "model_metadata.json").write_text(json.dumps({"action_space": CONTINUOUS["action_space"]}))
    with pytest.raises(ModelImportError, match="constant of shape"):
        import_model(tmp_path / "model.pb", tmp_path / "x.pt")


@pytest.mark.slow
@needs_fixtures
def test_import_a_training_checkpoint_folder(tmp_path, frames):
    """DeepRacer's model/ folder: the real checkpoint's .index and .meta (reInvent2019-TestModel), with a .data
    file of stand-in weights at the offsets the index gives; the imported net computes what the checkpoint's
    variables compute (a reference forward pass by the variables' names)."""
    from multirace.deepracer.checkpoint import Checkpoint, read_index

    source = FIXTURES / "reInvent2019-TestModel" / "model"
    model = tmp_path / "model"
    model.mkdir()
    for name in (".coach_checkpoint", "11_Step-38428.ckpt.index", "11_Step-38428.ckpt.meta", "model_metadata.json"):
        (model / name).write_bytes((source / name).read_bytes())
    index = read_index(model / "11_Step-38428.ckpt.index")
    rng = np.random.default_rng(5)
    data = bytearray(max(e["offset"] + e["size"] for e in index.values()))
    for entry in index.values():
        shape = entry["shape"]
        fan = int(np.prod(shape[:-1])) if len(shape) > 1 else 100
        values = (rng.standard_normal(int(np.prod(shape))) / np.sqrt(fan)).astype("<f4")
        data[entry["offset"]:entry["offset"] + entry["size"]] = values.tobytes()
    (model / "11_Step-38428.ckpt.data-00000-of-00001").write_bytes(bytes(data))
    assert cli_main(["agent", "import", str(tmp_path), "--out", str(tmp_path / "checkpoint.pt")]) == 0
    policy = multirace.load_agent(tmp_path / "checkpoint.pt")
    assert isinstance(policy.agent.net, CameraNet) and policy.agent.net.network == SHALLOW
    variables = Checkpoint(model / "11_Step-38428.ckpt")
    net1 = "main_level/agent/main/online/network_1"

    def reference(image):  # TF's NHWC graph, step by step, from the variables by name
        x = torch.from_numpy(car_input(image) / 255).permute(0, 3, 1, 2)
        for k, stride in ((0, 4), (2, 2), (4, 1)):
            scope = f"{net1}/FRONT_FACING_CAMERA/Conv2d_{k}"
            x = torch.relu(torch.nn.functional.conv2d(
                x, torch.from_numpy(variables[f"{scope}/kernel"]).permute(3, 2, 0, 1),
                torch.from_numpy(variables[f"{scope}/bias"]), stride=stride))
        x = x.permute(0, 2, 3, 1).flatten(1)
        for scope, relu in (("middleware_fc_embedder/Dense_0", True), ("ppo_head_0/policy_fc", False)):
            x = x @ torch.from_numpy(variables[f"{net1}/{scope}/kernel"]) + torch.from_numpy(
                variables[f"{net1}/{scope}/bias"])
            x = torch.relu(x) if relu else x
        return torch.softmax(x, 1)[0].numpy()

    for obs in frames:
        mine = torch.softmax(torch.from_numpy(policy.agent.outputs(obs["camera"])[0]), 0).numpy()
        np.testing.assert_allclose(mine, reference(obs["camera"]), atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["five_layer", "sac_lidar"])
def test_imported_deepracer_networks_go_back_to_the_car(tmp_path, frames, kind):
    """An imported 5-layer or SAC (camera+LIDAR) model exports to a car archive that OpenVINO runs as the
    imported policy does (SAC's tanh inside the graph), and imports back to the same commands."""
    if kind == "five_layer":
        metadata = {"action_space": [{"steering_angle": s, "speed": 1.5} for s in (-30, -15, 0, 15, 30)],
                    "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK"}
        graph = deepracer_graph(np.random.default_rng(1), convs=FIVE_LAYER_CONVS, embedder_dense=(64,), outputs=5,
                                camera="FRONT_FACING_CAMERA")
    else:
        metadata = {**CONTINUOUS, "sensor": ["FRONT_FACING_CAMERA", "LIDAR"], "training_algorithm": "sac"}
        graph = deepracer_graph(np.random.default_rng(3), convs=SHALLOW_CONVS, head_hidden=(256,), outputs=2,
                                discrete=False, algorithm="sac", camera="FRONT_FACING_CAMERA", lidar=64)
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "model.pb").write_bytes(graph)
    (tmp_path / "in" / "model_metadata.json").write_text(json.dumps(metadata))
    import_model(tmp_path / "in" / "model.pb", tmp_path / "imported.pt")
    policy = multirace.load_agent(tmp_path / "imported.pt")
    assert cli_main(["agent", "export", str(tmp_path / "imported.pt"), "--out", str(tmp_path / "car.tar.gz")]) == 0
    folder = unpack(tmp_path / "car.tar.gz", tmp_path / "car")
    car_metadata = json.loads((folder / "model_metadata.json").read_text())
    assert car_metadata["sensor"] == metadata["sensor"] and car_metadata["training_algorithm"] == "clipped_ppo"
    compiled = ov.Core().compile_model(ov.convert_model(str(folder / "agent" / "model.pb")), "CPU",
                                       {"INFERENCE_PRECISION_HINT": "f32"})
    import_model(tmp_path / "car.tar.gz", tmp_path / "back.pt")
    back = multirace.load_agent(tmp_path / "back.pt")
    for obs in frames:
        lidar = kind == "sac_lidar"
        feed = {input_name("FRONT_FACING_CAMERA") + ":0": car_input(obs["camera"])}
        if lidar:
            feed[input_name("LIDAR") + ":0"] = obs["lidar"][None].astype(np.float32)
        observation = obs if lidar else obs["camera"]
        car = compiled(feed)[0][0]
        mine = policy.agent.outputs(observation)[0]
        if lidar:  # the car maps [-1, 1] linearly: steering 30 v, speed 2 + v
            np.testing.assert_allclose([30 * car[0], 2 + car[1]], mine[:2], atol=1e-4)
        else:
            np.testing.assert_allclose(car, torch.softmax(torch.from_numpy(mine), 0).numpy(), atol=1e-5)
        np.testing.assert_allclose(back.command(observation), policy.command(observation), atol=1e-4)


LEAGUE_TOML = """
[league]
name = "imported"
seeds = [1]
bots = ["bot:follow@1.0"]
step_budget = 0.5
match_timeout = 120
replays = false

[[tracks]]
name = "reinvent_base"

[time_trial]
format = "reset_rule"
laps = 1
max_steps = 60

[head_to_head]
cars = 2
laps = 1
max_steps = 60
"""


def test_imported_deepracer_networks_race_and_league(tmp_path):
    """A 5-layer discrete model and a SAC camera+LIDAR model, imported as DeepRacer layers (not multirace
    networks), race against each other and a bot without forfeiting, and play their league matches."""
    five = {"action_space": [{"steering_angle": s, "speed": 1.5} for s in (-30, -15, 0, 15, 30)],
            "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK"}
    sac = {**CONTINUOUS, "sensor": ["FRONT_FACING_CAMERA", "LIDAR"], "training_algorithm": "sac"}
    graphs = {"five": (five, deepracer_graph(np.random.default_rng(1), convs=FIVE_LAYER_CONVS, embedder_dense=(64,),
                                             outputs=5, camera="FRONT_FACING_CAMERA")),
              "sac": (sac, deepracer_graph(np.random.default_rng(3), convs=SHALLOW_CONVS, head_hidden=(256,), outputs=2,
                                           discrete=False, algorithm="sac", camera="FRONT_FACING_CAMERA", lidar=64))}
    for name, (metadata, graph) in graphs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "model.pb").write_bytes(graph)
        (tmp_path / name / "model_metadata.json").write_text(json.dumps(metadata))
        import_model(tmp_path / name / "model.pb", tmp_path / f"{name}.pt")
        assert isinstance(load_agent(tmp_path / f"{name}.pt").net, GraphNet)  # the race loader builds it

    result = tmp_path / "race.json"
    assert cli_main(["race", str(tmp_path / "five.pt"), str(tmp_path / "sac.pt"), "bot:follow@1.0", "--laps", "1",
                     "--max-steps", "45", "--json", str(result)]) == 0
    cars = {car["name"]: car for car in json.loads(result.read_text())["cars"]}
    assert set(cars) == {"five", "sac", "bot:follow@1.0"}
    for name in ("five", "sac"):
        assert cars[name]["status"] != "forfeit" and cars[name]["progress"] > 0, cars[name]

    from multirace.league.submissions import init_league, submit
    from multirace.league.runner import run_league
    folder = tmp_path / "league"
    init_league(folder)
    (folder / "league.toml").write_text(LEAGUE_TOML)
    submit(folder, tmp_path / "five.pt", "five")
    stats = run_league(folder, workers=1, progress=False)
    assert stats["ran"] == 3 and stats["failed"] == 0  # 2 time trials and the heat
    with sqlite3.connect(folder / "results.sqlite") as conn:
        rows = conn.execute("SELECT status, result FROM results").fetchall()
    assert all(status == "ok" for status, _ in rows) and "forfeit" not in json.dumps([r for _, r in rows])


def test_the_exported_metadata_names_no_build_machine_folder(tmp_path):
    out = export_agent("racer", tmp_path / "racer.tar.gz")  # racer.pt was made with an absolute --action-space
    text = (unpack(out, tmp_path / "x") / "model_metadata.json").read_text()
    assert "action_space_racer.json" in text and "/agents/action_space_racer.json" not in text
