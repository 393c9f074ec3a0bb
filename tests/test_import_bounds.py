"""`agent import` and agent files within bounds: hostile DeepRacer graphs, archives and imported-graph agent
files (all made here) end in one clear error naming the file, node or field, in bounded memory and time."""
from __future__ import annotations

import gzip
import io
import json
import math
import subprocess
import sys
import tarfile

import numpy as np
import pytest
import torch

from multirace.cli import main
from multirace.deepracer.importer import ModelImportError, import_model
from multirace.deepracer.tfgraph import DT_FLOAT, DT_INT32, GraphBuilder, GraphDef
from multirace.racing.agentfile import AgentFileError, load_agent, write_agent_file
from multirace.racing.graphnet import GRAPH_FIELD, GraphNet

DISCRETE = {"action_space": [{"steering_angle": s, "speed": 1.0} for s in (-30, 0, 30)],
            "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"}
POLICY = "main_level/agent/main/online/network_1/ppo_head_0/policy"
MEMORY = 3 * 2**30  # address space of a probe: enough for torch, far below what the hostile files asked for


def small_graph(*, shape=(-1, 36, 48, 1), strides=(1, 4, 4, 1), kernel=None, weights=None) -> GraphBuilder:
    """A frozen policy graph small enough to build in a test: /255, one 4x4 convolution, flatten, dense, softmax."""
    g = GraphBuilder()
    x = g.node("network_0/FRONT_FACING_CAMERA/FRONT_FACING_CAMERA", "Placeholder", dtype=("type", DT_FLOAT),
               shape=("shape", list(shape)))
    x = g.op("truediv", "RealDiv", [x, g.const("truediv/y", np.float32(255))])
    kernel = kernel if kernel is not None else np.full((4, 4, 1, 2), 0.1, np.float32)
    x = g.op("conv/Conv2D", "Conv2D", [x, g.const("conv/kernel", kernel)], strides=("ints", list(strides)),
             padding="VALID", data_format="NHWC")
    x = g.op("relu", "Relu", [x])
    x = g.node("flatten", "Reshape", [x, g.const("flatten/shape", np.array([-1, 216], np.int32))],
               T=("type", DT_FLOAT), Tshape=("type", DT_INT32))
    weights = weights if weights is not None else np.full((216, 3), 0.01, np.float32)
    x = g.op("dense/MatMul", "MatMul", [x, g.const("dense/kernel", weights)])
    g.op(POLICY, "Softmax", [x])
    return g


def write_model(folder, graph: bytes, metadata=DISCRETE):
    folder.mkdir(exist_ok=True)
    (folder / "model.pb").write_bytes(graph)
    (folder / "model_metadata.json").write_text(metadata if isinstance(metadata, str) else json.dumps(metadata))
    return folder / "model.pb"


def node(graph: GraphDef, name: str):
    return next(n for n in graph.node if n.name == name)


def bounded_cli(*argv, memory=MEMORY, timeout=600):
    """`multirace ARGV` in a Python whose address space is capped (a probe that allocated GBs fails instead)."""
    code = (f"import resource, sys\nresource.setrlimit(resource.RLIMIT_AS, ({memory}, {memory}))\n"
            "from multirace.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    return subprocess.run([sys.executable, "-c", code, *map(str, argv)], capture_output=True, text=True,
                          timeout=timeout)


def test_a_small_graph_imports(tmp_path):
    import_model(write_model(tmp_path / "m", small_graph().to_bytes()), tmp_path / "ok.pt")
    assert load_agent(tmp_path / "ok.pt", step_budget=None).net.image_shape == (36, 48, 1)


def _cycle(g):  # the dense kernel read through two Identity nodes that read each other
    node(g.graph, "dense/MatMul").input[1] = "loop_a"
    g.node("loop_a", "Identity", ["loop_b"], T=("type", DT_FLOAT))
    g.node("loop_b", "Identity", ["loop_a"], T=("type", DT_FLOAT))


