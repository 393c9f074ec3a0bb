"""A league store that trusts nothing it has not checked: stored submissions are verified against the sha256
they are named by, a read-only league is reported as read-only, and `league table` writes only what it is
asked to, where it is asked to."""
import hashlib
import os
import subprocess
import sys

import pytest

from helpers import small_league
from multirace.environment.actions import load_action_space
from multirace.league.config import LeagueError
from multirace.league.submissions import init_league, submit
from multirace.racing.agentfile import make_metadata, save_agent
from multirace.racing.nets import TINY, build_net

SPACE = load_action_space(None)


def _agent(path, name="ok"):
    return save_agent(path, build_net(TINY, (120, 160, 1), SPACE), make_metadata(SPACE, TINY, name))


@pytest.fixture
def league(tmp_path):
    """A league with one submission, entrant "alice" (not run)."""
    toml = tmp_path / "small.toml"
    toml.write_text(small_league())
    folder = init_league(tmp_path / "lg", toml)
    row = submit(folder, _agent(tmp_path / "a.pt"), "alice", validate=False)
    return folder, row


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "multirace.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def one_line(done) -> str:
    lines = done.stderr.strip().splitlines()
    assert done.returncode != 0 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    return lines[0]


def snapshot(folder):
    """Every file under `folder` with its bytes' sha256."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_swapped_submission_is_refused_naming_the_entrant(league, tmp_path):
    folder, row = league
    stored = folder / "submissions" / f"{row['sha256']}.pt"
    stored.write_bytes(_agent(tmp_path / "other.pt", "impostor").read_bytes())  # valid, but not what was submitted
    for command in (("league", "run", folder, "--quiet"), ("league", "table", folder)):
        line = one_line(run_cli(*command))
        assert "'alice'" in line and "replaced or damaged" in line and stored.name in line


def test_a_match_refuses_a_submission_swapped_after_the_store_was_checked(league, tmp_path):
    from multirace.league.worker import run_match

    folder, row = league
    (folder / row["file"]).write_bytes(b"other bytes")
    spec = {"entrants": [{"name": "alice", "spec": f"submissions/{row['sha256']}.pt", "sha256": row["sha256"],
                          "step_budget": None}],
            "track": "reinvent_base", "reverse": False, "race": "reset_rule", "laps": 1, "seed": 1, "max_steps": 10}
    with pytest.raises(LeagueError, match="entrant 'alice'.*replaced or damaged"):
        run_match(spec, folder, None)


@pytest.fixture
def read_only(league, tmp_path):
    """The league folder made read-only: a read-only bind mount as root (root may write past file modes),
    else file modes."""
    folder, row = league
    if os.geteuid() == 0:
        bind = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True, text=True)
        if bind.returncode != 0:
            pytest.skip(f"cannot make a read-only bind mount here ({bind.stderr.strip()})")
        remount = subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True, text=True)
        if remount.returncode != 0:
            subprocess.run(["umount", str(folder)])
            pytest.skip(f"cannot remount read-only here ({remount.stderr.strip()})")
        yield folder
        subprocess.run(["umount", str(folder)], check=True)
    else:
        paths = [folder, *folder.rglob("*")]
        for p in paths:
            p.chmod(p.stat().st_mode & ~0o222)
        yield folder
        for p in paths:
            p.chmod(p.stat().st_mode | 0o200)


def test_a_read_only_league_is_reported_as_read_only_and_its_table_still_prints(read_only, tmp_path):
    folder = read_only
    before = snapshot(folder)
    for command in (("league", "run", folder, "--quiet"), ("league", "submit", folder, _agent(tmp_path / "b.pt"),
                                                            "--name", "bob")):
        line = one_line(run_cli(*command))
        assert "read-only" in line and "damaged" not in line and "backup" not in line
    table = run_cli("league", "table", folder)
    assert table.returncode == 0, table.stderr
    assert "alice" in table.stdout
    out = tmp_path / "table.html"
    plot = tmp_path / "ratings.png"
    assert run_cli("league", "table", folder, "--format", "html", "--out", out, "--plot", plot).returncode == 0
    assert out.read_text().startswith("<!DOCTYPE html>") and plot.read_bytes()[:4] == b"\x89PNG"
    assert snapshot(folder) == before


def test_league_table_writes_nothing_into_the_league_folder(league):
    folder, _ = league
    before = snapshot(folder)
    done = run_cli("league", "table", folder, "--format", "csv")
    assert done.returncode == 0 and done.stdout.startswith("rank,entrant")
    assert snapshot(folder) == before and not (folder / "ratings.png").exists()
