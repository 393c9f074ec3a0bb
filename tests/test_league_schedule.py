"""The uncertainty schedule: its choice of pairs, its settings in league.toml, and real league runs planned
batch by batch (deterministic, resumable), and the convergence measurement's reference."""
from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time

import pytest
from openskill.models import PlackettLuce

from multirace.cli import main as cli_main
from multirace.league.config import LeagueError, load_config
from multirace.league.convergence import measure, reference_rank, top_tau
from multirace.league.runner import run_league
from multirace.league.submissions import init_league
from multirace.league.table import compute_table
from multirace.league.uncertainty import rate, uncertain_heats

BOTS = ["bot:follow@0.6", "bot:follow@1.5", "bot:lanes@1.0", "bot:pass@1.2", "bot:racingline@0.8"]
TOML = f"""
[league]
name = "uncertainty league"
seeds = [1]
bots = {json.dumps(BOTS)}
max_retries = 1
replays = false

[[tracks]]
name = "reinvent_base"

[time_trial]
enabled = false

[head_to_head]
cars = 2
laps = 1
trials = 2
max_steps = 60
schedule = "uncertainty"
opponents = 2
batch = 2
"""


def _league(tmp_path, name="lg", toml=TOML):
    folder = tmp_path / name
    init_league(folder)
    (folder / "league.toml").write_text(toml)
    return folder


def _heats(folder) -> list[tuple[int, list[str], dict | None]]:
    """(round, entrants, result) of every stored head-to-head match, in schedule order."""
    with sqlite3.connect(folder / "results.sqlite") as conn:
        rows = conn.execute("SELECT s.round, s.spec, r.result FROM schedule s LEFT JOIN results r USING "
                            "(match_id) WHERE s.kind = 'head_to_head' ORDER BY s.seq").fetchall()
    return [(r, [e["name"] for e in json.loads(spec)["entrants"]], json.loads(result) if result else None)
            for r, spec, result in rows]


def test_uncertain_heats_spend_heats_where_the_table_is_unsure():
    model = PlackettLuce()
    ratings = {"a": model.rating(mu=30, sigma=1), "b": model.rating(mu=30.5, sigma=1),
               "c": model.rating(mu=10, sigma=1), "d": model.rating(mu=25, sigma=8),
               "e": model.rating(mu=24, sigma=8)}
    heats = uncertain_heats(model, ratings, 3, set())
    assert heats[0] == ("d", "e")  # close and unknown
    assert len({name for heat in heats for name in heat}) == 2 * len(heats)  # nobody twice in a batch
    assert ("d", "e") not in uncertain_heats(model, ratings, 2, {frozenset("de")})  # a pair meets once
    assert uncertain_heats(model, {"a": ratings["a"], "b": ratings["b"]}, 1, {frozenset("ab")}) == []
    fresh = {n: model.rating() for n in "abcdefgh"}  # all equal: the salt orders the choice
    assert uncertain_heats(model, fresh, 4, set()) == uncertain_heats(model, fresh, 4, set())
    assert any(uncertain_heats(model, fresh, 4, set(), salt=str(s)) != uncertain_heats(model, fresh, 4, set())
               for s in range(5))


def test_reference_ties_a_cycle_and_tau_skips_ties():
    beats = {("a", "b"), ("b", "c"), ("c", "a"), ("a", "d"), ("b", "d"), ("c", "d")}  # a cycle above d
    rank = reference_rank(list("abcd"), lambda x, y, seed: x if (x, y) in beats else y)
    assert rank == {"a": 0, "b": 0, "c": 0, "d": 3}
    assert top_tau(list("cbad"), rank) == pytest.approx(1.0)  # the tied three in any order
    assert top_tau(list("dabc"), rank) == pytest.approx(-1.0)
    assert top_tau(list("adbc"), rank) == pytest.approx(-1 / 3)  # a over d right, d over b and c wrong


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('schedule = "uncertainty"', 'schedule = "swiss"'), r"'head_to_head\.schedule' must be"),
    (lambda t: t.replace('schedule = "uncertainty"', "schedule = 3"), r"'head_to_head\.schedule' must be str"),
    (lambda t: t.replace('schedule = "uncertainty"', 'schedule = "round_robin"'),
     r"'head_to_head\.opponents' applies only with schedule = \"uncertainty\""),
    (lambda t: t.replace("cars = 2", "cars = 3"), r"'head_to_head\.cars' must be 2 with schedule"),
    (lambda t: t.replace("opponents = 2", "opponents = 0"), r"'head_to_head\.opponents' must be at least 1"),
    (lambda t: t.replace("batch = 2", "stop_sigma = -1"), r"'head_to_head\.stop_sigma' must be above 0"),
])
def test_bad_schedule_settings_name_the_file_and_field(tmp_path, edit, message):
    folder = _league(tmp_path, toml=edit(TOML))
    with pytest.raises(LeagueError, match=message) as err:
        load_config(folder)
    assert str(folder / "league.toml") in str(err.value)
    assert cli_main(["league", "run", str(folder)]) == 2  # an error message, no traceback


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """The small uncertainty league run to the end on 2 workers."""
    folder = _league(tmp_path_factory.mktemp("unc"))
    return folder, run_league(folder, workers=2, progress=False)


