"""How busy the machine is never decides a result: the same league run on an idle and on a loaded CPU
gives the same table (inference cost is judged in the agent's CPU time, not wall-clock time)."""
import json
import subprocess
import sys

import pytest

from multirace.cli import main
from multirace.resources import agents_dir
from helpers import small_league

# 5 ms: over 10x the shipped agent's inference (about 0.4 ms of CPU), well under what a descheduled step
# takes in wall-clock time on a loaded CPU
LEAGUE = small_league("load test", step_budget=0.005)


def run_league(folder, toml) -> list:
    assert main(["league", "init", str(folder), "--from", str(toml)]) == 0
    assert main(["league", "submit", str(folder), str(agents_dir() / "dagger_small.pt"), "--name", "small"]) == 0
    assert main(["league", "run", str(folder), "--workers", "2", "--quiet"]) == 0
    out = folder / "table.json"
    assert main(["league", "table", str(folder), "--format", "json", "--out", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.mark.slow
def test_the_same_league_gives_the_same_table_on_an_idle_and_a_loaded_machine(tmp_path):
    toml = tmp_path / "league.toml"
    toml.write_text(LEAGUE)
    idle = run_league(tmp_path / "idle", toml)
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(8)]  # 4 per core
    try:
        loaded = run_league(tmp_path / "loaded", toml)
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    for table in (idle, loaded):  # the folders differ; everything raced must not
        table.pop("league_dir", None)
        table.pop("generated", None)
    assert all(s["forfeits"] == 0 for s in loaded["standings"]), loaded["standings"]
    assert loaded == idle
