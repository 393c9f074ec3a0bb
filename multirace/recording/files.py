"""Input files of the recording commands (`plot`, `replay`): refused before they are opened unless regular."""
from __future__ import annotations

import stat
from pathlib import Path


def regular_file(path, what: str) -> Path:
    """`path` if it is a regular file; a one-line error naming it otherwise (a FIFO would block `open` and a
    device such as /dev/zero never ends: both are refused before they are opened)."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path}: no such file") from None
    except OSError as exc:
        raise ValueError(f"{what} {path}: cannot be read ({exc.strerror})") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{what} {path}: not a regular file (a folder, device, FIFO or socket)")
    return path
