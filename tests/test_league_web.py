"""`multirace league serve`, `league entrant add`, uploads and `league run --watch`, as people use them: the real
server (uvicorn, started by the CLI in a subprocess) on 127.0.0.1, real HTTP, a real SQLite store, real worker
subprocesses; the browser test drives the pages in Debian's headless Chromium."""
from __future__ import annotations

import hashlib
import os
import sqlite3
import threading

import av
import pytest
import torch

from multirace.league.config import parse_config
from multirace.league.runner import run_league
from multirace.league.schedule import build_schedule
from multirace.league.store import connect
from multirace.league.submissions import init_league, submit
from web_helpers import (REPO, TINY_TOML, Process, Server, agent_file, cli, copy_league, get_json, multipart,
                         request, upload, wait_until)

DAGGER = REPO / "agents" / "dagger_small.pt"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One cache folder (rerun's web viewer files) for every server of this module."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def played(tmp_path_factory):
    """A tiny league played to the end: 2 bots and the shipped DAgger agent, 1 lap (3 time trials, 3 heats)."""
    folder = tmp_path_factory.mktemp("played") / "lg"
    init_league(folder)
    (folder / "league.toml").write_text(TINY_TOML)
    submit(folder, DAGGER, "dagger")
    stats = run_league(folder, workers=2, progress=False)
    assert stats["ran"] == 6 and stats["failed"] == 0
    return folder


@pytest.fixture(scope="module")
def server(played, cache, tmp_path_factory):
    """A server on the played league that no test changes."""
    running = Server(cache, played, log=tmp_path_factory.mktemp("logs") / "serve.log")
    yield running
    running.stop()


@pytest.fixture
def league(played, tmp_path):
    """A copy of the played league for a test that changes it."""
    return copy_league(played, tmp_path / "lg")


def _token(cache, folder, name):
    done = cli(cache, "league", "entrant", "add", folder, name)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


def _results(folder):
    with sqlite3.connect(folder / "results.sqlite") as conn:
        return dict(conn.execute("SELECT match_id, recorded_at FROM results").fetchall())


def test_a_new_entrant_adds_only_its_own_heats():
    config = parse_config(TINY_TOML)
    entries = [{"name": n, "spec": f"submissions/{n}.pt", "sha256": n * 8, "step_budget": None}
               for n in ("bot:follow@1.5", "bot:follow@0.8", "dagger")]
    before = {m["match_id"] for m in build_schedule(config, entries)}
    entries.insert(2, {"name": "alice", "spec": "submissions/alice.pt", "sha256": "a" * 8, "step_budget": None})
    after = build_schedule(config, entries)
    assert before <= {m["match_id"] for m in after}
    new = [m for m in after if m["match_id"] not in before]
    assert len(new) == 1 + 3 and all("alice" in [e["name"] for e in m["spec"]["entrants"]] for m in new)


def test_entrant_add_prints_a_token_and_keeps_only_its_hash(league, cache):
    token = _token(cache, league, "alice")
    assert len(token) >= 40
    stored = b"".join(p.read_bytes() for p in league.glob("results.sqlite*"))
    assert token.encode() not in stored
    with sqlite3.connect(league / "results.sqlite") as conn:
        assert conn.execute("SELECT name, token_sha256 FROM entrants").fetchall() == [
            ("alice", hashlib.sha256(token.encode()).hexdigest())]
    again = cli(cache, "league", "entrant", "add", league, "alice")
    assert again.returncode == 2 and "exists already" in again.stderr
    listing = sorted(p.name for p in league.parent.rglob("*"))
    for hostile in ("../evil", "a/b", "<script>", "bot:follow@1.5", "x" * 65, "", "new\nline", "bot:x"):
        done = cli(cache, "league", "entrant", "add", league, hostile)
        assert done.returncode == 2 and "not a valid entrant name" in done.stderr, hostile
    assert sorted(p.name for p in league.parent.rglob("*")) == listing


def test_pages_and_api_show_the_league(server, played):
    url = server.url
    board = get_json(url + "/api/leaderboard")
    assert board["leaderboard"]["recorded"] == 6 and board["leaderboard"]["pending"] == 0
    assert [r["rank"] for r in board["rankings"]] == [1, 2, 3]
    assert {r["userProfile"]["alias"] for r in board["rankings"]} == {"bot:follow@1.5", "bot:follow@0.8", "dagger"}
    for r in board["rankings"]:
        assert r["stats"]["heats"] == 2 and set(r["stats"]) >= {"mu", "sigma", "wins", "collisionsCausedPerLap"}
    status, headers, page = request("GET", url + "/")
    assert status == 200 and headers["x-content-type-options"] == "nosniff"
    assert "default-src 'self'" in headers["content-security-policy"]
    for text in (b"Rating", b"Time-trial best lap (s)", b"At-fault collisions / lap", b"Forfeits", b"dagger",
                 b"bot:follow@1.5"):
        assert text in page
    dagger = get_json(url + "/api/entrants/dagger")
    assert [v["version"] for v in dagger["versions"]] == [1] and len(dagger["matches"]) == 3
    assert request("GET", url + "/entrants/dagger")[0] == 200
    matches = get_json(url + "/api/matches")["matches"]
    assert len(matches) == 6 and all(m["status"] == "ok" for m in matches)
    heat = next(m for m in matches if m["kind"] == "head_to_head")
    assert get_json(f"{url}/api/matches/{heat['match_id']}")["cars"][0]["position"] == 1
    status, _, page = request("GET", f"{url}/matches/{heat['match_id']}")
    assert status == 200 and b"<video" in page and b"Lap chart" in page and b"<svg" in page


def test_match_video_is_h264_faststart_and_replay_and_viewer_are_served(server, played, tmp_path):
    url = server.url
    heat = next(m for m in get_json(url + "/api/matches")["matches"] if m["kind"] == "head_to_head")
    status, headers, video = request("GET", f"{url}/matches/{heat['match_id']}/video.mp4")
    assert status == 200 and headers["content-type"] == "video/mp4"
    assert 0 <= video.find(b"moov") < video.find(b"mdat")  # faststart: the index comes first
    (tmp_path / "v.mp4").write_bytes(video)
    with av.open(str(tmp_path / "v.mp4")) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and sum(1 for _ in container.decode(stream)) > 30
    status, headers, part = request("GET", f"{url}/matches/{heat['match_id']}/video.mp4",
                                    headers={"Range": "bytes=0-99"})
    assert status == 206 and part == video[:100]
    status, _, replay = request("GET", f"{url}/matches/{heat['match_id']}/replay.rrd")
    assert status == 200 and replay == (played / heat["replay"]).read_bytes()
    status, _, index = request("GET", url + "/viewer/index.html")
    assert status == 200 and b"re_viewer.js" in index and b"fonts.googleapis" not in index
    status, headers, _ = request("GET", url + "/viewer/re_viewer_bg.wasm")
    assert status == 200 and headers["content-type"] == "application/wasm"


def test_unknown_and_hostile_paths_are_404(server, played):
    secret = (played / "league.toml").read_bytes()
    for path in ("/entrants/nobody", "/matches/0000000000000000", "/matches/../../etc/passwd",
                 "/matches/%2e%2e%2fleague.toml/replay.rrd", "/api/matches/xyz", "/static/../league.toml",
                 "/static/%2e%2e/%2e%2e/league.toml", "/viewer/../results.sqlite", "/api/entrants/%2e%2e",
                 "/matches/0000000000000000/video.mp4", "/entrants/%3Cscript%3E"):
        status, _, body = request("GET", server.url + path)
        assert status == 404, path
        assert secret not in body and b"<script>" not in body


def test_uploads_are_checked_and_refused_in_plain_words(league, cache, tmp_path):
    token = _token(cache, league, "alice")
    srv = Server(cache, league, "--max-upload-mb", "1", "--uploads-per-hour", "50", log=tmp_path / "serve.log")
    try:
        good = DAGGER.read_bytes()
        assert upload(srv.url, None, good) == (401, {"error": "refused: no token (send your entrant token; "
                                                                "the organiser gave it to you)"})
        status, answer = upload(srv.url, "w" * 43, good)
        assert status == 401 and "belongs to no entrant" in answer["error"]
        status, _, body = request("POST", srv.url + "/api/submissions", b"x" * (2 * 2**20),
                                  {"Authorization": f"Bearer {token}"})
        assert status == 413 and b"over 1 MB" in body
        chunks = (b"x" * 65536 for _ in range(40))  # 2.5 MB without a Content-Length
        status, _, body = request("POST", srv.url + "/api/submissions", chunks, {"Authorization": f"Bearer {token}"})
        assert status == 413
        assert upload(srv.url, token, b"")[0] == 400
        status, answer = upload(srv.url, token, os.urandom(5000))
        assert status == 422 and answer["error"].startswith("refused: the uploaded file")
        assert ".tmp" not in answer["error"]
        marker = tmp_path / "pwned"

        class Evil:
            def __reduce__(self):
                return (os.system, (f"touch {marker}",))

        torch.save({"format": "multirace-agent", "format_version": 1, "metadata": "{}", "state_dict": Evil()},
                   tmp_path / "pickled.pt")
        status, answer = upload(srv.url, token, (tmp_path / "pickled.pt").read_bytes())
        assert status == 422 and answer["error"].startswith("refused") and not marker.exists()
        status, answer = upload(srv.url, token, good, filename="../../../evil.pt")
        assert status == 422 and "another entrant" in answer["error"]  # the same bytes as dagger's
        mine = agent_file(tmp_path / "mine.pt", seed=5).read_bytes()
        status, answer = upload(srv.url, token, mine, filename="../../../evil.pt")
        assert status == 201 and answer["version"] == 1 and answer["name"] == "alice"
        assert upload(srv.url, token, mine)[1]["error"] == "refused: this file is one of your versions already " \
                                                           "(same sha256)"
    finally:
        srv.stop()
    names = sorted(p.name for p in (league / "submissions").iterdir())
    assert names == sorted(f"{hashlib.sha256(b).hexdigest()}.pt" for b in (good, mine))
    assert not list(league.parent.rglob("evil.pt"))
    connect(league).close()  # the store and the folder agree


def test_the_form_needs_its_csrf_token_and_same_origin(league, cache, tmp_path):
    token = _token(cache, league, "alice")
    srv = Server(cache, league, log=tmp_path / "serve.log")
    try:
        status, headers, page = request("GET", srv.url + "/submit")
        cookie = headers["set-cookie"].split(";")[0]
        assert status == 200 and "samesite=strict" in headers["set-cookie"].lower()
        csrf = cookie.split("=", 1)[1]
        assert f'value="{csrf}"'.encode() in page
        data = agent_file(tmp_path / "a.pt", seed=6).read_bytes()

        def post(fields, cookie_header, origin=None):
            body, kind = multipart(fields, {"file": ("a.pt", data)})
            headers = {"Content-Type": kind, **({"Cookie": cookie_header} if cookie_header else {})}
            if origin:
                headers["Origin"] = origin
            return request("POST", srv.url + "/submit", body, headers)

        assert post({"token": token}, cookie)[0] == 403
        assert post({"token": token, "csrf_token": csrf}, None)[0] == 403
        assert post({"token": token, "csrf_token": "x" + csrf}, cookie)[0] == 403
        status, _, page = post({"token": token, "csrf_token": csrf}, cookie, origin="http://evil.example")
        assert status == 403 and b"came from another site" in page
        assert request("GET", srv.url + "/api/entrants/alice")[0] == 404  # nothing was stored
        status, _, page = post({"token": token, "csrf_token": csrf}, cookie, origin=srv.url)
        assert status == 201 and b"Accepted" in page and b"version 1" in page
        status, _, page = post({"token": "wrong" * 9, "csrf_token": csrf}, cookie)
        assert status == 401 and b"belongs to no entrant" in page
    finally:
        srv.stop()


def test_rate_limits(league, cache, tmp_path):
    token = _token(cache, league, "alice")
    srv = Server(cache, league, "--uploads-per-hour", "2", log=tmp_path / "serve.log")
    try:
        assert [upload(srv.url, token, os.urandom(100))[0] for _ in range(3)] == [422, 422, 429]
        wrong = [upload(srv.url, "z" * 43, b"x")[0] for _ in range(31)]
        assert wrong[:30] == [401] * 30 and wrong[30] == 429
    finally:
        srv.stop()


def test_concurrent_uploads_all_land_as_distinct_versions(league, cache, tmp_path):
    tokens = {name: _token(cache, league, name) for name in ("alice", "bob")}
    files = [(name, agent_file(tmp_path / f"{name}{i}.pt", seed=10 + 2 * i + (name == "bob")).read_bytes())
             for name in tokens for i in range(2)]
    srv = Server(cache, league, log=tmp_path / "serve.log")
    answers = []
    try:
        threads = [threading.Thread(target=lambda n=n, d=d: answers.append(upload(srv.url, tokens[n], d)))
                   for n, d in files]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=600)
        assert sorted(status for status, _ in answers) == [201] * 4, answers
        for name in tokens:
            versions = get_json(f"{srv.url}/api/entrants/{name}")["versions"]
            assert [v["version"] for v in versions] == [1, 2] and [v["racing"] for v in versions] == [False, True]
    finally:
        srv.stop()
    connect(league).close()