def _broadcast(g):  # 20 unused constants of 2^26 values, one float_val each (35 bytes apiece)
    for k in range(20):
        g.node(f"unused_{k}", "Const", dtype=("type", DT_FLOAT), value=np.array(1, np.float32))
        node(g.graph, f"unused_{k}").attr["value"].tensor.tensor_shape.dim.add(size=2**26)


def _used_broadcast(g):  # the dense kernel declared as 8000 x 7000 values from one float_val
    t = node(g.graph, "dense/kernel").attr["value"].tensor
    t.ClearField("tensor_content")
    t.float_val.append(0.5)
    del t.tensor_shape.dim[:]
    t.tensor_shape.dim.add(size=8000)
    t.tensor_shape.dim.add(size=7000)


def _short_strides(g):
    del node(g.graph, "conv/Conv2D").attr["strides"].list.i[2:]


def _missing_rescaler(g):  # the head's gradient rescaler (1-r)*x + r*x with its factors missing from the graph
    node(g.graph, POLICY).input[0] = "rescaler/add"
    g.node("rescaler/add", "Add", ["rescaler/mul_a", "rescaler/mul_b"], T=("type", DT_FLOAT))
    g.node("rescaler/mul_a", "Mul", ["dense/MatMul", "rescaler/r"], T=("type", DT_FLOAT))
    g.node("rescaler/mul_b", "Mul", ["dense/MatMul", "rescaler/one_minus_r"], T=("type", DT_FLOAT))


@pytest.mark.parametrize("change, words", [
    (_cycle, "form a cycle"),
    (_broadcast, None),
    (_used_broadcast, "over 51,048,576 values"),
    (_short_strides, "attribute strides is [1, 4]; expected 4 positive integers"),
    (_missing_rescaler, "'rescaler/r' is referenced but not in the graph"),
])
def test_a_hostile_graph_is_a_clear_error_in_bounded_memory(tmp_path, change, words):
    g = small_graph()
    change(g)
    pb = write_model(tmp_path / "m", g.to_bytes())
    done = bounded_cli("agent", "import", pb, "--out", tmp_path / "x.pt")
    if words is None:  # unused constants are never decoded: the model imports
        assert done.returncode == 0, done.stderr[-2000:]
        return
    assert done.returncode == 2 and words in done.stderr and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert not (tmp_path / "x.pt").exists()


def test_an_average_pool_with_a_short_window_names_the_node(tmp_path):
    g = small_graph()
    node(g.graph, "relu").op = "AvgPool"
    node(g.graph, "relu").attr["ksize"].list.i.extend([1, 2])
    node(g.graph, "relu").attr["strides"].list.i.extend([1, 2])
    node(g.graph, "relu").attr["padding"].s = b"VALID"
    with pytest.raises(ModelImportError, match="node 'relu' .AvgPool.: attribute ksize is"):
        import_model(write_model(tmp_path / "m", g.to_bytes()), tmp_path / "x.pt")


@pytest.mark.parametrize("shape", [[-1, 2000, 2000, 1], [-1, 1080, 1920, 3]])
def test_a_huge_declared_image_is_a_clear_error_not_gigabytes(tmp_path, shape):
    from test_export import SHALLOW_CONVS, deepracer_graph  # (skips without OpenVINO, as its module does)

    graph = GraphDef()
    graph.ParseFromString(deepracer_graph(np.random.default_rng(0), convs=SHALLOW_CONVS, outputs=3))
    placeholder = next(n for n in graph.node if n.op == "Placeholder")
    del placeholder.attr["shape"].shape.dim[:]
    for size in shape:
        placeholder.attr["shape"].shape.dim.add(size=size)
    pb = write_model(tmp_path / "m", graph.SerializeToString())
    done = bounded_cli("agent", "import", pb, "--out", tmp_path / "x.pt")
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert "model.pb" in done.stderr and ("reads" in done.stderr or "over the limit" in done.stderr), done.stderr


