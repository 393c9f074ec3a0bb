"""Shared memory that carries camera images from a race to its replay writer without the socket.

A replay's camera images are most of what a race hands its writer (`replay_process`): sent through the
socket, each is copied into the kernel and out again. An `ImageArena` is a ring of memory that both processes
map (an anonymous file, its descriptor passed to the writer at its start): the race copies a step's images
into it once (`put`, the cars' images one after another) and sends only where they lie (an `ArenaImage`); the
writer reads them from there (`image`), encodes them and gives the space back (`release`). The first 8 bytes
hold how many bytes of the ring the writer has given back in all; positions count bytes written since the
arena was made, so they only grow, and a stale reading of the count by the race only makes it see less free
space. Images that do not fit in the free space are not waited for: `put` returns None and the race sends
them through the socket as before.
"""
from __future__ import annotations

import mmap
import os
import struct
import tempfile
from typing import NamedTuple

import numpy as np

HEADER_BYTES = 64  # the writer's count of released bytes, then padding to a cache line
RELEASED = struct.Struct("=q")  # that count, in the header
ALIGN = 64  # each image starts on a cache line (a power of 2)


class ArenaImage(NamedTuple):
    """Where images lie in the arena: their position (bytes written since the arena was made, before them),
    shape (how many, then one image's) and dtype, and the position after them (what the writer releases once
    it has read them)."""

    start: int
    shape: tuple
    dtype: str
    end: int


class ImageArena:
    """A ring of `size` bytes mapped from the open file `fd` (`create` makes one; the writer maps the same
    file with `ImageArena(fd, size)`)."""

    def __init__(self, fd: int, size: int):
        self.fd, self.size = fd, size
        # mapped with its pages in place (MAP_POPULATE), so that no race step waits on their first touch
        self._map = mmap.mmap(fd, HEADER_BYTES + size, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0))
        self._written = 0  # the race's side: bytes handed out so far (gaps at the ring's end included)

    @classmethod
    def create(cls, size: int) -> ImageArena:
        """A new arena in an anonymous file (memfd where the system has it, else an unlinked temporary file)."""
        if hasattr(os, "memfd_create"):
            fd = os.memfd_create("multirace-replay-images")
        else:
            fd = os.dup(tempfile.TemporaryFile().fileno())
        os.ftruncate(fd, HEADER_BYTES + size)
        return cls(fd, size)

    def put(self, images: list[np.ndarray]) -> ArenaImage | None:
        """Copy `images` (C-contiguous arrays of one shape and dtype, e.g. the cars' camera images of a step) one
        after another into the ring; where they lie (as one array of shape (len(images), *shape)), or None where
        the free space cannot take them now."""
        first, size = images[0], self.size
        nbytes = first.nbytes * len(images)
        start = (self._written + ALIGN - 1) & -ALIGN
        offset = start % size
        if offset + nbytes > size:  # not in one piece before the ring's end: start at its beginning
            start += size - offset
            offset = 0
        end = start + nbytes
        if end - RELEASED.unpack_from(self._map)[0] > size:
            return None
        at = HEADER_BYTES + offset
        for image in images:
            self._map[at:at + first.nbytes] = image  # (a slice of the map: fastest)
            at += first.nbytes
        self._written = end
        return ArenaImage(start, (len(images), *first.shape), first.dtype.str, end)

    def image(self, where: ArenaImage) -> np.ndarray:
        """The writer's side: the images at `where` as one array, a view of the ring (valid until it is
        released)."""
        dtype = np.dtype(where.dtype)
        count = (where.end - where.start) // dtype.itemsize
        return np.frombuffer(self._map, dtype, count, HEADER_BYTES + where.start % self.size).reshape(where.shape)

    def release(self, end: int) -> None:
        """The writer's side: give back the ring up to position `end` (every image before it has been read)."""
        RELEASED.pack_into(self._map, 0, max(RELEASED.unpack_from(self._map)[0], end))

    def close(self) -> None:
        """Unmap the ring and close its file."""
        self._map.close()
        os.close(self.fd)
