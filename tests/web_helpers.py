"""Helpers for the league web tests: a tiny played league, the real server and runner as subprocesses, HTTP."""
from __future__ import annotations

import http.client
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import torch

from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import make_metadata, save_agent
from multirace.racing.nets import SMALL, build_net

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from multirace.cli import main; sys.exit(main())"]
TINY_TOML = """
[league]
name = "web test league"
seeds = [1]
bots = ["bot:follow@1.5", "bot:follow@0.8"]
step_budget = 0.5
max_retries = 1
match_timeout = 180
replays = true

[[tracks]]
name = "reinvent_base"
directions = ["forward"]

[time_trial]
format = "reset_rule"
laps = 1
max_steps = 200

[head_to_head]
cars = 2
laps = 1
max_steps = 200
"""


def env(cache: Path) -> dict:
    """The environment of the server and runner subprocesses: this checkout first, a shared viewer cache."""
    out = dict(os.environ)
    out["PYTHONPATH"] = str(REPO) + (os.pathsep + out["PYTHONPATH"] if out.get("PYTHONPATH") else "")
    out["XDG_CACHE_HOME"] = str(cache)
    return out


def cli(cache: Path, *args, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run `multirace ARGS` in a subprocess."""
    return subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True, timeout=timeout,
                          env=env(cache))


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def agent_file(path: Path, seed: int, name: str = "agent") -> Path:
    """A small valid agent file (its bytes differ with the seed)."""
    space = load_action_space(None)
    torch.manual_seed(seed)
    return save_agent(path, build_net(SMALL, (120, 160, 1), space), make_metadata(space, SMALL, name))


def copy_league(source: Path, dest: Path) -> Path:
    shutil.copytree(source, dest, ignore=shutil.ignore_patterns("run.lock", "videos"))
    return dest


class Process:
    """A `multirace ...` subprocess that runs until stopped (SIGTERM) or killed (SIGKILL)."""

    def __init__(self, cache: Path, *args, log: Path):
        self.log = open(log, "ab")
        self.proc = subprocess.Popen(CLI + [str(a) for a in args], stdout=self.log, stderr=subprocess.STDOUT,
                                     env=env(cache), start_new_session=True)

    def kill(self) -> None:
        """SIGKILL, as a crash or an OOM kill would (its own children, e.g. workers, are left running)."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


class Server(Process):
    """`multirace league serve DIR` on a free port of 127.0.0.1, up once its API answers."""

    def __init__(self, cache: Path, folder: Path, *extra, log: Path):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        super().__init__(cache, "league", "serve", folder, "--port", self.port, *extra, log=log)
        deadline = time.monotonic() + 180
        while True:
            try:
                if request("GET", self.url + "/api/leaderboard")[0] == 200:
                    return
            except OSError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"league serve did not start: {Path(log).read_text()[-2000:]}")
            time.sleep(0.3)


def request(method: str, url: str, body=None, headers: dict | None = None, timeout: float = 180):
    """(status, headers as a dict with lower-case names, body bytes) of one HTTP request."""
    rest = url.split("://", 1)[1]
    hostport, _, path = rest.partition("/")
    host, port = hostport.split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=timeout)
    try:
        chunked = body is not None and not isinstance(body, (bytes, str))
        conn.request(method, "/" + path, body=body, headers=headers or {}, encode_chunked=chunked)
        response = conn.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        conn.close()


def get_json(url: str):
    status, _, body = request("GET", url)
    assert status == 200, (url, status, body[:300])
    return json.loads(body)


def multipart(fields: dict, files: dict) -> tuple[bytes, str]:
    """A multipart/form-data body and its content type; files map a field to (filename, bytes)."""
    boundary = uuid.uuid4().hex
    parts = []
    for name, value in fields.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode())
    for name, (filename, data) in files.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="{filename}"\r\n'
                     f'Content-Type: application/octet-stream\r\n\r\n'.encode() + data + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def upload(url: str, token: str | None, data: bytes, filename: str = "agent.pt"):
    """POST an agent file to the JSON API as multipart; (status, parsed JSON)."""
    body, kind = multipart({}, {"file": (filename, data)})
    headers = {"Content-Type": kind}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    status, _, answer = request("POST", url + "/api/submissions", body, headers)
    return status, json.loads(answer)


def wait_until(predicate, timeout: float, what: str, every: float = 1.0):
    """Poll `predicate` until it returns a true value (returned) or `timeout` s pass (AssertionError)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)
