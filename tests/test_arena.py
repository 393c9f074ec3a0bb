"""The shared image arena between a race and its replay writer: what the race puts is what the writer reads,
space comes back only when the writer releases it, and a full arena refuses rather than overwrites."""
from __future__ import annotations

import os

import numpy as np
import pytest

from multirace.recording.arena import ALIGN, ImageArena


@pytest.fixture
def arenas():
    """The race's arena and the writer's mapping of the same memory (as the writer process maps it)."""
    race = ImageArena.create(4 * 19_200 + 3 * ALIGN)
    writer = ImageArena(os.dup(race.fd), race.size)
    yield race, writer
    race.close()
    writer.close()


def frame(value: int) -> np.ndarray:
    return np.full((120, 160), value, np.uint8) + np.arange(160, dtype=np.uint8)


def test_the_writer_reads_what_the_race_put(arenas):
    race, writer = arenas
    rgb = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    where_grey, where_rgb = race.put([frame(7), frame(8)]), race.put([rgb[:40]])
    np.testing.assert_array_equal(writer.image(where_grey), np.stack([frame(7), frame(8)]))
    np.testing.assert_array_equal(writer.image(where_rgb), rgb[None, :40])
    assert writer.image(where_rgb).shape == (1, 40, 160, 3) and where_rgb.start % ALIGN == 0


def test_a_full_arena_refuses_until_the_writer_releases_and_then_wraps(arenas):
    race, writer = arenas
    placed = [race.put([frame(k)]) for k in range(4)]
    assert all(placed)
    assert race.put([frame(9)]) is None  # no room: the caller sends this one another way, nothing is overwritten
    for k, where in enumerate(placed):
        np.testing.assert_array_equal(writer.image(where)[0], frame(k))
    writer.release(placed[1].end)  # the first two read
    assert race.put([frame(10), frame(11), frame(12)]) is None  # room for two: the three are refused together
    again = race.put([frame(10), frame(11)])
    assert again is not None and race.put([frame(12)]) is None
    assert again.start // race.size == 1 and again.start % race.size == 0  # at the ring's start again
    for k, where in ((2, placed[2]), (3, placed[3])):
        np.testing.assert_array_equal(writer.image(where)[0], frame(k))
    np.testing.assert_array_equal(writer.image(again), np.stack([frame(10), frame(11)]))


def test_images_larger_than_the_arena_are_refused(arenas):
    race, _ = arenas
    assert race.put([np.zeros(race.size + 1, np.uint8)]) is None
    assert race.put([frame(1)] * 5) is None  # four fit, not five
    assert race.put([frame(1)]) is not None  # and the arena is as it was
