"""Hostile and careless input to a league: damaged stores, concurrent and killed runs, names as markup, bad
definitions, a file swapped during submit, agent files that break the loader. Real SQLite, real subprocesses."""
from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time

import pytest

from multirace.cli import main
from multirace.environment.actions import load_action_space
from multirace.league.config import LeagueError, load_config
from multirace.league.runner import RUN_LOCK, run_league
from multirace.league.schedule import sync_schedule
from multirace.league.store import connect
from multirace.league.submissions import init_league, submit
from multirace.league.table import COLUMNS, compute_table, rating_plot_png, to_csv, to_html, to_markdown
from multirace.racing.agentfile import make_metadata, save_agent
from multirace.racing.nets import TINY, build_net

SPACE = load_action_space(None)
TIMEOUT = 300  # seconds any subprocess may take before the test fails (a hang, not a slow machine)

LEAGUE = """
[league]
name = "hostile"
seeds = [1]
bots = ["bot:follow@1.5", "bot:lanes@1.0"]
replays = false

[[tracks]]
name = "reinvent_base"
directions = ["forward"]

[time_trial]
format = "reset_rule"
laps = 1
max_steps = 40

[head_to_head]
cars = 2
laps = 1
max_steps = 40
"""


def _agent(path, name="ok"):
    return save_agent(path, build_net(TINY, (120, 160, 1), SPACE), make_metadata(SPACE, TINY, name))


def _league(tmp_path, toml=LEAGUE, name="lg"):
    template = tmp_path / f"{name}.toml"
    template.write_text(toml)
    return init_league(tmp_path / name, template)


def _cli(*argv):
    """`multirace ...` in a subprocess: (exit code, stdout, stderr)."""
    done = subprocess.run([sys.executable, "-m", "multirace.cli", *map(str, argv)], capture_output=True, text=True,
                          timeout=TIMEOUT)
    return done.returncode, done.stdout, done.stderr


def _results(folder):
    with sqlite3.connect(folder / "results.sqlite") as conn:
        return conn.execute("SELECT match_id, status, result FROM results").fetchall()


# ------------------------------------------------------------------ a damaged store is refused, never rebuilt
def _truncate(path, size):
    with open(path, "r+b") as handle:
        handle.truncate(size)


