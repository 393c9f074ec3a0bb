"""The `multirace race` command: a real subprocess, its JSON record, and clear errors."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from multirace.cli import main

RESULT_KEYS = {"name", "file_sha256", "position", "laps", "lap_times", "best_lap", "total_time", "resets",
               "penalties", "collisions", "status", "reason"}


def test_race_command_prints_a_table_and_writes_the_record(tmp_path):
    out = tmp_path / "result.json"
    run = subprocess.run([sys.executable, "-m", "multirace.cli", "race", "agents/dagger_small.pt", "bot:follow@1.5",
                          "--laps", "1", "--seed", "3", "--json", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "dagger_small" in run.stdout and "bot:follow@1.5" in run.stdout and "finished" in run.stdout
    record = json.loads(out.read_text())
    assert record["format"] == "head_to_head" and record["track"] == "reinvent_base" and record["seed"] == 3
    assert [car["position"] for car in record["cars"]] == [1, 2]
    for car in record["cars"]:
        assert RESULT_KEYS <= set(car)
        assert car["status"] == "finished" and car["laps"] == 1
        assert car["total_time"] == pytest.approx(sum(car["lap_times"]))
    agent = next(car for car in record["cars"] if car["name"] == "dagger_small")
    assert len(agent["file_sha256"]) == 64


@pytest.mark.parametrize("args,message", [
    (["race", "missing.pt"], "missing.pt"),
    (["race", "bot:follow@1", "--track", "nowhere"], "track 'nowhere'"),
    (["race", "bot:follow@1", "--laps", "0"], "laps"),
    (["race", "bot:warp@1"], "bot:KIND@SPEED"),
    (["race", "bot:follow@1", "--obstacles", "9"], "obstacles"),
    (["race", "bot:follow@1", "--video", "race.avi"], "MP4 only"),
])
def test_bad_arguments_get_a_clear_error_and_exit_2(args, message, capsys):
    assert main(args) == 2
    assert message in capsys.readouterr().err


def test_a_shipped_agent_by_name_is_not_shadowed_by_a_folder_of_that_name(tmp_path, monkeypatch):
    from multirace.resources import resolve_agent_path
    from multirace.resources import agents_dir

    monkeypatch.chdir(tmp_path)
    (tmp_path / "racer").mkdir()  # e.g. a training run's output folder
    assert resolve_agent_path("racer") == agents_dir() / "racer.pt"
    assert resolve_agent_path("mine") == Path("mine")  # no shipped agent of that name: the path as given


@pytest.mark.parametrize("argv,field", [
    (["evaluate", "racer", "--quick"], "agents"),
    (["explain", "racer"], "agent"),
    (["agent", "inspect", "racer"], "file"),
    (["agent", "export", "racer", "--out", "m.tar.gz"], "file"),
    (["league", "submit", "lg", "racer", "--name", "r"], "file"),
    (["imitate", "--out", "a.pt", "--init", "racer"], "init"),
    (["train", "--out", "a.pt", "--init", "racer"], "init"),
])
def test_every_command_that_takes_an_agent_file_takes_a_shipped_name(argv, field, tmp_path, monkeypatch):
    from multirace.cli import build_parser
    from multirace.resources import agents_dir

    monkeypatch.chdir(tmp_path)  # a folder with no agents/ in it, as a user's
    value = getattr(build_parser().parse_args(argv), field)
    assert (value[0] if isinstance(value, list) else value) == str(agents_dir() / "racer.pt")


def test_agent_inspect_and_agent_list_work_by_name_from_any_folder(tmp_path):
    from multirace.resources import agents_dir, list_agents

    inspect = subprocess.run([sys.executable, "-m", "multirace.cli", "agent", "inspect", "dagger_fast", "--json"],
                             capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert inspect.returncode == 0, inspect.stderr
    info = json.loads(inspect.stdout)
    assert info["valid"] and info["name"] == "dagger_fast"
    listed = subprocess.run([sys.executable, "-m", "multirace.cli", "agent", "list", "--json"],
                            capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    rows = json.loads(listed.stdout)
    assert [row["name"] for row in rows] == list_agents()
    for row in rows:
        assert Path(row["path"]) == agents_dir() / f"{row['name']}.pt" and row["parameters"] > 100_000
        assert "m/s" in row["actions"] and row["network"]
        assert "clean" in row["held_out"] and "per lap" in row["traffic"]  # agents/README's "At a glance" figures
    made_by = {row["name"]: row["made_by"] for row in rows}  # the method, and whom it learnt from
    assert made_by["racer"] == "dagger bot:racingline@0.9, 25 min"
    assert made_by["racer_h2h_lidar"].startswith("dagger RL teacher ") and made_by["racer_h2h_lidar"].endswith(" min")
    assert made_by["racer_h2h"] == "weight blend (WiSE-FT), 0.75 cg7 + 0.25 cg1"  # of two RL-teacher students


def test_race_help_names_every_bot_kind(capsys):
    from multirace.environment.bots import BOT_KINDS

    assert main(["race", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert all(kind in text.split("KIND:")[1] for kind in BOT_KINDS), text


def test_a_reader_that_stops_early_ends_a_printing_command_quietly():
    # the command's output goes to a pipe nobody reads any more (`multirace agent inspect racer --json | head -0`)
    code = ("import os, sys\nread, write = os.pipe()\nos.close(read)\n"
            "sys.stdout = open(write, 'w', buffering=1)  # line by line: the first print meets the closed pipe\n"
            "from multirace.cli import main\nsys.exit(main(['agent', 'inspect', 'racer', '--json']))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "Traceback" not in done.stderr and "Error" not in done.stderr, done.stderr
