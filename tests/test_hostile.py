"""Hostile and careless input: every probe ends in a clear error, a forfeit with a reason, or correct
behaviour; none hangs, none crashes with a raw traceback, nothing reaches what it must not."""
import time

import numpy as np
import pytest

import multirace
from helpers import small_league
from multirace.environment.rewards import RewardFunctionError

# ------------------------------------------------------------------ reward functions
BAD_REWARDS = {
    "loops_forever": ("def reward_function(params):\n    while True:\n        pass\n", "did not return within"),
    "exits": ("import sys\ndef reward_function(params):\n    sys.exit(0)\n", "sys.exit(0)"),
    "huge_int": ("def reward_function(params):\n    return 10**400\n", "too large for a float"),
    "string": ("def reward_function(params):\n    return '0.5'\n", "not a str"),
    "bool": ("def reward_function(params):\n    return True\n", "not a bool"),
    "recursion": ("def reward_function(params):\n    return reward_function(params)\n", "RecursionError"),
}


def _env_with(tmp_path, source, name="reward.py"):
    path = tmp_path / name
    path.write_text(source)
    return multirace.parallel_env(num_cars=1, reward_function=str(path), max_steps=20)


@pytest.mark.parametrize("case", sorted(BAD_REWARDS))
def test_a_bad_reward_function_is_a_clear_error_naming_the_file_and_step(tmp_path, case):
    source, words = BAD_REWARDS[case]
    env = _env_with(tmp_path, source, f"{case}.py")
    env.reset(seed=0)
    start = time.monotonic()
    with pytest.raises(RewardFunctionError) as err:
        env.step({"car_0": 0})
    assert f"{case}.py" in str(err.value) and "step 1" in str(err.value) and words in str(err.value)
    assert time.monotonic() - start < 10


@pytest.mark.parametrize("source, words", [
    ("while True:\n    pass\n", "did not finish within"),
    ("import sys\nsys.exit(3)\n", r"sys\.exit\(3\)"),
])
def test_a_reward_file_that_hangs_or_exits_when_loaded_is_a_clear_error(tmp_path, monkeypatch, source, words):
    monkeypatch.setattr("multirace.environment.rewards.LOAD_TIME_LIMIT", 1.0)  # the limit, not its 10 s value
    path = tmp_path / "load.py"
    path.write_text(source + "def reward_function(params):\n    return 1.0\n")
    with pytest.raises(RewardFunctionError, match=words):
        multirace.parallel_env(num_cars=1, reward_function=str(path))


def test_what_a_reward_function_does_to_its_params_reaches_nothing(tmp_path):
    env = _env_with(tmp_path, "def reward_function(params):\n"
                              "    del params['is_offtrack']\n"
                              "    params['x'] = 12345\n"
                              "    params['waypoints'][0] = (999, 999)\n"
                              "    params['closest_waypoints'].append(7)\n"
                              "    return 1.0\n")
    waypoints = list(env.track.waypoints)
    env.reset(seed=0)
    for _ in range(3):
        _, rewards, _, _, infos = env.step({"car_0": 0})
    assert rewards["car_0"] == 1.0
    info = infos["car_0"]
    assert "is_offtrack" in info and info["x"] != 12345 and len(info["closest_waypoints"]) == 2
    assert env.track.waypoints == waypoints and info["waypoints"][0] == waypoints[0]


# ------------------------------------------------------------------ env arguments and actions
CONTINUOUS = {"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.1, "high": 4}},
              "action_space_type": "continuous"}


@pytest.mark.parametrize("action, words", [(-1, "out of range"), (10, "out of range"), (3.7, "integer index"),
                                           ("2", "integer index"), (True, "integer index"), (None, "integer index")])
def test_a_bad_discrete_action_names_the_car_and_step(action, words):
    env = multirace.parallel_env(num_cars=2)
    env.reset(seed=0)
    env.step({"car_0": 1, "car_1": 1})
    with pytest.raises(ValueError, match=f"step 2, car_1: .*{words}"):
        env.step({"car_0": 1, "car_1": action})