DAMAGE = {
    "truncated_to_zero": (lambda f: _truncate(f / "results.sqlite", 0), "empty"),
    "deleted_with_submissions": (lambda f: (f / "results.sqlite").unlink(), "missing"),
    "half_truncated": (lambda f: _truncate(f / "results.sqlite", (f / "results.sqlite").stat().st_size // 2),
                       "damaged|not a multirace league store"),
    "garbage_header": (lambda f: (f / "results.sqlite").write_bytes(
        os.urandom(100) + (f / "results.sqlite").read_bytes()[100:]), "damaged"),
    "submission_deleted": (lambda f: next((f / "submissions").glob("*.pt")).unlink(), "missing from submissions"),
    "stray_submission": (lambda f: (f / "submissions" / ("0" * 64 + ".pt")).write_bytes(b"x"),
                         "does not know"),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_every_command_refuses_a_damaged_league_and_says_how_to_recover(tmp_path, capsys, case):
    folder = _league(tmp_path)
    submit(folder, _agent(tmp_path / "a.pt"), "a", validate=False)
    conn = connect(folder)
    sync_schedule(folder, load_config(folder), conn)  # the store holds a schedule: several pages
    conn.close()  # the last connection checkpoints the WAL into the file
    damage, words = DAMAGE[case]
    damage(folder)
    def listing():  # the run lock and SQLite's own -wal and -shm side files aside
        return sorted(p.name for p in folder.iterdir() if p.name != RUN_LOCK and not p.name.endswith(("-wal", "-shm")))

    before = listing()
    for argv in (["league", "run", folder, "--workers", "1", "--quiet"], ["league", "table", folder],
                 ["league", "submit", folder, _agent(tmp_path / "b.pt", "b"), "--name", "b"]):
        code = main([str(a) for a in argv])
        err = capsys.readouterr().err
        assert code != 0, argv
        assert re.search(words, err), err
        assert "league init" in err and "Traceback" not in err  # the way to recover, no sqlite3 traceback
    assert listing() == before  # nothing recreated or written


# ------------------------------------------------------------------ one runner at a time; a killed one leaves no lock
def test_a_second_run_is_refused_while_one_runs_and_a_killed_run_leaves_no_lock(tmp_path):
    folder = _league(tmp_path)
    first = subprocess.Popen([sys.executable, "-m", "multirace.cli", "league", "run", str(folder), "--workers", "1",
                              "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
    try:
        lock = folder / RUN_LOCK
        deadline = time.monotonic() + TIMEOUT
        while not (lock.exists() and lock.read_text() == f"pid {first.pid}"):
            assert first.poll() is None and time.monotonic() < deadline, "the first run never took the lock"
            time.sleep(0.05)
        os.kill(first.pid, signal.SIGSTOP)  # holds the lock for as long as this test needs
        code, out, err = _cli("league", "run", folder, "--workers", "1", "--quiet")
        assert code != 0 and "another `multirace league run`" in err and f"pid {first.pid}" in err, err
        assert "Traceback" not in err
        os.killpg(first.pid, signal.SIGKILL)  # the run and its workers, mid-league
        first.wait(timeout=TIMEOUT)
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
            first.wait()
    code, out, err = _cli("league", "run", folder, "--workers", "1", "--quiet")
    assert code == 0, err  # the kernel released the killed run's lock
    conn = connect(folder)
    try:
        scheduled = {row[0] for row in conn.execute("SELECT match_id FROM schedule")}
        attempts = {row[0] for row in conn.execute("SELECT attempts FROM schedule")}
    finally:
        conn.close()
    results = _results(folder)
    assert len(results) == len(scheduled) == 3  # 2 time trials and 1 heat: each recorded once
    assert {r[0] for r in results} == scheduled and {r[1] for r in results} == {"ok"} and attempts == {0}


# ------------------------------------------------------------------ names are data, never markup
@pytest.mark.parametrize("name", ["=HYPERLINK(\"http://x\")", "+1", "@cmd", "-2", "a|b", "line\nbreak",
                                  "[bold]x[/bold]", "$\\frac{$", "<b>x</b>", "\x1b[31mred", "x" * 65, "", " a",
                                  "a ", "bot:follow@1.0"])
def test_submit_refuses_names_that_are_not_plain_text(tmp_path, capsys, name):
    folder = _league(tmp_path)
    code = main(["league", "submit", str(folder), str(_agent(tmp_path / "a.pt")), "--name", name])
    assert code != 0 and "valid entrant name" in capsys.readouterr().err
    assert not list((folder / "submissions").iterdir())


@pytest.mark.parametrize("name", ["two\nlines", "bell\x07", "\x1b]8;;http://x\x07link", "x" * 101, "   "])
def test_init_refuses_a_league_name_that_is_not_one_line_of_text(tmp_path, name):
    with pytest.raises(LeagueError, match="league.name"):
        _league(tmp_path, LEAGUE.replace('name = "hostile"', f"name = {json.dumps(name)}"))
    assert not (tmp_path / "lg").exists()


HOSTILE = "$\\frac{$ | =HYPERLINK(\"http://x\") <script>x</script>\n[/bold] @SUM(1)"


def test_names_and_reasons_are_shown_as_written_in_every_table_format(tmp_path):
    """Defence in depth: even names the validation would refuse (a store from elsewhere, a forfeit reason
    from an agent's exception) render as text in Markdown, CSV, HTML and the rating plot."""
    folder = _league(tmp_path)
    table = compute_table(folder)
    table["league"] = HOSTILE
    for i, standing in enumerate(table["standings"]):
        standing["entrant"] = "=+-@"[i % 4] + HOSTILE + standing["entrant"]
        standing["forfeit_reasons"] = [HOSTILE]
    table["time_trials"] = [{"rank": 1, "entrant": HOSTILE, "tt_best_lap": 1.0, "tt_completion": 1.0,
                             "tt_avg_lap": 1.0}]
    table["rating_history"] = [{"round": 0, "ordinal": {s["entrant"]: 1.0 for s in table["standings"]}}]

    md = to_markdown(table)
    for line in md.splitlines():
        if line.startswith("|"):  # every row keeps its cells: a name's | and newline break nothing
            assert len(re.findall(r"(?<!\\)\|", line)) in (len(COLUMNS) + 1, 6), line
    assert "<script>" not in md and "\\|" in md and "\n[/bold]" not in md

    for row in list(csv.reader(to_csv(table).splitlines()))[1:]:
        assert not row[COLUMNS.index("entrant")].startswith(("=", "+", "-", "@")), row  # no formula

    page = to_html(table)
    body = page.split("<body>", 1)[1]
    assert "<script>" not in body and "&lt;script&gt;" in body

    png = rating_plot_png(table)  # no mathtext: a `$` in a name does not break the plot
    assert png.startswith(b"\x89PNG")


# ------------------------------------------------------------------ definitions refused up front, at init and at run
@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace("seeds = [1]", "seeds = [-1]"), "league.seeds"),
    (lambda t: t.replace('name = "reinvent_base"', 'name = "no_such_track"'), "unusable track"),
    (lambda t: t.replace('bots = ["bot:follow@1.5", "bot:lanes@1.0"]', 'bots = ["bot:fly@9"]'), "league.bots"),
    (lambda t: t.replace("laps = 1", "laps = 0", 1), "time_trial.laps"),
], ids=["negative_seed", "unknown_track", "unknown_bot", "zero_laps"])
def test_a_bad_definition_is_refused_at_init_and_at_run(tmp_path, edit, words):
    bad = tmp_path / "bad.toml"
    bad.write_text(edit(LEAGUE))
    code, _, err = _cli("league", "init", tmp_path / "new", "--from", bad)
    assert code != 0 and words in err and "Traceback" not in err, err
    assert not (tmp_path / "new").exists()

    folder = _league(tmp_path)
    (folder / "league.toml").write_text(edit(LEAGUE))  # edited after init
    code, _, err = _cli("league", "run", folder, "--workers", "1", "--quiet")
    assert code != 0 and words in err and "Traceback" not in err, err
    assert not _results(folder)  # refused before a single match


def test_init_refuses_a_missing_template_and_an_existing_league(tmp_path, capsys):
    assert main(["league", "init", str(tmp_path / "new"), "--from", str(tmp_path / "typo.toml")]) != 0
    assert "typo.toml: no such league definition" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()  # no league silently made from the default
    folder = _league(tmp_path)
    assert main(["league", "init", str(folder)]) != 0
    assert "already exists" in capsys.readouterr().err
    (folder / "league.toml").unlink()  # a league's results without its definition are not adopted silently
    assert main(["league", "init", str(folder)]) != 0
    assert "results.sqlite: already exists" in capsys.readouterr().err
    (tmp_path / "binary.toml").write_bytes(b"\xff\xfe\x00garbage")
    assert main(["league", "init", str(tmp_path / "other"), "--from", str(tmp_path / "binary.toml")]) != 0
    assert "binary.toml: unreadable" in capsys.readouterr().err


# ------------------------------------------------------------------ submit stores exactly the bytes it validated
def _swap_when_copied(folder, source, replacement: bytes):
    """A thread that replaces `source` with `replacement` as soon as submit has made its copy."""
    def run():
        deadline = time.monotonic() + TIMEOUT
        while time.monotonic() < deadline and not list((folder / "submissions").glob(".*.tmp")):
            time.sleep(0.005)
        source.write_bytes(replacement)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_file_swapped_during_validation_changes_nothing(tmp_path):
    folder = _league(tmp_path)
    good = _agent(tmp_path / "good.pt").read_bytes()
    source = tmp_path / "entry.pt"

    source.write_bytes(b"not an agent file" * 100)  # a bad file, swapped for a good one once copied
    swap = _swap_when_copied(folder, source, good)
    with pytest.raises(LeagueError, match="refused"):
        submit(folder, source, "swapped")
    swap.join()
    assert not list((folder / "submissions").iterdir())

    source.write_bytes(good)  # a good file, swapped for garbage once copied: the validated bytes are stored
    swap = _swap_when_copied(folder, source, b"garbage" * 100)
    row = submit(folder, source, "kept")
    swap.join()
    assert open(row["file"], "rb").read() == good and row["sha256"] == hashlib.sha256(good).hexdigest()
    assert [p.name for p in (folder / "submissions").iterdir()] == [f"{row['sha256']}.pt"]


def test_submit_refuses_special_files_without_blocking(tmp_path, capsys):
    folder = _league(tmp_path)
    fifo = tmp_path / "fifo.pt"
    os.mkfifo(fifo)
    for path in (fifo, "/dev/zero", tmp_path):
        assert main(["league", "submit", str(folder), str(path), "--name", "x"]) != 0
        assert "not a regular file" in capsys.readouterr().err


# ------------------------------------------------------------------ a file that breaks the loader forfeits
def _unloadable(kind, path):
    import torch

    state = build_net(TINY, (120, 160, 1), SPACE).state_dict()
    metadata = make_metadata(SPACE, TINY, kind)
    if kind == "infinite_image":
        metadata["image"]["height"] = float("inf")
        text = json.dumps(metadata)
    elif kind == "deep_metadata":
        text = "[" * 200_000
    else:  # a tensor with an instance attribute
        tensor = state["head.weight"].clone()
        tensor.extra = 1
        state["head.weight"] = tensor
        text = json.dumps(metadata)
    torch.save({"format": "multirace-agent", "format_version": 1, "metadata": text, "state_dict": state}, path)
    return path


def test_agents_that_break_the_loader_forfeit_and_the_heat_counts(tmp_path):
    toml = LEAGUE.replace('bots = ["bot:follow@1.5", "bot:lanes@1.0"]', 'bots = ["bot:follow@1.5"]') \
        .replace("[time_trial]", "[time_trial]\nenabled = false").replace("cars = 2", "cars = 4")
    folder = _league(tmp_path, toml)
    kinds = ("infinite_image", "deep_metadata", "tensor_attribute")
    for kind in kinds:  # past submission's validation, as a file stored by an older version could be
        submit(folder, _unloadable(kind, tmp_path / f"{kind}.pt"), kind, validate=False)
    stats = run_league(folder, workers=1, progress=False)
    assert stats["ran"] == 1 and stats["failed"] == 0  # one heat of four, not "failed after 3 attempts"
    (_, status, result), = _results(folder)
    cars = {car["name"]: car for car in json.loads(result)["cars"]}
    assert cars["bot:follow@1.5"]["status"] != "forfeit"
    for kind in kinds:
        assert cars[kind]["status"] == "forfeit" and cars[kind]["reason"], cars[kind]
    table = compute_table(folder)
    assert table["standings"][0]["entrant"] == "bot:follow@1.5" and not table["failed"]


def test_a_store_that_fails_mid_run_is_a_clear_error_and_the_next_run_resumes(tmp_path, capsys):
    folder = _league(tmp_path, LEAGUE.replace("[head_to_head]", "[head_to_head]\nenabled = false"))
    with sqlite3.connect(folder / "results.sqlite") as conn:  # every result write now fails, as a full disk would
        conn.execute("CREATE TRIGGER no_space BEFORE INSERT ON results BEGIN SELECT RAISE(ABORT, 'disk full'); END")
    assert main(["league", "run", str(folder), "--workers", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "results.sqlite" in err and "disk full" in err and "Traceback" not in err, err
    with sqlite3.connect(folder / "results.sqlite") as conn:
        conn.execute("DROP TRIGGER no_space")
        assert conn.execute("SELECT COUNT(*) FROM results").fetchone()[0] == 0  # nothing half written
    assert main(["league", "run", str(folder), "--workers", "1", "--quiet"]) == 0
    assert {status for _, status, _ in _results(folder)} == {"ok"} and len(_results(folder)) == 2
