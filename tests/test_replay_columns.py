"""The replay's columns, built straight in Arrow (`recording.columns`), are exactly the arrays rerun's own
archetype helpers build from the same values: same descriptors, same Arrow types, same values."""
from __future__ import annotations

import numpy as np
import rerun as rr

from multirace.recording import columns

RNG = np.random.default_rng(0)


def arrays(column_list) -> list:
    return [(c.component_descriptor(), c.as_arrow_array()) for c in column_list]


def assert_same_columns(ours, theirs):
    assert len(ours) == len(theirs)
    for (our_descriptor, our_array), (their_descriptor, their_array) in zip(arrays(ours), arrays(theirs)):
        assert our_descriptor == their_descriptor
        assert our_array.type == their_array.type, our_descriptor
        assert our_array.equals(their_array), our_descriptor


def test_time_index_is_rerun_time_columns():
    steps, times = np.arange(3, 40, 2), np.arange(3, 40, 2) / 15.0
    ours = columns.time_index(steps, times)
    theirs = [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("race_time", duration=times)]
    for our, their in zip(ours, theirs):
        assert our.timeline_name() == their.timeline_name()
        assert our.as_arrow_array().type == their.as_arrow_array().type
        assert our.as_arrow_array().equals(their.as_arrow_array())


def test_transforms_scalars_and_images_are_rerun_columns():
    translations, quaternions = RNG.normal(size=(17, 3)), RNG.normal(size=(17, 4))
    assert_same_columns(columns.transform_columns(translations, quaternions),
                        rr.Transform3D.columns(translation=translations, quaternion=quaternions))
    values = RNG.normal(size=17)
    values[3] = np.inf
    assert_same_columns(columns.scalar_columns(values), rr.Scalars.columns(scalars=values))
    blobs = [RNG.integers(0, 256, size).astype(np.uint8).tobytes() for size in (5, 0, 300, 1)]
    assert_same_columns(columns.image_columns(blobs, "image/jpeg"),
                        rr.EncodedImage.columns(blob=[np.frombuffer(b, np.uint8) for b in blobs],
                                                media_type=["image/jpeg"] * len(blobs)))