@pytest.mark.parametrize("action", [[float("nan"), 1.0], [0.0, float("inf")], [1.0], "fast"])
def test_a_bad_continuous_action_names_the_car_and_step(action):
    env = multirace.parallel_env(num_cars=1, action_space=CONTINUOUS)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="step 1, car_0"):
        env.step({"car_0": action})
    assert np.all(np.isfinite(env.world.poses))  # no NaN reached the world


@pytest.mark.parametrize("kwargs, words", [({"max_steps": -1}, "max_steps"), ({"max_steps": 0}, "max_steps"),
                                           ({"max_steps": 2.5}, "max_steps"), ({"laps": 1.7}, "laps"),
                                           ({"laps": 0}, "laps")])
def test_bad_env_arguments_are_refused_up_front(kwargs, words):
    with pytest.raises(ValueError, match=words):
        multirace.parallel_env(num_cars=1, **kwargs)


def test_cli_refuses_a_zero_step_limit_before_racing(capsys):
    from multirace.cli import main

    assert main(["race", "bot:follow@1.0", "--max-steps", "0"]) == 2
    assert "--max-steps" in capsys.readouterr().err


# ------------------------------------------------------------------ agent files
import io  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import pickle  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import zipfile  # noqa: E402

from multirace.environment.actions import ActionSpaceError, load_action_space  # noqa: E402
from multirace.racing.agentfile import AgentFileError, load_agent, make_metadata, save_agent  # noqa: E402
from multirace.racing.nets import SHALLOW, TINY, build_net  # noqa: E402

SPACE = load_action_space(None)


def _valid_agent(path):
    return save_agent(path, build_net(TINY, (120, 160, 1), SPACE), make_metadata(SPACE, TINY, "ok"))


def _rewrite(path, edit):
    """Rewrite the torch archive at `path`, passing each (name, bytes, compress_type) through `edit`."""
    with zipfile.ZipFile(path) as archive:
        entries = [(i.filename, archive.read(i), i.compress_type) for i in archive.infolist()]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data, compress in entries:
            name, data, compress = edit(name, data, compress)
            archive.writestr(name, data, compress_type=compress)
    path.write_bytes(buffer.getvalue())
    return path


class _Bytearray:
    def __reduce__(self):
        return (bytearray, (3 * 10**9,))


def _bytearray_bomb(path):
    payload = pickle.dumps({"format": "multirace-agent", "format_version": 1, "metadata": "{}",
                            "state_dict": {"x": _Bytearray()}}, protocol=2)
    return _rewrite(_valid_agent(path), lambda n, d, c: (n, payload if n.endswith("data.pkl") else d, c))


def _patched_count(path):
    def edit(name, data, compress):  # the first storage claims 10**9 floats: a 4 GB allocation
        if name.endswith("data.pkl"):
            at = data.index(b"X\x03\x00\x00\x00cpu") + 8
            at = data.index(b"t", at)  # the storage tuple ends with its element count, then TUPLE
            start = max(data.rindex(op, at - 6, at) for op in (b"K", b"M", b"J") if data.rfind(op, at - 6, at) >= 0)
            data = data[:start] + b"J" + (10**9).to_bytes(4, "little") + data[at:]
        return name, data, compress
    return _rewrite(_valid_agent(path), edit)


def _patched_shape(path):
    def edit(name, data, compress):  # the first tensor claims 2**30 rows over its small storage
        if name.endswith("data.pkl"):
            import pickletools

            ops = list(pickletools.genops(data))
            at = next(k for k, (op, _, _) in enumerate(ops) if op.name == "BINPERSID")
            op, _, pos = ops[at + 3]  # storage offset, MARK, then the first size
            assert op.name == "BININT1"
            data = data[:pos] + b"J" + (2**30).to_bytes(4, "little") + data[pos + 2:]
        return name, data, compress
    return _rewrite(_valid_agent(path), edit)


def _deflated(path):
    return _rewrite(_valid_agent(path), lambda n, d, c: (n, d, zipfile.ZIP_DEFLATED if "/data/" in n else c))


