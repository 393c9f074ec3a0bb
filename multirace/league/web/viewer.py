"""Rerun's web viewer, served by the league's app from this machine.

rerun-sdk ships its web viewer (index.html, re_viewer.js, re_viewer_bg.wasm) inside its native module and
hands it out through its own small web server. `viewer_assets()` starts that server once in a child process
on a free loopback port, copies the files into a cache folder (once per rerun version), and stops it; the
league's app then serves them under /viewer/. The page's links to web fonts are removed on the way, so
nothing loads from the internet; the viewer opens a replay given as `?url=`.
"""
from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

FILES = ("index.html", "re_viewer.js", "re_viewer_bg.wasm", "favicon.ico")
_REMOTE_LINKS = re.compile(r"<link\b[^>]*https?://[^>]*>", re.S)
SERVE = ("import sys, time, rerun as rr\n"
         "rr.serve_web_viewer(web_port=int(sys.argv[1]), open_browser=False)\n"
         "time.sleep(600)\n")


def _cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "multirace"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _fetch(port: int, name: str, deadline: float) -> bytes:
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/{name}", timeout=30) as response:
                return response.read()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def viewer_assets(cache: Path | None = None) -> Path:
    """The folder holding rerun's web viewer files for the installed rerun-sdk, fetched once into the cache."""
    import rerun

    folder = (cache or _cache_root()) / f"rerun-web-viewer-{rerun.__version__}"
    if all((folder / name).is_file() for name in FILES):
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    port = free_port()
    child = subprocess.Popen([sys.executable, "-c", SERVE, str(port)], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        for name in FILES:
            data = _fetch(port, name, deadline)
            if name == "index.html":
                data = _REMOTE_LINKS.sub("", data.decode()).encode()
            tmp = folder / f".{name}.{os.getpid()}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, folder / name)
    finally:
        child.kill()
        child.wait()
    return folder
