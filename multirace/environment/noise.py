"""DeepRacer's action noise, drawn in blocks: the same numbers as a draw per step, at a fraction of the cost.

A numpy `Generator` call costs about a microsecond whatever it draws, so the
env's steering and speed noise (a standard normal pair per car per step) is
drawn for many steps at once. A block of k draws of one shape is exactly the
k draws made one at a time (the generator fills arrays value by value), so
the races are the same; `settle` leaves the generator where the draws one at a
time would have, before anything else draws from it.
"""
from __future__ import annotations

import numpy as np

BLOCK_STEPS = 256  # steps of noise drawn at once


class NoiseBlocks:
    """Standard normal draws of `shape` from `rng`: `next()` gives one draw (nested lists of floats), the same
    values in the same order as ``rng.standard_normal(shape).tolist()`` per call."""

    def __init__(self, rng: np.random.Generator, shape: tuple[int, ...]):
        self.rng, self.shape = rng, shape
        self._block: list = []
        self._used = 0
        self._state_before = None  # the generator's state before the block was drawn

    def next(self) -> list:
        """The next draw."""
        if self._used == len(self._block):
            self._state_before = self.rng.bit_generator.state
            self._block = self.rng.standard_normal((BLOCK_STEPS, *self.shape)).tolist()
            self._used = 0
        draw = self._block[self._used]
        self._used += 1
        return draw

    def settle(self) -> None:
        """Put the generator where drawing one `shape` per `next` call would have left it (the block's unused
        draws given back), before anything else draws from it."""
        if self._state_before is not None:
            self.rng.bit_generator.state = self._state_before
            self.rng.standard_normal((self._used, *self.shape))
        self._block, self._used, self._state_before = [], 0, None
