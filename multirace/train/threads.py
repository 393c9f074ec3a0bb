"""How many torch threads a learner's update may use on this machine now."""
from __future__ import annotations

import os


def default_threads() -> int:
    """Torch threads for training: every core on an idle machine, else 1.

    On a busy machine several torch threads spin against other processes and a
    training step gets many times slower than on one thread (a small CNN's
    update step: 25 ms on one thread, 580 ms on two, with the cores shared).
    """
    cores = os.cpu_count() or 1
    try:
        busy = os.getloadavg()[0] > 0.5
    except OSError:
        busy = False
    return 1 if busy else cores


def update_threads(requested: int) -> int:
    """`requested` threads for an update while the workers wait, or 1 where other processes hold the cores."""
    return max(1, min(int(requested), default_threads()))
