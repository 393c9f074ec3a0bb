"""Block sums of camera images, the training workers' half of a net's first average pool (`nets.pool_image`).

A compiled kernel in its own module: races never pool, so they never load it (the first-compile notice looks
at every loaded module's kernels).
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def block_sums(rows, k, channels):
    """The int16 sums of the k x k pixel blocks of an image given as uint8 rows of W x `channels` interleaved
    values, (H, W * channels): (H // k, W // k * channels), interleaved the same way.

    The k rows of a block row are added into one row first (a contiguous, vectorisable loop), then each
    block's k columns.
    """
    height, values = rows.shape
    width = values // channels
    out = np.empty((height // k, (width // k) * channels), np.int16)
    row = np.empty(values, np.int16)
    for block_row in range(height // k):
        row[:] = 0
        for y in range(block_row * k, block_row * k + k):
            source = rows[y]
            for i in range(values):
                row[i] += source[i]
        for block in range(width // k):
            for c in range(channels):
                total = 0
                for x in range(block * k, block * k + k):
                    total += row[x * channels + c]
                out[block_row, block * channels + c] = total
    return out