def test_import_refuses_non_finite_weights_before_writing(tmp_path):
    weights = np.full((216, 3), 0.01, np.float32)
    weights[5, 1] = np.inf
    with pytest.raises(ModelImportError, match="not finite|non-finite"):
        import_model(write_model(tmp_path / "m", small_graph(weights=weights).to_bytes()), tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()
    from test_export import SHALLOW_CONVS, deepracer_graph

    graph = GraphDef()  # the same through a multirace network (CameraNet): refused by the loader's own checks
    graph.ParseFromString(deepracer_graph(np.random.default_rng(0), convs=SHALLOW_CONVS, outputs=3))
    kernel = next(n for n in graph.node if n.name.endswith("policy_fc/kernel")).attr["value"].tensor
    kernel.tensor_content = np.full(len(kernel.tensor_content) // 4, np.nan, np.float32).tobytes()
    with pytest.raises(ModelImportError, match="refused before writing: .*non-finite"):
        import_model(write_model(tmp_path / "n", graph.SerializeToString()), tmp_path / "y.pt")
    assert not (tmp_path / "y.pt").exists()


def test_deeply_nested_metadata_is_a_clear_error(tmp_path):
    nested = '{"action_space": ' + "[" * 100_000 + "]" * 100_000 + "}"
    with pytest.raises(ModelImportError, match="model_metadata.json is nested too deeply"):
        import_model(write_model(tmp_path / "m", small_graph().to_bytes(), nested), tmp_path / "x.pt")


def _archive(path, members):
    with tarfile.open(path, "w:gz") as tar:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def test_a_truncated_archive_is_one_line(tmp_path, capsys):
    whole = _archive(tmp_path / "whole.tar.gz", [("model_metadata.json", json.dumps(DISCRETE).encode()),
                                                 ("agent/model.pb", small_graph().to_bytes())]).read_bytes()
    (tmp_path / "cut.tar.gz").write_bytes(whole[:len(whole) // 2])
    assert main(["agent", "import", str(tmp_path / "cut.tar.gz"), "--out", str(tmp_path / "x.pt")]) == 2
    err = capsys.readouterr().err
    assert "cut.tar.gz: not a readable .tar.gz archive" in err and err.count("\n") == 1, err


def test_an_archive_member_of_64_gib_of_zeros_is_refused_from_its_header(tmp_path):
    """The archive's header declares 64 GiB of zeros before the model; its gzip stream is written here in
    pieces (a few MB on disk, nothing like 64 GiB in memory) and the import refuses it without reading on."""
    path = tmp_path / "bomb.tar.gz"
    header = tarfile.TarInfo("zeros.bin")
    header.size = 64 * 2**30
    with gzip.open(path, "wb", compresslevel=1) as out:
        out.write(header.tobuf(format=tarfile.GNU_FORMAT))
        zeros = bytes(2**24)
        for _ in range(64):  # the first GiB of the member (enough for the point; the header says 64)
            out.write(zeros)
    done = bounded_cli("agent", "import", path, "--out", tmp_path / "x.pt", timeout=300)
    assert done.returncode == 2 and "'zeros.bin'" in done.stderr and "over 512 MB" in done.stderr, done.stderr


def _graph_agent(path, spec, image):
    """An imported-graph agent file (a `GraphNet` spec in its metadata) of a few KB."""
    from multirace.environment.actions import ActionSpace

    space = ActionSpace(DISCRETE)
    net = GraphNet(spec, space)
    metadata = {"name": "graph", "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEPRACER_GRAPH",
                "image": dict(zip(("height", "width", "channels"), image)), "version": "5",
                "training_algorithm": "deepracer_import", **space.to_metadata(), GRAPH_FIELD: spec}
    return write_agent_file(path, metadata, net)


def test_an_imported_graph_agent_that_would_need_gigabytes_is_refused_by_its_numbers(tmp_path):
    spec = {"inputs": {"FRONT_FACING_CAMERA": {"shape": [1080, 1920, 3], "layers": [
        {"type": "conv", "in": 3, "out": 512, "k": 1, "stride": 1}, {"type": "pool", "k": 1080},
        {"type": "flatten"}]}}, "layers": [{"type": "dense", "in": 512, "out": 3}], "output": "softmax"}
    path = _graph_agent(tmp_path / "huge.pt", spec, (1080, 1920, 3))
    assert path.stat().st_size < 64 * 2**10
    with pytest.raises(AgentFileError, match="'deepracer_graph' .*one inference computes [0-9,]+ values"):
        load_agent(path, step_budget=None)
    done = bounded_cli("race", path, "bot:follow@1.0", "--max-steps", "3", memory=2 * 2**30)
    assert done.returncode == 0 and "forfeit" in done.stdout, done.stderr[-2000:]
    done = bounded_cli("agent", "export", path, "--out", tmp_path / "car.tar.gz", memory=2 * 2**30)
    assert done.returncode == 2 and "one inference computes" in done.stderr, done.stderr[-2000:]
    assert not (tmp_path / "car.tar.gz").exists()


def test_a_name_of_five_thousand_digits_forfeits_its_entrant_naming_the_field(tmp_path):
    spec = {"inputs": {"FRONT_FACING_CAMERA": {"shape": [36, 48, 1], "layers": [{"type": "flatten"}]}},
            "layers": [{"type": "dense", "in": 1728, "out": 3}], "output": "softmax"}
    path = _graph_agent(tmp_path / "digits.pt", spec, (36, 48, 1))
    payload = torch.load(path, weights_only=True)
    payload["metadata"] = payload["metadata"].replace('"name": "graph"', '"name": ' + "9" * 5000)
    torch.save(payload, path)
    with pytest.raises(AgentFileError, match="metadata field 'name' is a number of over 4,300 digits"):
        load_agent(path, step_budget=None)


def test_inspect_prints_the_start_of_huge_metadata(tmp_path, capsys):
    spec = {"inputs": {"FRONT_FACING_CAMERA": {"shape": [36, 48, 1], "layers": [{"type": "flatten"}]}},
            "layers": [{"type": "dense", "in": 1728, "out": 3}], "output": "softmax"}
    path = _graph_agent(tmp_path / "big.pt", spec, (36, 48, 1))
    payload = torch.load(path, weights_only=True)
    metadata = json.loads(payload["metadata"])
    metadata["training"] = {"notes": ["x" * 100] * 30_000}  # 3 MB of metadata, within the 4 MB limit
    payload["metadata"] = json.dumps(metadata)
    torch.save(payload, path)
    assert main(["agent", "inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "more characters of metadata; --json prints them all" in out and len(out) < 100_000
    assert math.isclose(len(out), 20_000, rel_tol=0.5)


def test_long_list_attributes_are_not_decoded():
    from multirace.deepracer.tfgraph import parse_graph

    g = small_graph()
    g.node("unused", "NoOp", [], strides=("ints", range(10_000)))
    nodes = parse_graph(g.to_bytes())
    assert nodes["unused"].attrs["strides"] is None and nodes["conv/Conv2D"].attrs["strides"] == [1, 4, 4, 1]


def test_a_constant_listing_more_values_than_its_shape_is_a_clear_error(tmp_path):
    g = small_graph()
    t = node(g.graph, "dense/kernel").attr["value"].tensor
    t.ClearField("tensor_content")
    t.float_val.extend([0.5] * (216 * 3 + 1))
    with pytest.raises(ModelImportError, match="node 'dense/kernel': a constant of shape .216, 3. lists 649 values"):
        import_model(write_model(tmp_path / "m", g.to_bytes()), tmp_path / "x.pt")


@pytest.mark.slow  # decodes 50 M values (about 30 s here)
def test_a_graph_over_the_parameter_limit_is_refused_before_its_network_is_built(tmp_path):
    g = small_graph()
    t = node(g.graph, "dense/kernel").attr["value"].tensor
    t.ClearField("tensor_content")
    t.float_val.append(0.01)
    del t.tensor_shape.dim[:]
    t.tensor_shape.dim.add(size=216)
    t.tensor_shape.dim.add(size=231_500)  # 50,004,000 values from one float_val: within the walk's budget
    node(g.graph, POLICY).op = "Identity"  # no softmax over 231,500 outputs: a continuous head, say
    done = bounded_cli("agent", "import", write_model(tmp_path / "m", g.to_bytes()), "--out", tmp_path / "x.pt")
    assert done.returncode == 2 and "50,235,534 parameters, over the limit of 50,000,000" in done.stderr, done.stderr
