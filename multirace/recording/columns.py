"""The replay's columns for rerun's `send_columns`, built straight in Arrow.

rerun's archetype helpers (`rr.Scalars.columns`, `rr.Transform3D.columns`, `rr.TimeColumn`, ...) check and
convert their inputs value by value, which costs about 100 microseconds a call: most of the writer's time
per block of columns, and most of what a race waits for at its end. The replay's columns are always the
same few kinds from numpy arrays of known types, so they are built here as the very Arrow arrays rerun
builds (tests/test_replay_columns.py compares them), wrapped in rerun's public column protocols
(`TimeColumnLike`, `ComponentBatchLike`).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import rerun as rr

BLOB_TYPE = pa.list_(pa.field("item", pa.uint8(), nullable=False))  # rerun's `Blob` component
TRANSLATION_TYPE = pa.list_(pa.field("item", pa.float32(), nullable=False), 3)
QUATERNION_TYPE = pa.list_(pa.field("item", pa.float32(), nullable=False), 4)
SCALARS = rr.Scalars.descriptor_scalars()
TRANSLATION = rr.Transform3D.descriptor_translation()
QUATERNION = rr.Transform3D.descriptor_quaternion()
BLOB = rr.EncodedImage.descriptor_blob()
MEDIA_TYPE = rr.EncodedImage.descriptor_media_type()


class _Time:
    """A time line's column (rerun's `TimeColumnLike`)."""

    def __init__(self, name: str, values: pa.Array):
        self.name, self.values = name, values

    def timeline_name(self) -> str:
        return self.name

    def as_arrow_array(self) -> pa.Array:
        return self.values


class _Component:
    """A component's column, one value per row (rerun's `ComponentBatchLike`)."""

    def __init__(self, descriptor, values: pa.Array):
        self.descriptor = descriptor
        self.values = pa.ListArray.from_arrays(pa.array(np.arange(len(values) + 1, dtype=np.int32)), values)

    def component_descriptor(self):
        return self.descriptor

    def as_arrow_array(self) -> pa.Array:
        return self.values


def time_index(steps: np.ndarray, times: np.ndarray) -> list:
    """The ``step`` (sequence) and ``race_time`` (duration, seconds) columns of some rows."""
    nanoseconds = (np.asarray(times, np.float64) * 1e9).astype("timedelta64[ns]")
    return [_Time("step", pa.array(np.asarray(steps, np.int64), pa.int64())),
            _Time("race_time", pa.array(nanoseconds, pa.duration("ns")))]


def transform_columns(translations: np.ndarray, quaternions: np.ndarray) -> list:
    """`Transform3D` columns of rows of (x, y, z) translations and (x, y, z, w) quaternions."""
    return [_Component(TRANSLATION, _fixed_size(translations, TRANSLATION_TYPE)),
            _Component(QUATERNION, _fixed_size(quaternions, QUATERNION_TYPE))]


def scalar_columns(values: np.ndarray) -> list:
    """The `Scalars` column of one value per row."""
    return [_Component(SCALARS, pa.array(np.asarray(values, np.float64)))]


def image_columns(blobs: list[bytes], media_type: str) -> list:
    """`EncodedImage` columns of one encoded image (bytes of `media_type`) per row."""
    offsets = np.zeros(len(blobs) + 1, np.int32)
    np.cumsum([len(blob) for blob in blobs], out=offsets[1:])
    data = pa.array(np.frombuffer(b"".join(blobs), np.uint8))
    images = pa.ListArray.from_arrays(pa.array(offsets), data, type=BLOB_TYPE)
    return [_Component(BLOB, images), _Component(MEDIA_TYPE, pa.array([media_type] * len(blobs), pa.utf8()))]


def _fixed_size(rows: np.ndarray, arrow_type: pa.DataType) -> pa.FixedSizeListArray:
    values = np.ascontiguousarray(rows, np.float32).reshape(-1)
    return pa.FixedSizeListArray.from_arrays(pa.array(values), type=arrow_type)
