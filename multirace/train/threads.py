"""How a learner's update runs on this machine: how many torch threads, in which precision."""
from __future__ import annotations

import os

PRECISIONS = ("auto", "float32", "bfloat16")  # TrainConfig.update_precision


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


def update_in_bfloat16(precision: str) -> bool:
    """Whether an update of `precision` (`PRECISIONS`) runs its passes in bfloat16: "auto" does where the
    CPU has native bfloat16 instructions (AVX512-BF16, AMX; elsewhere it would be emulated, and slower)."""
    if precision == "auto":
        import torch

        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return precision == "bfloat16"