def test_a_server_killed_mid_upload_loses_nothing(league, cache, tmp_path):
    token = _token(cache, league, "alice")
    data = agent_file(tmp_path / "a.pt", seed=7).read_bytes()
    srv = Server(cache, league, log=tmp_path / "serve.log")
    thread = threading.Thread(target=lambda: _swallow(upload, srv.url, token, data), daemon=True)
    thread.start()
    wait_until(lambda: list((league / "submissions").glob(".*.tmp")), 120, "the upload to be validating", 0.05)
    srv.kill()
    connect(league).close()  # the store is intact and agrees with submissions/
    srv = Server(cache, league, log=tmp_path / "serve2.log")
    try:
        assert get_json(srv.url + "/api/leaderboard")["leaderboard"]["recorded"] == 6
        assert not list((league / "submissions").glob(".*.tmp"))  # the killed upload's copy is cleared
        assert upload(srv.url, token, data)[0] == 201  # nothing half-made stands in its way
    finally:
        srv.stop()


def _swallow(function, *args):
    try:
        function(*args)
    except OSError:  # the server was killed under the request
        pass


@pytest.mark.slow
def test_watch_plays_only_what_a_new_version_needs_and_survives_kill_9(league, cache, tmp_path):
    before = _results(league)
    token = _token(cache, league, "alice")
    srv = Server(cache, league, log=tmp_path / "serve.log")
    runner = None
    try:
        assert upload(srv.url, token, agent_file(tmp_path / "v1.pt", seed=8).read_bytes())[0] == 201
        runner = Process(cache, "league", "run", league, "--watch", "--workers", "2", "--poll", "0.5",
                         log=tmp_path / "watch.log")
        board = wait_until(lambda: _settled(srv.url, 10), 600, "the first version's matches")
        after_v1 = _results(league)
        assert {k: after_v1[k] for k in before} == before  # nothing played again
        assert len(after_v1) == 6 + 4  # its time trial and its 3 heats
        assert upload(srv.url, token, agent_file(tmp_path / "v2.pt", seed=9).read_bytes())[0] == 201
        wait_until(lambda: len(_results(league)) > len(after_v1), 600, "the second version's first result")
        runner.kill()  # SIGKILL mid-run; its worker processes die with their pipes
        runner.stop()
        runner = Process(cache, "league", "run", league, "--watch", "--workers", "2", "--poll", "0.5",
                         log=tmp_path / "watch2.log")
        board = wait_until(lambda: _settled(srv.url, 10), 600, "the second version's matches")
        final = _results(league)
        assert len(final) == 6 + 4 + 4 and {k: final[k] for k in after_v1} == after_v1
        alice = next(r for r in board["rankings"] if r["userProfile"]["alias"] == "alice")
        assert alice["stats"]["heats"] == 3 and alice["submissionNumber"] == 2  # the table counts the newest only
    finally:
        if runner is not None:
            runner.stop()
        srv.stop()


