"""League runner: definitions, submission checks, full runs in real worker subprocesses, kill -9 and resume,
misbehaving agents, tables."""
from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import make_metadata, save_agent
from multirace.cli import main as cli_main
from multirace.league.config import DEFAULT_TOML, LeagueError, load_config, parse_config
from multirace.league.runner import run_league
from multirace.league.schedule import build_schedule
from multirace.league.store import connect
from multirace.league.submissions import init_league, submit
from multirace.league.table import compute_table, to_html, write_table
from multirace.racing.nets import SMALL, build_net
from helpers import overflow_on_camera_images

REPO = Path(__file__).resolve().parents[1]
DAGGER = REPO / "agents" / "dagger_small.pt"
SPACE = load_action_space(None)

GOOD_TOML = """
[league]
name = "test league"
seeds = [1]
bots = ["bot:follow@1.5", "bot:follow@0.6", "bot:lanes@1.0"]
step_budget = 0.5
max_retries = 1
match_timeout = 120
replays = true

[[tracks]]
name = "reinvent_base"
directions = ["forward"]

[time_trial]
format = "reset_rule"
laps = 1
max_steps = 520

[head_to_head]
cars = 2
laps = 1
max_steps = 520
"""

# Test-only fault injection for worker processes: a sitecustomize that wraps CameraNet.forward so that a
# net whose head.bias[0] carries a tag misbehaves on real camera images (not on the blank smoke-test image).
HOOK = textwrap.dedent('''
    import importlib.abc, os, sys, time

    def _patch(module):
        original = module.CameraNet.forward

        def forward(self, obs):
            import torch
            tag = float(self.head.bias[0])
            if torch.as_tensor(obs).max() > 0:
                if tag == 1234.5:
                    raise RuntimeError("boom in forward")
                if tag == 2345.5:
                    os.kill(os.getpid(), 9)
                if tag == 3456.5:
                    time.sleep(3600)
                if tag == 4567.5:  # slow inference: it burns 0.25 s of CPU (budgets count CPU time)
                    end = time.thread_time() + 0.25
                    while time.thread_time() < end:
                        pass
            return original(self, obs)

        module.CameraNet.forward = forward

    class _Finder(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name != "multirace.racing.nets":
                return None
            for finder in sys.meta_path:
                if finder is self or not hasattr(finder, "find_spec"):
                    continue
                spec = finder.find_spec(name, path, target)
                if spec is not None:
                    break
            else:
                return None
            run = spec.loader.exec_module

            def exec_module(module):
                run(module)
                _patch(module)

            spec.loader.exec_module = exec_module
            return spec

    sys.meta_path.insert(0, _Finder())
''')
TAGS = {"exception": 1234.5, "crash": 2345.5, "hang": 3456.5, "sleepy": 4567.5}


def _agent(path, seed=0, tag=None, name="agent", nan_on_images=False):
    torch.manual_seed(seed)
    net = build_net(SMALL, (120, 160, 1), SPACE)
    if nan_on_images:
        overflow_on_camera_images(net)
    with torch.no_grad():
        if tag is not None:
            net.head.bias[0] = tag
    return save_agent(path, net, make_metadata(SPACE, SMALL, name))


def _league(tmp_path, name="lg", toml=GOOD_TOML):
    folder = tmp_path / name
    init_league(folder)
    (folder / "league.toml").write_text(toml)
    return folder


def _results(folder):
    with sqlite3.connect(folder / "results.sqlite") as conn:
        return conn.execute("SELECT match_id, status, result, reason FROM results").fetchall()


def _comparable(table):
    return json.dumps(table, sort_keys=True)


@pytest.fixture
def hook_env(tmp_path, monkeypatch):
    hook_dir = tmp_path / "hook"
    hook_dir.mkdir()
    (hook_dir / "sitecustomize.py").write_text(HOOK)
    old = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", str(hook_dir) + (os.pathsep + old if old else ""))
    return hook_dir


