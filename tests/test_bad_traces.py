"""`multirace plot` and `multirace replay` on files that are not what they claim, or far larger than usual:
each is a one-line error naming the file, or a result in bounded time and memory (hostile files made here)."""
import os
import subprocess
import sys

import pytest

from multirace.cli import main
from multirace.recording.simtrace import SIMTRACE_COLUMNS

HEADER = ",".join(SIMTRACE_COLUMNS) + "\n"


def _row(episode=0, step=1, x=1.0, y=2.0, throttle=1.0, reward=1.0, status="in_progress") -> str:
    return (f"{episode},{step},{x},{y},0.0,0.0,{throttle},3,{reward},False,True,1.0,1,17.71,0.07,{status},0.0\n")


def _one_line_error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("body, words", [
    (HEADER + _row() + "0,2," + "9" * 200_000 + "\n", "not a readable CSV (field larger than field limit"),
    (HEADER.replace("throttle", "gas") + _row(), "no column throttle"),
    (HEADER + _row() + _row(x="inf"), "line 3: column X is 'inf', not a finite number"),
    (HEADER + _row(reward="-inf"), "line 2: column reward is '-inf'"),
    (HEADER + _row(episode="9" * 5000), "column episode is"),
    (HEADER + "0," * (1 << 20), "line 2: longer than 1048576 characters"),
])
def test_a_bad_sim_trace_is_a_one_line_error_naming_the_file(tmp_path, capsys, body, words):
    path = tmp_path / "trace.csv"
    path.write_text(body)
    err = _one_line_error(capsys, ["plot", str(path)])
    assert str(path) in err and words in err, err
    assert not (tmp_path / "trace.png").exists()


@pytest.mark.parametrize("command", ["plot", "replay"])
@pytest.mark.parametrize("kind", ["fifo", "dev_zero"])
def test_fifos_and_devices_are_refused_unopened(tmp_path, command, kind):
    path = "/dev/zero"
    if kind == "fifo":
        path = str(tmp_path / "trace")
        os.mkfifo(path)
    argv = [command, path] + (["--summary"] if command == "replay" else [])
    done = subprocess.run([sys.executable, "-m", "multirace.cli", *argv], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "not a regular file" in done.stderr and path in done.stderr, done.stderr[-2000:]


def test_thirty_thousand_episodes_plot_in_a_few_drawing_calls(tmp_path, capsys):
    path = tmp_path / "many.csv"
    with open(path, "w") as f:
        f.write(HEADER)
        for episode in range(30_000):
            f.write(_row(episode, 1, x=episode % 7, y=episode % 5, status="off_track" if episode % 9 == 0 else "x"))
    assert main(["plot", str(path)]) == 0
    assert (tmp_path / "many.png").stat().st_size > 0 and "many.png" in capsys.readouterr().out


def _bounded(code: str, memory_bytes: int, timeout: int):
    """Run `code` in a Python whose address space is capped (a probe that allocated GBs fails instead)."""
    limit = f"import resource\nresource.setrlimit(resource.RLIMIT_AS, ({memory_bytes}, {memory_bytes}))\n"
    return subprocess.run([sys.executable, "-c", limit + code], capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_two_million_rows_are_streamed_in_bounded_memory(tmp_path):
    path = tmp_path / "long.csv"
    with open(path, "w") as f:
        f.write(HEADER)
        rows = "".join(_row(k % 4, k, x=k % 100 / 10, y=k % 37 / 10) for k in range(10_000))  # long jumps, too
        for _ in range(200):
            f.write(rows)
    done = _bounded(f"import sys\nfrom multirace.cli import main\nsys.exit(main(['plot', {str(path)!r}]))\n",
                    3 << 30, timeout=1200)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "long.png").stat().st_size > 0


def _rrd_with_info(path, text: str) -> None:
    import rerun as rr

    rec = rr.RecordingStream("multirace")
    rec.save(str(path))
    rec.log("race/info", rr.TextDocument(text), static=True)
    rec.flush()
    rec.disconnect()


@pytest.mark.parametrize("text", ['[1, 2, 3]', '{"track": "t", "format": "f", "laps": 1, "reverse": false}',
                                  '{"track": "t", "format": "f", "laps": 1, "reverse": false, "cars": [7]}',
                                  '{"track": "t", "format": "f", "laps": "x", "reverse": false, "cars": []}',
                                  "[" * 100_000 + "]" * 100_000, "{not json"])
def test_a_replay_whose_race_description_is_not_ours_is_a_one_line_error(tmp_path, capsys, text):
    path = tmp_path / "race.rrd"
    _rrd_with_info(path, text)
    err = _one_line_error(capsys, ["replay", str(path), "--summary"])
    assert str(path) in err and "race/info" in err, err


def test_a_sim_trace_over_the_row_limit_is_refused_not_read_whole(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("multirace.recording.simtrace.MAX_COLUMN_ROWS", 1000)
    path = tmp_path / "endless.csv"
    path.write_text(HEADER + _row() * 1001)
    err = _one_line_error(capsys, ["plot", str(path)])
    assert str(path) in err and "over 1,000 rows" in err, err