def _huge_image(path):  # a small file whose metadata claims the shallow network on 1080x1920 colour images
    metadata = make_metadata(SPACE, SHALLOW, "huge", image_shape=(1080, 1920, 3))
    torch_save({"format": "multirace-agent", "format_version": 1, "metadata": json.dumps(metadata),
                "state_dict": build_net(TINY, (120, 160, 1), SPACE).state_dict()}, path)
    return path


def _deep_metadata(path):
    torch_save({"format": "multirace-agent", "format_version": 1, "metadata": "[" * 200_000, "state_dict": {}}, path)
    return path


def torch_save(obj, path):
    import torch

    torch.save(obj, path)


def _fifo(path):
    os.mkfifo(path)
    return path


HOSTILE_AGENTS = {
    "bytearray_bomb": (_bytearray_bomb, "refused: the file's pickle names '.*bytearray'"),
    "patched_element_count": (_patched_count, "declares 1000000000 elements"),
    "deflated_storage": (_deflated, "stored, uncompressed"),
    "patched_tensor_shape": (_patched_shape, "unreadable"),
    "metadata_claims_huge_images": (_huge_image, "out of range|over the limit"),
    "deeply_nested_metadata": (_deep_metadata, "nested too deeply|unreadable"),
    "fifo": (_fifo, "not a regular file"),
    "dev_zero": (lambda path: "/dev/zero", "not a regular file"),
    "folder": (lambda path: path.parent, "is a directory"),
}


MEMORY_LIMIT = 3 * 2**29  # 1.5 GB of address space for the loading process


