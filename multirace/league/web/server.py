"""Serving a league's web app with uvicorn: loopback by default, a warning when bound to a network."""
from __future__ import annotations

import ipaddress
import sys

LOOPBACK_NAMES = {"localhost"}


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and localhost; False for every other address or name."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def serve(folder, host: str = "127.0.0.1", port: int = 8000, upload_limit: int | None = None,
          uploads_per_hour: int = 20) -> None:
    """Serve the league in `folder` until interrupted (Ctrl-C)."""
    import uvicorn

    from ..submissions import MAX_SUBMISSION_BYTES
    from .app import create_app

    if not is_loopback(host):
        print(f"multirace league serve: warning: serving on {host}, reachable from other machines; anyone who "
              "can reach it sees the league and can try tokens (put it behind HTTPS for a public network)",
              file=sys.stderr)
    app = create_app(folder, upload_limit=upload_limit or MAX_SUBMISSION_BYTES, uploads_per_hour=uploads_per_hour)
    shown = f"[{host}]" if ":" in host else host
    print(f"league {folder}: http://{shown}:{port}/ (Ctrl-C to stop)", file=sys.stderr, flush=True)
    uvicorn.run(app, host=host, port=port, log_level="warning", server_header=False,
                timeout_graceful_shutdown=5)