# ------------------------------------------------------------------ definitions
def test_default_toml_and_init(tmp_path):
    config = parse_config((REPO / "league" / "default.toml").read_text(), "league/default.toml")
    assert (REPO / "league" / "default.toml").read_text() == DEFAULT_TOML.read_text()
    assert config.time_trial and config.head_to_head and config.bots
    folder = init_league(tmp_path / "new")
    for name in ("league.toml", "submissions", "replays", "results.sqlite"):
        assert (folder / name).exists()
    assert load_config(folder).name == config.name
    with pytest.raises(LeagueError, match="already exists"):
        init_league(folder)


@pytest.mark.parametrize("edit, message", [
    (lambda t: t + "\n[league\n", "not valid TOML"),
    (lambda t: t.replace('name = "reinvent_base"', 'name = "no_such_track"'), r"tracks\[0\]\.name.*no_such_track"),
    (lambda t: t.replace('format = "reset_rule"', 'format = "drag_race"'), r"time_trial\.format.*drag_race"),
    (lambda t: t.replace('format = "reset_rule"', 'format = "head_to_head"'), r"time_trial\.format"),
    (lambda t: t.replace("seeds = [1]\n", ""), r"missing key 'league\.seeds'"),
    (lambda t: t.replace('name = "test league"\n', ""), r"missing key 'league\.name'"),
    (lambda t: t.replace("cars = 2", "cars = 9"), r"head_to_head\.cars"),
    (lambda t: t.replace("cars = 2", 'cars = "two"'), r"head_to_head\.cars' must be int"),
    (lambda t: t.replace('"bot:lanes@1.0"', '"bot:zigzag@1"'), r"league\.bots.*zigzag"),
    (lambda t: t.replace('directions = ["forward"]', 'directions = ["sideways"]'), r"tracks\[0\]\.directions"),
    (lambda t: t.replace("step_budget = 0.5", "step_budgett = 0.5"), r"unknown key 'league\.step_budgett'"),
])
def test_malformed_league_toml(tmp_path, edit, message):
    folder = _league(tmp_path, toml=edit(GOOD_TOML))
    with pytest.raises(LeagueError, match=message) as err:
        load_config(folder)
    assert str(folder / "league.toml") in str(err.value)
    assert cli_main(["league", "run", str(folder)]) == 2  # the CLI reports it as an error, no traceback


def test_schedule_is_balanced_and_stable():
    config = parse_config(GOOD_TOML.replace("seeds = [1]", "seeds = [1, 2, 3]").replace(
        'directions = ["forward"]', 'directions = ["forward", "reverse"]').replace("cars = 2", "cars = 3"))
    entries = [{"name": n, "spec": f"submissions/{n}.pt", "sha256": n * 8, "step_budget": None}
               for n in ("a", "b", "c", "d")]
    schedule = build_schedule(config, entries)
    assert build_schedule(config, entries) == schedule  # deterministic
    assert len({m["match_id"] for m in schedule}) == len(schedule)
    trials = [m for m in schedule if m["kind"] == "time_trial"]
    assert len(trials) == 4 * 2 * 3  # entrants x directions x seeds
    heats = [m["spec"]["entrants"] for m in schedule if m["kind"] == "head_to_head"]
    assert len(heats) == 4 * 2 * 3  # C(4,3) heats per direction and seed
    pairs, slots = {}, {}
    for heat in heats:
        names = [e["name"] for e in heat]
        for i, a in enumerate(names):
            slots[(a, i)] = slots.get((a, i), 0) + 1
            for b in names[i + 1:]:
                pairs[frozenset((a, b))] = pairs.get(frozenset((a, b)), 0) + 1
    assert len(set(pairs.values())) == 1 and len(pairs) == 6  # every pair meets equally often
    assert len(set(slots.values())) == 1 and len(slots) == 12  # every entrant starts from every grid slot equally