@pytest.fixture(scope="module")
def hostile_agent_outcomes(tmp_path_factory):
    """Every hostile agent file loaded in one subprocess held to `MEMORY_LIMIT` of address space (an
    allocation past it fails there); per file: what load_agent said and the process's peak RSS so far (VmHWM)."""
    folder = tmp_path_factory.mktemp("hostile_agents")
    paths = {case: str(make(folder / f"{case}.pt")) for case, (make, _) in HOSTILE_AGENTS.items()}
    code = ("import json, resource, sys\n"
            f"resource.setrlimit(resource.RLIMIT_AS, ({MEMORY_LIMIT}, {MEMORY_LIMIT}))\n"
            "from multirace.racing.agentfile import AgentFileError, load_agent\n"
            "def peak_kb():  # this process's own peak RSS (ru_maxrss would include the parent's, kept over exec)\n"
            "    with open('/proc/self/status') as status:\n"
            "        return next(int(line.split()[1]) for line in status if line.startswith('VmHWM'))\n"
            "outcomes = {}\n"
            "for case, path in json.loads(sys.argv[1]).items():\n"
            "    try:\n"
            "        load_agent(path)\n"
            "        outcome = 'loaded'\n"
            "    except AgentFileError as exc:\n"
            "        outcome = str(exc)\n"
            "    outcomes[case] = [outcome, peak_kb()]\n"
            "print(json.dumps(outcomes))\n")
    done = subprocess.run([sys.executable, "-c", code, json.dumps(paths)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("case", sorted(HOSTILE_AGENTS))
def test_hostile_agent_files_are_refused_in_bounded_memory_and_time(hostile_agent_outcomes, case):
    import re

    outcome, peak_kb = hostile_agent_outcomes[case]
    assert outcome != "loaded"
    assert re.search(HOSTILE_AGENTS[case][1], outcome), outcome  # the reason, not a MemoryError at the limit
    assert peak_kb < 1.5 * 2**20  # under 1.5 GB at its peak (the interpreter with torch is about 0.3 GB)


@pytest.mark.parametrize("case", ["bytearray_bomb", "fifo"])
def test_a_hostile_agent_forfeits_and_the_race_goes_on(tmp_path, case):
    from multirace.racing.runner import RaceConfig, make_controller, run_race

    path = HOSTILE_AGENTS[case][0](tmp_path / f"{case}.pt")
    result = run_race([make_controller(str(path)), make_controller("bot:follow@1.0")],
                      RaceConfig(race="head_to_head", laps=1, max_steps=60))
    cars = {c["car"]: c for c in result["cars"]}
    assert cars["car_0"]["status"] == "forfeit" and cars["car_1"]["status"] != "forfeit"


# ------------------------------------------------------------------ action spaces
@pytest.mark.parametrize("content, words", [
    ("{\"action_space\": [{\"steering_angle\": 0, \"speed\": \"1.0\"}]}".encode(), "must be numbers"),
    ("{\"action_space\": [{\"steering_angle\": true, \"speed\": 1.0}]}".encode(), "must be numbers"),
    ("\ufeff{}".encode("utf-16"), "not UTF-8"),
    (b"\x00\xff\x13garbage", "not UTF-8|not valid JSON"),
    (b"[" * 100_000, "nested too deeply|not valid JSON"),
    (json.dumps({"action_space": [{"steering_angle": 0, "speed": 1.0}] * 5_000}).encode(), "more than the 1000"),
    (json.dumps({"action_space": [{"steering_angle": 0, "speed": 1.0}] * 200_000}).encode(), "larger than 1 MB"),
], ids=["speed_as_text", "boolean", "utf16", "binary", "deep", "too_many_actions", "huge_file"])
def test_bad_action_space_files_are_clear_errors(tmp_path, content, words):
    path = tmp_path / "model_metadata.json"
    path.write_bytes(content)
    with pytest.raises(ActionSpaceError, match=words):
        load_action_space(path)
    with pytest.raises(ActionSpaceError, match="is a folder"):
        load_action_space(tmp_path)


# ------------------------------------------------------------------ names are data, never markup
EVIL_NAME = "\x1b[31m\x1b]8;;http://x\x07[link=http://x]evil[/link][/bold] | =1\n"


def test_a_hostile_agent_name_is_shown_as_text_in_the_results_table(tmp_path, capsys, monkeypatch):
    from multirace.cli import main

    monkeypatch.setenv("COLUMNS", "250")  # a wide terminal: the name is not wrapped

    path = save_agent(tmp_path / "evil.pt", build_net(TINY, (120, 160, 1), SPACE), make_metadata(SPACE, TINY, EVIL_NAME))
    assert main(["race", str(path), "bot:follow@1.0", "--laps", "1", "--max-steps", "30"]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out
    assert "[link=http://x]evil" in out  # printed as written (markup not rendered, no hyperlink made)


def test_league_names_are_escaped_in_every_table_format(tmp_path):
    from multirace.league.config import LeagueError
    from multirace.league.runner import run_league
    from multirace.league.submissions import init_league, submit
    from multirace.league.table import write_table

    folder = tmp_path / "lg"
    init_league(folder)
    toml = (folder / "league.toml").read_text()
    toml = toml.replace('name = "multirace default league"', 'name = "$\\\\frac{$ | =HYPERLINK(1) <b>"')
    toml = toml.replace("seeds = [1, 2]", "seeds = [1]").replace("laps = 3", "laps = 1")
    toml = toml.replace('directions = ["forward", "reverse"]', 'directions = ["forward"]')
    toml = toml.replace('[[tracks]]\nname = "2022_summit_speedway"\ndirections = ["forward"]\n', "")
    (folder / "league.toml").write_text(toml)
    for bad in ("=HYPERLINK(\"http://x\")", "a|b", "line\nbreak", "[bold]x", "x" * 65, "$\\frac{$"):
        with pytest.raises(LeagueError, match="not a valid entrant name"):
            submit(folder, _valid_agent(tmp_path / "a.pt"), bad)
    submit(folder, _valid_agent(tmp_path / "a.pt"), "plain-name_1.0")
    run_league(folder, workers=1, progress=False)
    md = write_table(folder, "md")
    assert "$\\\\frac{$ \\| =HYPERLINK(1) &lt;b&gt;" in md  # Markdown's own escapes: shown as written
    html = write_table(folder, "html")
    assert "<b>" not in html.split("<body>", 1)[-1] and "&lt;b&gt;" in html  # rating plot drew the title too
    assert all(not cell.startswith(("=", "+", "@")) for line in write_table(folder, "csv").splitlines()
               for cell in line.split(","))


# ------------------------------------------------------------------ leagues
SMALL_LEAGUE = small_league()


@pytest.fixture
def league(tmp_path):
    from multirace.league.runner import run_league
    from multirace.league.submissions import init_league, submit

    toml = tmp_path / "small.toml"
    toml.write_text(SMALL_LEAGUE)
    folder = init_league(tmp_path / "lg", toml)
    submit(folder, _valid_agent(tmp_path / "a.pt"), "a", validate=False)
    run_league(folder, workers=1, progress=False)
    return folder


def _truncate(path, size):
    with open(path, "r+b") as handle:
        handle.truncate(size)


DAMAGE = {
    "truncated_to_zero": (lambda db: _truncate(db, 0), "empty"),
    "deleted": (lambda db: db.unlink(), "missing"),
    "half_truncated": (lambda db: _truncate(db, db.stat().st_size // 2), "damaged|not a multirace league store"),
    "garbage_header": (lambda db: db.write_bytes(b"garbage!" * 512 + db.read_bytes()[4096:]), "damaged"),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_league_store_is_refused_with_the_way_to_recover(league, case):
    from multirace.cli import main
    from multirace.league.config import LeagueError
    from multirace.league.runner import run_league
    from multirace.league.table import write_table

    db = league / "results.sqlite"
    for side in ("-wal", "-shm"):
        (league / f"results.sqlite{side}").unlink(missing_ok=True)
    damage, words = DAMAGE[case]
    damage(db)
    for action in (lambda: run_league(league, workers=1, progress=False), lambda: write_table(league, "md")):
        with pytest.raises(LeagueError, match=words) as err:
            action()
        assert "league init" in str(err.value)  # the way to recover
    assert main(["league", "table", str(league)]) == 2


def test_a_second_league_run_is_refused_while_one_holds_the_lock(league):
    import fcntl

    from multirace.league.config import LeagueError
    from multirace.league.runner import RUN_LOCK, run_league

    with open(league / RUN_LOCK, "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(LeagueError, match="another `multirace league run`"):
            run_league(league, workers=1, progress=False)
    assert run_league(league, workers=1, progress=False)["ran"] == 0  # released: runs (nothing left to do)


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace("seeds = [1]", "seeds = [-1]"), "seeds"),
    (lambda t: t.replace('name = "reinvent_base"', 'name = "no_such_track"'), "unusable track"),
    (lambda t: t.replace('bots = ["bot:follow@1.5"]', 'bots = ["bot:fly@9"]'), "bot"),
])
def test_a_bad_league_definition_is_refused_at_init(tmp_path, edit, words):
    from multirace.league.config import LeagueError
    from multirace.league.submissions import init_league

    toml = tmp_path / "bad.toml"
    toml.write_text(edit(SMALL_LEAGUE))
    with pytest.raises(LeagueError, match=words):
        init_league(tmp_path / "lg", toml)
    assert not (tmp_path / "lg").exists()


def test_init_refuses_a_missing_template_and_a_path_that_is_a_file(tmp_path):
    from multirace.league.config import LeagueError
    from multirace.league.submissions import init_league

    with pytest.raises(LeagueError, match="no such league definition"):
        init_league(tmp_path / "lg", tmp_path / "typo.toml")
    (tmp_path / "file").write_text("x")
    with pytest.raises(LeagueError, match="not a folder"):
        init_league(tmp_path / "file")


# ------------------------------------------------------------------ nothing a file holds is ever run
class _Payload:
    """Pickles as a call that would create the marker file if anything ever ran it."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _torch_zip_with_code(path, marker):
    torch_save({"format": "multirace-agent", "format_version": 1, "metadata": "{}",
                "state_dict": {"x": _Payload(marker)}}, path)


def _raw_pickle(path, marker):
    path.write_bytes(pickle.dumps(_Payload(marker), protocol=4))


def _protocol0_global(path, marker):
    path.write_bytes(f"cos\nsystem\n(S'touch {marker}'\ntR.".encode())


@pytest.mark.parametrize("make", [_torch_zip_with_code, _raw_pickle, _protocol0_global],
                         ids=["reduce_in_torch_zip", "raw_pickle", "protocol0_global"])
def test_code_in_an_agent_file_is_refused_and_never_run(tmp_path, make):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pt"
    make(path, marker)
    with pytest.raises(AgentFileError, match="refused|unreadable"):
        load_agent(path, step_budget=None)
    assert not marker.exists()


def test_code_in_a_track_file_is_refused_and_never_run(tmp_path):
    from multirace.sim.tracks import TrackError, load_track

    marker = tmp_path / "ran"
    np.save(tmp_path / "evil.npy", np.array([_Payload(marker)] * 6, dtype=object).reshape(1, 6), allow_pickle=True)
    with pytest.raises(TrackError, match="evil.npy: cannot be read"):
        load_track(tmp_path / "evil.npy")
    assert not marker.exists()


def test_agent_inspect_runs_under_memory_and_time_limits(tmp_path):
    from multirace.racing.agentfile import inspect_agent_isolated

    info = inspect_agent_isolated(_bytearray_bomb(tmp_path / "bomb.pt"))
    assert info["valid"] is False and "bytearray" in info["error"]
    info = inspect_agent_isolated(_valid_agent(tmp_path / "ok.pt"), timeout=0.01)
    assert info["valid"] is False and "did not finish within" in info["error"]


def test_agent_inspect_prints_a_hostile_name_as_text(tmp_path, capsys):
    from multirace.cli import main

    path = save_agent(tmp_path / "evil.pt", build_net(TINY, (120, 160, 1), SPACE), make_metadata(SPACE, TINY, EVIL_NAME))
    assert main(["agent", "inspect", str(path)]) == 0
    name_line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("name"))
    assert "\x1b" not in name_line and "\x07" not in name_line and "[link=http://x]evil" in name_line


# ------------------------------------------------------------------ tracks
def _ring(points=120, radius=3.0, half_width=0.4):
    theta = np.linspace(0, 2 * np.pi, points)
    unit = np.column_stack([np.cos(theta), np.sin(theta)])
    return np.column_stack([radius * unit, (radius - half_width) * unit, (radius + half_width) * unit])


HOSTILE_TRACKS = {
    "empty": (lambda: np.zeros((0, 6)), "0 waypoints"),
    "centimetres": (lambda: _ring() * 100, "implausible scale"),
    "millimetres": (lambda: _ring() * 1000, "implausible scale"),
    "six_cm_road": (lambda: _ring(half_width=0.03), "wide \\(median\\)"),
    "centre_outside": (lambda: np.column_stack([_ring()[:, 0:2] * 1.2, _ring()[:, 2:6]]), "outside the road"),
    "too_many_rows": (lambda: _ring(points=100_001, radius=10.0), "100001 waypoints"),
    "open_route": (lambda: np.column_stack([np.linspace(0, 10, 50), np.zeros(50), np.linspace(0, 10, 50),
                                            np.full(50, 0.4), np.linspace(0, 10, 50), np.full(50, -0.4)]),
                   "not a closed loop"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_TRACKS))
def test_hostile_track_files_are_clear_errors_naming_the_file(tmp_path, case):
    from multirace.sim.tracks import TrackError

    make, words = HOSTILE_TRACKS[case]
    path = tmp_path / f"{case}.npy"
    np.save(path, make())
    start = time.monotonic()
    with pytest.raises(TrackError, match=words) as err:
        multirace.parallel_env(track=str(path), num_cars=1)
    assert str(path) in str(err.value)
    assert time.monotonic() - start < 30  # no quadratic check, no giant texture


@pytest.mark.parametrize("case", ["fifo", "folder", "huge"])
def test_special_track_files_are_refused_unread(tmp_path, case):
    from multirace.sim.tracks import TrackError

    path = tmp_path / "t.npy"
    if case == "fifo":
        os.mkfifo(path)
    elif case == "folder":
        path.mkdir()
    else:
        with open(path, "wb") as handle:  # sparse: 1 GB without writing it
            handle.truncate(2**30)
    with pytest.raises(TrackError, match="not a regular file|over the 16 MB limit"):
        multirace.parallel_env(track=str(path), num_cars=1)


def test_eight_cars_on_a_short_loop_is_a_clear_error():
    from multirace.sim.tracks import Track, TrackError

    small = Track(_ring(radius=0.38, half_width=0.3), source="small.npy")
    with pytest.raises(TrackError, match="8 cars need a start grid"):
        multirace.parallel_env(track=small, num_cars=8)


# ------------------------------------------------------------------ more reward functions, action spaces, outputs
def test_a_reward_function_that_swallows_its_timeout_is_still_an_error(tmp_path):
    env = _env_with(tmp_path, "def reward_function(params):\n    try:\n        while True:\n            pass\n"
                              "    except BaseException:\n        return 1.0\n", "swallow.py")
    env.reset(seed=0)
    with pytest.raises(RewardFunctionError, match="swallow.py did not return within"):
        env.step({"car_0": 0})


def test_a_fifo_action_space_file_is_refused_unread(tmp_path):
    os.mkfifo(tmp_path / "model_metadata.json")
    with pytest.raises(ActionSpaceError, match="not a regular file"):
        load_action_space(tmp_path / "model_metadata.json")


@pytest.mark.parametrize("option, value, words", [("--json", ".", "is a folder"),
                                                   ("--replay", "file/race.rrd", "is a file, not a folder"),
                                                   ("--video", "file/sub/race.mp4", "is a file, not a folder"),
                                                   ("--simtrace", "file/deeper/t.csv", "is a file, not a folder")])
def test_unusable_output_paths_are_refused_before_the_race(tmp_path, monkeypatch, capsys, option, value, words):
    from multirace.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("a file, not a folder")
    assert main(["race", "bot:follow@1.0", "--max-steps", "5", option, value]) == 2
    out, err = capsys.readouterr()
    assert words in err and option in err and "time_trial" not in out  # no race ran


def test_a_reward_callable_that_keeps_catching_its_timeout_ends_the_process_with_a_message():
    # a Python callable runs in-process under SIGALRM (a reward FILE runs in its own process: test_reward_process)
    code = ("import multirace\nfrom multirace.environment import rewards\n"
            "rewards.CALL_TIME_LIMIT, rewards.GIVE_UP_AFTER = 0.2, 0.5\n"
            "def stubborn(params):\n    while True:\n        try:\n            while True:\n"
            "                pass\n        except BaseException:\n            pass\n"
            "env = multirace.parallel_env(num_cars=1, reward_function=stubborn, max_steps=5)\n"
            "env.reset(seed=0)\nenv.step({'car_0': 0})\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 124 and "ignored its 0.2 s time limit" in done.stderr, done.stderr[-2000:]


def test_a_reward_file_that_keeps_catching_its_timeout_is_killed_with_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr("multirace.environment.rewards.CALL_TIME_LIMIT", 0.2)
    env = _env_with(tmp_path, "def reward_function(params):\n    while True:\n        try:\n            while True:\n"
                              "                pass\n        except BaseException:\n            pass\n", "stubborn.py")
    env.reset(seed=0)
    with pytest.raises(RewardFunctionError, match="stubborn.py did not return within 0.2 s at step 1"):
        env.step({"car_0": 0})


def test_integer_index_scalars_and_one_element_arrays_drive():
    env = multirace.parallel_env(num_cars=2)
    env.reset(seed=0)
    _, _, _, _, infos = env.step({"car_0": np.int64(7), "car_1": np.array([7])})
    assert env.actions.command(np.array([7])) == env.actions.command(np.int64(7)) == (0.0, 1.0)
    assert infos["car_0"]["speed"] > 0 and infos["car_1"]["speed"] > 0


# ------------------------------------------------------------------ CLI inputs that are not what they claim
@pytest.mark.parametrize("argv, words", [
    (["replay", "{garbage}", "--summary"], "not a rerun replay"),
    (["plot", "/etc/passwd"], "not a DeepRacer sim-trace CSV"),
    (["replay", "{missing}", "--summary"], "no such file"),
])
def test_files_that_are_not_what_the_command_reads_are_one_line_errors(tmp_path, capsys, argv, words):
    from multirace.cli import main

    (tmp_path / "garbage.rrd").write_bytes(b"garbage\n" * 10)
    argv = [a.format(garbage=tmp_path / "garbage.rrd", missing=tmp_path / "missing.rrd") for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_laps_given_as_text_are_refused():
    with pytest.raises(ValueError, match="laps"):
        multirace.parallel_env(num_cars=1, laps="2")
