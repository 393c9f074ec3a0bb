"""DeepRacer's action noise, drawn in blocks: the same numbers as a draw per step, at a fraction of the cost.

A numpy `Generator` call costs about a microsecond whatever it draws, so the
env's steering and speed noise (a standard normal pair per car per step) is
drawn for many steps at once. A block of k draws of one shape is exactly the
k draws made one at a time (the generator fills arrays value by value), so
the races are the same; `settle` leaves the generator where the draws one at a
time would have, before anything else draws from it. A block is kept as one
flat list of floats: a nested list per draw would be thousands of small lists
living for hundreds of steps, which the garbage collector's generations
promote until a full collection of the whole process (tens of milliseconds)
runs every few thousand steps.
"""
from __future__ import annotations

import numpy as np

BLOCK_STEPS = 256  # steps of noise drawn at once


class NoiseBlocks:
    """Standard normal draws of `shape` from `rng`: `next()` gives one draw as a flat list of floats in C order,
    the values of ``rng.standard_normal(shape).ravel().tolist()`` per call."""

    def __init__(self, rng: np.random.Generator, shape: tuple[int, ...]):
        self.rng, self.shape = rng, shape
        self._size = int(np.prod(shape))  # values per draw
        self._block: list = []  # the block's draws, one flat list
        self._used = 0  # draws given from it
        self._state_before = None  # the generator's state before the block was drawn

    def next(self) -> list:
        """The next draw."""
        size, used = self._size, self._used
        if used * size == len(self._block):
            self._state_before = self.rng.bit_generator.state
            self._block = self.rng.standard_normal((BLOCK_STEPS, *self.shape)).ravel().tolist()
            used = 0
        self._used = used + 1
        return self._block[used * size:(used + 1) * size]

    def settle(self) -> None:
        """Put the generator where drawing one `shape` per `next` call would have left it (the block's unused
        draws given back), before anything else draws from it."""
        if self._state_before is not None:
            self.rng.bit_generator.state = self._state_before
            self.rng.standard_normal((self._used, *self.shape))
        self._block, self._used, self._state_before = [], 0, None