# ------------------------------------------------------------------ submissions
def test_submit_refuses_bad_files(tmp_path):
    folder = _league(tmp_path)
    good = _agent(tmp_path / "good.pt", seed=3, name="good")
    row = submit(folder, good, "good")
    assert (folder / "submissions" / f"{row['sha256']}.pt").read_bytes() == good.read_bytes()
    with pytest.raises(LeagueError, match="duplicate of submission 'good'"):
        submit(folder, good, "again")
    other = _agent(tmp_path / "other.pt", seed=4, name="other")
    with pytest.raises(LeagueError, match="already submitted"):
        submit(folder, other, "good")

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    evil = tmp_path / "evil.pt"
    torch.save({"format": "multirace-agent", "format_version": 1, "metadata": "{}", "state_dict": Evil()}, evil)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:2000])
    wrong_meta = tmp_path / "wrong_meta.pt"
    torch.save({"format": "multirace-agent", "format_version": 1,
                "metadata": json.dumps({**make_metadata(SPACE, SMALL, "x"), "neural_network": "NOPE"}),
                "state_dict": build_net().state_dict()}, wrong_meta)
    for path, reason in [(evil, "refused"), (truncated, "truncated"),
                         (wrong_meta, "neural_network")]:
        with pytest.raises(LeagueError, match=reason) as err:
            submit(folder, path, path.stem)
        assert str(path) in str(err.value)
    assert not marker.exists()
    assert cli_main(["league", "submit", str(folder), str(truncated), "--name", "t"]) == 1
    with connect(folder) as conn:
        assert [r[0] for r in conn.execute("SELECT name FROM submissions")] == ["good"]
    assert sorted(p.name for p in (folder / "submissions").iterdir()) == [f"{row['sha256']}.pt"]