def test_league_run_plans_each_batch_from_the_results_before_it(planned):
    folder, stats = planned
    heats = _heats(folder)
    assert stats["failed"] == 0 and stats["ran"] == len(heats) == 5 * 2  # opponents 2 x 5 entrants / 2
    assert all(result is not None for *_, result in heats)
    rounds = sorted({r for r, *_ in heats})
    assert rounds == [0, 1, 2]  # batches of 2, 2 and the 1 pairing left of the budget
    model, met, recorded = PlackettLuce(), set(), []
    for round_no in rounds:
        batch = [(names, result) for r, names, result in heats if r == round_no]
        pairs = list(dict.fromkeys(tuple(sorted(names)) for names, _ in batch))
        ratings = rate(model, BOTS, recorded)  # only the batches before this one
        assert pairs == uncertain_heats(model, ratings, min(2, 5 - len(met)), met)
        assert sorted(names for names, _ in batch) == sorted(
            [list(p) for p in pairs] + [list(p)[::-1] for p in pairs])  # each pairing from both grid orders
        met |= {frozenset(p) for p in pairs}
        recorded += [[(c["name"], c["position"]) for c in sorted(result["cars"], key=lambda c: c["position"])]
                     for _, result in batch]
    table = compute_table(folder)
    assert table["pending"] == 0 and table["scheduled"] == 10
    assert [point["round"] for point in table["rating_history"]] == rounds
    again = run_league(folder, workers=2, progress=False)
    assert again["ran"] == 0 and len(_heats(folder)) == 10  # the budget is spent: nothing more is planned


def test_the_same_league_gives_the_same_table_on_one_worker(planned, tmp_path):
    folder, _ = planned
    other = _league(tmp_path)
    run_league(other, workers=1, progress=False)
    assert [(r, n) for r, n, _ in _heats(other)] == [(r, n) for r, n, _ in _heats(folder)]
    assert json.dumps(compute_table(other), sort_keys=True) == json.dumps(compute_table(folder), sort_keys=True)


@pytest.mark.slow
def test_kill_9_between_batches_then_resume_gives_the_same_table(planned, tmp_path):
    folder, _ = planned
    other = _league(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "multirace.cli", "league", "run", str(other), "--workers", "2",
                             "--quiet"], start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        for _ in range(100_000):  # until the second batch has a result
            assert proc.poll() is None, "the run finished before it could be killed"
            try:
                if sum(result is not None for *_, result in _heats(other)) >= 5:
                    break
            except sqlite3.OperationalError:  # not created yet, or busy
                pass
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert 5 <= sum(result is not None for *_, result in _heats(other)) < 10
    run_league(other, workers=2, progress=False)
    assert [(r, n) for r, n, _ in _heats(other)] == [(r, n) for r, n, _ in _heats(folder)]
    assert json.dumps(compute_table(other), sort_keys=True) == json.dumps(compute_table(folder), sort_keys=True)


def test_the_convergence_measurement_runs_on_real_races_and_reuses_them(tmp_path):
    entrants = {b: b for b in ("bot:follow@0.6", "bot:follow@1.0", "bot:follow@1.5", "bot:pass@1.2")}
    out = tmp_path / "cv.json"
    found = measure(entrants, out, steps=60, batch=2, workers=2, chains=2)
    rank = found["reference_rank"]
    assert rank["bot:follow@1.5"] < rank["bot:follow@0.6"] and rank["bot:follow@1.0"] < rank["bot:follow@0.6"]
    assert found["races"] == 2 * 2 * 6  # both grid orders of 6 pairings on 2 seeds
    for schedule in ("uncertainty", "round_robin"):
        for chain in found[schedule]["chains"]:
            assert max(map(int, chain["curve"])) == 6  # every pairing played in the end
    cache = out.with_suffix(".heats.json")
    stamp = cache.stat().st_mtime_ns
    again = measure(entrants, out, steps=60, batch=2, workers=2, chains=2)
    assert json.loads(json.dumps(again)) == json.loads(json.dumps(found)) == json.loads(out.read_text())
    assert cache.stat().st_mtime_ns == stamp  # the second measurement raced nothing