def _settled(url, recorded):
    board = get_json(url + "/api/leaderboard")
    return board if board["leaderboard"]["pending"] == 0 and board["leaderboard"]["recorded"] == recorded else None


# ------------------------------------------------------------------ in a real browser
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run"]
CHROMIUM = "/usr/bin/chromium"


def _browser(playwright):
    return playwright.chromium.launch(executable_path=CHROMIUM, args=BROWSER_ARGS)


@pytest.mark.slow
def test_in_a_browser_upload_watch_the_board_change_play_the_video_open_the_replay(league, cache, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"no browser: {CHROMIUM} is not installed (apt-get install chromium)")
    token = _token(cache, league, "alice")
    srv = Server(cache, league, log=tmp_path / "serve.log")
    runner = Process(cache, "league", "run", league, "--watch", "--workers", "2", "--poll", "0.5",
                     log=tmp_path / "watch.log")
    agent = agent_file(tmp_path / "alice.pt", seed=11)
    try:
        with sync_api.sync_playwright() as playwright:
            browser = _browser(playwright)
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            outside = []
            page.on("request", lambda r: None if r.url.startswith((srv.url, "data:", "blob:"))
                    else outside.append(r.url))
            page.goto(srv.url + "/submit")
            page.fill("input[name=token]", token)
            page.set_input_files("input[name=file]", str(agent))
            page.click("button[type=submit]")
            assert "Accepted" in page.inner_text("#outcome")
            page.goto(srv.url + "/")
            assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth && "
                                 "document.getElementById('standings').scrollWidth <= 1280")
            page.wait_for_function("() => /10 of 10 matches played/.test(document.getElementById('summary').innerText)",
                                   timeout=600_000)  # the page redrew itself as the runner played alice's matches
            assert "alice" in page.inner_text("#standings")
            page.click("#latest a >> nth=0")
            page.wait_for_selector("#race-video")
            page.evaluate("document.getElementById('race-video').play()")
            page.wait_for_function("() => { const v = document.getElementById('race-video'); "
                                   "return v.readyState >= 2 && v.currentTime > 0.5; }", timeout=120_000)
            page.click("#open-viewer")
            viewer = page.frame_locator("#viewer")
            viewer.locator("canvas#the_canvas_id.visible").wait_for(state="attached", timeout=180_000)
            assert not outside, outside
            phone = browser.new_page(viewport={"width": 390, "height": 844})
            for path in ("/", page.url.replace(srv.url, ""), "/entrants/alice", "/submit"):
                phone.goto(srv.url + path)
                assert phone.evaluate("document.documentElement.scrollWidth <= window.innerWidth"), path
            browser.close()
    finally:
        runner.stop()
        srv.stop()