# ------------------------------------------------------------------ full runs
@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A league of 4 entrants (3 bots and the shipped DAgger agent) run to completion, uninterrupted."""
    folder = _league(tmp_path_factory.mktemp("ref"))
    submit(folder, DAGGER, "dagger")
    stats = run_league(folder, workers=2, progress=False)
    return folder, stats


def test_league_runs_to_completion_and_ranks(reference, tmp_path, capsys):
    folder, stats = reference
    assert stats["scheduled"] == 4 + 6 and stats["ran"] == 10 and stats["failed"] == 0
    rows = _results(folder)
    assert len(rows) == 10 and all(status == "ok" for _, status, _, _ in rows)
    with connect(folder) as conn:
        assert conn.execute("SELECT COUNT(*) FROM schedule WHERE status != 'done'").fetchone()[0] == 0
    for match_id, *_ in rows:
        replay = folder / "replays" / f"{match_id}.rrd"
        assert replay.stat().st_size > 1000
    assert not list((folder / "replays").glob("*.tmp"))
    table = compute_table(folder)
    by_name = {s["entrant"]: s for s in table["standings"]}
    fast, slow = by_name["bot:follow@1.5"], by_name["bot:follow@0.6"]
    assert fast["rating"] > slow["rating"]
    assert fast["tt_best_lap"] < slow["tt_best_lap"]
    assert fast["rank"] < slow["rank"]
    tt = [s["entrant"] for s in table["time_trials"]]
    assert tt.index("bot:follow@1.5") < tt.index("bot:follow@0.6")
    assert by_name["dagger"]["heats"] == 3 and by_name["dagger"]["tt_completion"] is not None
    cars = [car for _, _, result, _ in rows for car in json.loads(result)["cars"]]
    for name, standing in by_name.items():  # penalties and at-fault collisions from every race's record
        mine = [car for car in cars if car["name"] == name]
        assert standing["penalties"] == sum(car["penalties"] for car in mine)
        laps = sum(car["laps"] for car in mine)
        assert standing["collisions_caused_per_lap"] == (round(sum(car["collisions_caused"] for car in mine) / laps, 4)
                                                         if laps else None)
    assert table["rating_history"] and table["pending"] == 0
    # a second run finds nothing to do and changes nothing
    again = run_league(folder, workers=2, progress=False)
    assert again["ran"] == 0 and len(_results(folder)) == 10
    # exports
    assert cli_main(["league", "table", str(folder)]) == 0  # the default: terminal tables, readable headers
    text = capsys.readouterr().out
    assert "TT best lap (s)" in text.replace("\n", " ") or "best lap (s)" in text
    assert "tt_best_lap" not in text and "┃ entrant" in text
    assert "penalties" in text and "at-fault" in text
    for fmt in ("md", "csv", "json", "html"):
        out = tmp_path / f"table.{fmt}"
        assert cli_main(["league", "table", str(folder), "--format", fmt, "--out", str(out)]) == 0
        assert out.stat().st_size > 100
    assert "bot:follow@1.5" in (tmp_path / "table.md").read_text()
    assert (tmp_path / "table.csv").read_text().splitlines()[0].startswith("rank,entrant,rating")
    assert json.loads((tmp_path / "table.json").read_text())["standings"][0]["rank"] == 1
    page = (tmp_path / "table.html").read_text()
    assert page.count("data:image/png;base64,") == 2  # rating plot and the track map
    assert f"{folder.name}/replays/" in page and "<script" not in page
    assert not (folder / "ratings.png").exists()  # the table writes only what was asked, where asked
    assert cli_main(["league", "table", str(folder), "--plot", str(tmp_path / "ratings.png")]) == 0
    assert (tmp_path / "ratings.png").read_bytes()[:4] == b"\x89PNG"


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run"]


def test_the_html_standings_fit_1280_px_in_a_browser(reference, tmp_path):
    if CHROMIUM is None:
        pytest.skip("no chromium installed (apt-get install chromium): the page is not measured in a browser")
    sync_playwright = pytest.importorskip("playwright.sync_api", reason="pip install playwright").sync_playwright
    folder, _ = reference
    table = compute_table(folder)
    first, longest = table["standings"][0]["entrant"], "L" * 64  # the longest name an entrant may have
    table["standings"][0]["entrant"] = longest
    for point in table["rating_history"]:
        point["ordinal"][longest] = point["ordinal"].pop(first)
    page_file = tmp_path / "table.html"
    page_file.write_text(to_html(table))
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=BROWSER_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(page_file.as_uri())
            standings = page.locator("table").first
            assert standings.evaluate("t => t.getBoundingClientRect().right") <= 1280
            assert page.evaluate("() => document.documentElement.scrollWidth") <= 1280  # no sideways scrolling
            headers = standings.locator("th").all_inner_texts()
            assert headers and not any("_" in h for h in headers), headers  # readable, not identifiers
            align = standings.evaluate(
                "t => [...t.rows[1].cells].map(c => getComputedStyle(c).textAlign)")
            assert align[1] == "left" and align[0] == align[2] == "right"  # entrant left, numbers right
        finally:
            browser.close()


def test_kill_9_mid_run_then_resume_matches_uninterrupted(reference, tmp_path):
    ref_folder, _ = reference
    folder = _league(tmp_path)
    submit(folder, DAGGER, "dagger")
    proc = subprocess.Popen([sys.executable, "-m", "multirace.cli", "league", "run", str(folder), "--workers", "2",
                             "--quiet"], start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if (folder / "results.sqlite").exists():
                try:
                    if len(_results(folder)) >= 3:
                        break
                except sqlite3.OperationalError:
                    pass
            assert proc.poll() is None, "the run finished before it could be killed"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    done_before = len(_results(folder))
    assert 3 <= done_before < 10
    stats = run_league(folder, workers=2, progress=False)
    assert stats["ran"] == 10 - done_before
    rows = _results(folder)
    assert len(rows) == 10 and len({r[0] for r in rows}) == 10
    with connect(folder) as conn:
        scheduled = {r[0] for r in conn.execute("SELECT match_id FROM schedule")}
    assert scheduled == {r[0] for r in rows}
    assert _comparable(compute_table(folder)) == _comparable(compute_table(ref_folder))
    assert not list((folder / "replays").glob("*.tmp"))


BAD_TOML = GOOD_TOML.replace('bots = ["bot:follow@1.5", "bot:follow@0.6", "bot:lanes@1.0"]',
                             'bots = ["bot:follow@1.5"]').replace("step_budget = 0.5", "step_budget = 0.1") \
    .replace("cars = 2", "cars = 4").replace("max_steps = 520", "max_steps = 200")


def test_misbehaving_agents_forfeit_and_league_completes(tmp_path, hook_env):
    folder = _league(tmp_path, toml=BAD_TOML)
    submit(folder, _agent(tmp_path / "nan.pt", seed=1, nan_on_images=True, name="n"), "nan")
    submit(folder, _agent(tmp_path / "exc.pt", seed=2, tag=TAGS["exception"], name="e"), "exception")
    submit(folder, _agent(tmp_path / "sleepy.pt", seed=3, tag=TAGS["sleepy"], name="s"), "sleepy")
    stats = run_league(folder, workers=2, progress=False)
    assert stats["scheduled"] == 4 + 1 and stats["ran"] == 5 and stats["failed"] == 0
    expected = {"nan": "non-finite", "exception": "boom in forward", "sleepy": "budget"}
    seen = {name: 0 for name in expected}
    for _, status, result, _ in _results(folder):
        for car in json.loads(result)["cars"]:
            if car["name"] in expected:
                assert car["status"] == "forfeit" and expected[car["name"]] in car["reason"], car
                seen[car["name"]] += 1
            else:
                assert car["status"] == "finished", car
    assert seen == {name: 2 for name in expected}  # its time trial and the heat
    table = compute_table(folder)
    assert table["standings"][0]["entrant"] == "bot:follow@1.5"
    reasons = {s["entrant"]: " ".join(s["forfeit_reasons"]) for s in table["standings"]}
    assert "boom" in reasons["exception"] and "budget" in reasons["sleepy"]
    assert "Forfeits" in write_table(folder, "md")


@pytest.mark.slow
def test_crashing_and_hanging_workers_cost_only_their_match(tmp_path, hook_env):
    toml = BAD_TOML.replace("match_timeout = 120", "match_timeout = 20").replace(
        "[head_to_head]", "[head_to_head]\nenabled = false")
    folder = _league(tmp_path, toml=toml)
    submit(folder, _agent(tmp_path / "crash.pt", seed=4, tag=TAGS["crash"], name="c"), "crash")
    submit(folder, _agent(tmp_path / "hang.pt", seed=5, tag=TAGS["hang"], name="h"), "hang")
    stats = run_league(folder, workers=2, progress=False)  # the hung worker is killed at the match timeout
    assert stats["scheduled"] == 3 and stats["ran"] == 1 and stats["failed"] == 2
    by_entrant = {}
    with connect(folder) as conn:
        for spec, status, attempts, reason in conn.execute(
                "SELECT s.spec, r.status, s.attempts, r.reason FROM schedule s JOIN results r USING (match_id)"):
            by_entrant[json.loads(spec)["entrants"][0]["name"]] = (status, attempts, reason)
    assert by_entrant["bot:follow@1.5"][0] == "ok"
    assert by_entrant["crash"][:2] == ("failed", 2) and "crashed" in by_entrant["crash"][2]
    assert by_entrant["hang"][:2] == ("failed", 2) and "timed out" in by_entrant["hang"][2]
    table = compute_table(folder)
    assert len(table["failed"]) == 2 and table["pending"] == 0
    assert run_league(folder, workers=2, progress=False)["ran"] == 0  # failed matches are final


def test_ray_without_ray_is_a_clear_error(tmp_path):
    try:
        import ray  # noqa: F401
        pytest.skip("ray is installed")
    except ImportError:
        pass
    folder = _league(tmp_path)
    with pytest.raises(LeagueError, match=r"pip install 'multirace\[ray\]'"):
        run_league(folder, ray_address="auto", progress=False)


@pytest.mark.slow
def test_ray_local_instance_gives_the_same_table(reference, tmp_path):
    pytest.importorskip("ray")
    ref_folder, _ = reference
    folder = _league(tmp_path)
    submit(folder, DAGGER, "dagger")
    stats = run_league(folder, ray_address="local", progress=False)
    assert stats["ran"] == 10 and stats["failed"] == 0
    assert len(_results(folder)) == 10
    assert all((folder / "replays" / f"{mid}.rrd").stat().st_size > 1000 for mid, *_ in _results(folder))
    assert _comparable(compute_table(folder)) == _comparable(compute_table(ref_folder))
