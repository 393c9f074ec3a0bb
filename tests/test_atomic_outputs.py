"""Written outputs are atomic: on a full disk every command fails in one line naming the file, the previous
file of that name survives byte for byte, and nothing half-written is left beside it."""
import os
import subprocess
import sys
import uuid

import pytest

from multirace.atomic import AtomicOutput, OutputError, write_bytes

TMPFS_BYTES = 2 * 2**20


@pytest.fixture
def small_disk(tmp_path):
    """A folder on its own 2 MB filesystem (a tmpfs: needs root and a mount command), unmounted afterwards."""
    folder = tmp_path / "disk"
    folder.mkdir()
    if os.geteuid() != 0:
        pytest.skip("a full filesystem needs a 2 MB tmpfs, and mounting one needs root")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_BYTES}", "tmpfs", str(folder)],
                          capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({made.stderr.strip()})")
    yield folder
    subprocess.run(["umount", str(folder)], check=True)


def fill(folder, leave: int = 0):
    """Fill `folder`'s filesystem until at most `leave` bytes are free."""
    stats = os.statvfs(folder)
    free = stats.f_bavail * stats.f_frsize
    with open(folder / f"filler-{uuid.uuid4().hex[:6]}", "wb") as f:
        try:
            f.write(b"\0" * max(free - leave, 0))
            f.flush()
        except OSError:
            pass


def leftovers(folder, keep):
    """Files in `folder` besides those in `keep` and the fillers."""
    return sorted(p.name for p in folder.iterdir() if p.name not in keep and not p.name.startswith("filler-"))


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "multirace.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def assert_one_line_error(done, *words):
    assert done.returncode != 0, done.stdout
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    for word in words:
        assert str(word) in lines[0], lines[0]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(small_disk):
    target = small_disk / "data.bin"
    write_bytes(target, b"old")
    fill(small_disk)
    with pytest.raises(OutputError, match="data.bin: not written"):
        write_bytes(target, b"x" * 100_000)
    assert target.read_bytes() == b"old" and leftovers(small_disk, {"data.bin"}) == []


def test_an_error_inside_the_block_keeps_the_target_and_removes_the_temporary(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(ZeroDivisionError):
        with AtomicOutput(target) as tmp:
            tmp.write_text("half")
            1 / 0
    assert target.read_text() == "old" and leftovers(tmp_path, {"out.txt"}) == []


def test_a_replaced_file_keeps_its_permissions(tmp_path):
    target = tmp_path / "private.json"
    target.write_text("old")
    target.chmod(0o600)
    write_bytes(target, b"new")
    assert target.read_bytes() == b"new" and target.stat().st_mode & 0o777 == 0o600


def test_export_onto_a_full_disk_keeps_the_previous_archive(small_disk):
    archive = small_disk / "model.tar.gz"
    assert run_cli("agent", "export", "dagger_small", "--out", archive).returncode == 0
    before = archive.read_bytes()
    fill(small_disk, leave=200_000)  # less than a second archive needs
    done = run_cli("agent", "export", "dagger_small", "--out", archive)
    assert_one_line_error(done, archive, "not written")
    assert archive.read_bytes() == before and leftovers(small_disk, {"model.tar.gz"}) == []


def test_import_onto_a_full_disk_leaves_no_partial_agent_file(small_disk, tmp_path):
    archive = tmp_path / "model.tar.gz"
    assert run_cli("agent", "export", "dagger_small", "--out", archive).returncode == 0
    agent = small_disk / "imported.pt"
    agent.write_bytes(b"previous agent")
    fill(small_disk, leave=100_000)
    done = run_cli("agent", "import", archive, "--out", agent)
    assert_one_line_error(done, agent)
    assert agent.read_bytes() == b"previous agent" and leftovers(small_disk, {"imported.pt"}) == []


@pytest.mark.parametrize("option, name", [("--replay", "race.rrd"), ("--video", "race.mp4"),
                                          ("--simtrace", "race.csv"), ("--json", "race.json")])
@pytest.mark.parametrize("leave", [0, 60_000])  # full before the race, or filling up during it
def test_race_outputs_on_a_full_disk_fail_in_one_line_and_keep_the_old_file(small_disk, option, name, leave):
    target = small_disk / name
    target.write_bytes(b"the previous good file")
    fill(small_disk, leave=leave)
    done = run_cli("race", "bot:follow@1.0", "--laps", "1", "--max-steps", "450", option, target)
    if done.returncode == 0:  # it fitted: then it is the new file, whole
        assert target.read_bytes() != b"the previous good file" and target.stat().st_size > 100
        assert leftovers(small_disk, {name}) == []
        return
    assert_one_line_error(done, target, "not written")
    assert target.read_bytes() == b"the previous good file" and leftovers(small_disk, {name}) == []


def test_a_league_table_onto_a_full_disk_keeps_the_old_table(small_disk, tmp_path):
    from helpers import small_league

    toml = tmp_path / "small.toml"
    toml.write_text(small_league())
    folder = tmp_path / "lg"
    assert run_cli("league", "init", folder, "--from", toml).returncode == 0
    table = small_disk / "table.html"
    table.write_text("old table")
    fill(small_disk)
    done = run_cli("league", "table", folder, "--format", "html", "--out", table)
    assert_one_line_error(done, table)
    assert table.read_text() == "old table" and leftovers(small_disk, {"table.html"}) == []
