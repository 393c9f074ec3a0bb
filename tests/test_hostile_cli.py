"""Command-line arguments are checked before any work starts: a bad one is a one-line error that names the
option (or the file), exit code 2, no traceback; run as a user runs them, in a subprocess."""
import os
import subprocess
import sys

import pytest

import multirace
from multirace.resources import agents_dir


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "multirace.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def assert_refused(done, *words):
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, (done.returncode, done.stdout[-500:], done.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr[-2000:]
    for word in words:
        assert word in lines[0], lines[0]
    assert "time_trial on" not in done.stdout and "wrote" not in done.stdout  # nothing ran


@pytest.mark.parametrize("argv, words", [
    (["train", "--minutes", "-1", "--out", "{tmp}/a.pt"], ["--minutes", "-1"]),
    (["train", "--minutes", "nan", "--out", "{tmp}/a.pt"], ["--minutes"]),
    (["train", "--cars", "0", "--out", "{tmp}/a.pt"], ["--cars"]),
    (["train", "--cars", "-3", "--out", "{tmp}/a.pt"], ["--cars"]),
    (["train", "--envs", "0", "--out", "{tmp}/a.pt"], ["--envs"]),
    (["train", "--envs", "two", "--out", "{tmp}/a.pt"], ["--envs", "two"]),
    (["train", "--seed", "-1", "--out", "{tmp}/a.pt"], ["--seed"]),
    (["train", "--set", "gamma=abc", "--out", "{tmp}/a.pt"], ["--set gamma", "number"]),
    (["train", "--set", "epochs=0", "--out", "{tmp}/a.pt"], ["--set epochs"]),
    (["train", "--set", "anneal_lr=yes", "--out", "{tmp}/a.pt"], ["--set anneal_lr"]),
    (["train", "--set", "no_such=1", "--out", "{tmp}/a.pt"], ["--set no_such"]),
    (["train", "--set", 'eval_tracks=["Nowhere_track"]', "--out", "{tmp}/a.pt"], ["--set eval_tracks", "Nowhere_track"]),
    (["train", "--set", 'track_sampling="hardest"', "--out", "{tmp}/a.pt"], ["--set track_sampling"]),
    (["train", "--set", 'eval_randomize="wild"', "--out", "{tmp}/a.pt"], ["--set eval_randomize", "wild"]),
    (["train", "--set", 'update_precision="float16"', "--out", "{tmp}/a.pt"], ["--set update_precision"]),
    (["train", "--cars", "4", "--set", "cars_per_env=8", "--out", "{tmp}/a.pt"], ["--set cars_per_env", "--cars"]),
    (["train", "--set", "seed=3", "--out", "{tmp}/a.pt"], ["--set seed", "--seed"]),
    (["train", "--track", "nowhere", "--out", "{tmp}/a.pt"], ["--track", "nowhere"]),
    (["train", "--network", "NOPE", "--out", "{tmp}/a.pt"], ["--network", "NOPE"]),
    (["train", "--action-space", "{tmp}/missing.json", "--out", "{tmp}/a.pt"], ["--action-space", "missing.json"]),
    (["train", "--init", "{tmp}/missing.pt", "--out", "{tmp}/a.pt"], ["--init", "missing.pt"]),
    (["train", "--reward", "{tmp}/missing.py", "--out", "{tmp}/a.pt"], ["--reward", "missing.py"]),
    (["imitate", "--traffic-share", "2", "--out", "{tmp}/a.pt"], ["--traffic-share"]),
    (["imitate", "--minutes", "-1", "--out", "{tmp}/a.pt"], ["--minutes"]),
    (["imitate", "--max-samples", "0", "--out", "{tmp}/a.pt"], ["--max-samples"]),
    (["imitate", "--speed", "0", "--out", "{tmp}/a.pt"], ["--speed"]),
    (["imitate", "--threads", "0", "--out", "{tmp}/a.pt"], ["--threads"]),
    (["imitate", "--procedural-tracks", "-2", "--out", "{tmp}/a.pt"], ["--procedural-tracks"]),
    (["race", "bot:follow@1.0", "--laps", "0"], ["--laps"]),
    (["race", "bot:follow@1.0", "--seed", "-1"], ["--seed"]),
    (["race", "bot:follow@1.0", "--obstacles", "7"], ["--obstacles"]),
    (["race", "bot:follow@1.0", "--max-steps", "1.5"], ["--max-steps"]),
    (["race", "bot:follow@1.0", "--video", "/proc/race.mp4"], ["--video", "/proc/race.mp4"]),
    (["race", "bot:follow@1.0", "--replay", "/proc/self/race.rrd"], ["--replay", "race.rrd"]),
    (["race", "bot:follow@1.0", "--json", "{tmp}"], ["--json", "is a folder"]),
    (["explain", "racer", "--steps", "0"], ["--steps"]),
    (["explain", "racer", "--scale", "1000"], ["--scale"]),
    (["evaluate", "racer", "--laps", "0"], ["--laps"]),
    (["evaluate", "racer", "--seeds", "-1"], ["--seeds"]),
    (["bench", "--seconds", "0"], ["--seconds"]),
    (["bench", "--replay-seconds", "-5"], ["--replay-seconds"]),
    (["league", "run", "{tmp}", "--workers", "0"], ["--workers"]),
    (["league", "table", "{tmp}", "--out", "/proc/table.md"], ["--out", "/proc/table.md"]),
    (["league", "init", "/proc/league"], ["/proc/league", "cannot create"]),
    (["evaluate", "{agent}", "--tracks", "Oval_track,nowhere"], ["--tracks", "nowhere"]),
    (["imitate", "--traffic", "zoom@1", "--out", "{tmp}/a.pt"], ["--traffic", "zoom@1"]),
    (["plot", "{tmp}/missing.csv"], ["TRACE.csv", "missing.csv", "no such file"]),
    (["replay", "{tmp}/missing.rrd", "--summary"], ["missing.rrd", "no such file"]),
])
def test_a_bad_argument_is_one_line_naming_the_option_before_any_work(tmp_path, argv, words):
    agent = agents_dir() / "dagger_small.pt"
    assert_refused(run_cli(*[a.format(tmp=tmp_path, agent=agent) for a in argv]), *words)


@pytest.mark.skipif(os.geteuid() != 0, reason="a read-only mount needs root (file modes alone do not stop root)")
def test_an_output_on_a_read_only_filesystem_is_refused_before_the_race(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m,ro", "tmpfs", str(folder)]).returncode != 0:
        pytest.skip("cannot mount a read-only tmpfs here")
    try:
        for option, name in (("--video", "race.mp4"), ("--replay", "race.rrd"), ("--json", "out/race.json")):
            assert_refused(run_cli("race", "bot:follow@1.0", option, folder / name), option, "Read-only")
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@pytest.mark.parametrize("kwargs, words", [({"num_cars": "four"}, "num_cars"), ({"num_cars": 2.5}, "num_cars"),
                                           ({"num_cars": 0}, "num_cars")])
def test_bad_env_keywords_name_the_keyword(kwargs, words):
    with pytest.raises(ValueError, match=words):
        multirace.parallel_env(**kwargs)


def test_a_negative_seed_names_the_seed():
    env = multirace.parallel_env(num_cars=1)
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=-1)
