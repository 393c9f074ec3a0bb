"""Written outputs: every file the project writes appears complete or not at all.

A file is written to a hidden temporary file beside its target, flushed to disk, and renamed over the
target only when it is complete (`os.replace`, atomic on one filesystem). On any failure the temporary
file is removed and the target, if it existed, is left exactly as it was::

    with AtomicOutput("model.tar.gz") as tmp:   # tmp: the path to write to
        write_archive(tmp)
    write_bytes("table.csv", data)              # the same for bytes or text in hand
"""
from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path


class OutputError(OSError):
    """An output file could not be written (full disk, no permission, ...); the message names the file, and
    any previous file of that name is unchanged."""


def output_error(target, exc: BaseException) -> OutputError:
    """The one-line OutputError for `target` from the error that stopped its writing."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
    return OutputError(f"{target}: not written ({reason}); any previous file there is unchanged")


class AtomicOutput:
    """One output file being written: write to `tmp`, then `commit()` (or leave the `with` block) to put it
    in place, or `discard()` to drop it. Errors of the filesystem become one OutputError naming the target."""

    def __init__(self, target):
        self.target = Path(target)
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise output_error(self.target, exc) from None
        # hidden and unique; ends in .tmp so that no glob for the target's kind (*.pt, *.rrd) sees it: a
        # writer that picks a format by suffix must be told the format
        self.tmp = self.target.with_name(f".{self.target.name}.{secrets.token_hex(4)}.tmp")

    def commit(self) -> Path:
        """Flush the finished temporary file to disk and rename it over the target (keeping the permissions
        of a file it replaces)."""
        try:
            fd = os.open(self.tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            if self.target.is_file():
                os.chmod(self.tmp, self.target.stat().st_mode & 0o7777)
            os.replace(self.tmp, self.target)
        except OSError as exc:
            self.discard()
            raise output_error(self.target, exc) from None
        _fsync_folder(self.target.parent)
        return self.target

    @contextlib.contextmanager
    def guard(self, *errors):
        """`with output.guard():` a writer's failure inside (an OSError, or one of `errors` for libraries
        that report a full disk otherwise) drops the temporary file and becomes one OutputError."""
        try:
            yield
        except OutputError:
            self.discard()
            raise
        except (OSError, *errors) as exc:
            self.discard()
            raise output_error(self.target, exc) from None

    def discard(self) -> None:
        """Remove the temporary file, if any (the target is untouched)."""
        try:
            self.tmp.unlink(missing_ok=True)
        except OSError:
            pass

    def __enter__(self) -> Path:
        return self.tmp

    def __exit__(self, kind, exc, tb) -> bool:
        if kind is None:
            self.commit()
            return False
        self.discard()
        if isinstance(exc, OSError) and not isinstance(exc, OutputError):
            raise output_error(self.target, exc) from None
        return False


def _fsync_folder(folder: Path) -> None:
    """Make a rename in `folder` durable where the platform allows it (not on Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_bytes(target, data: bytes) -> Path:
    """Write `data` to `target` atomically; returns the target path."""
    with AtomicOutput(target) as tmp:
        tmp.write_bytes(data)
    return Path(target)


def write_text(target, text: str) -> Path:
    """Write `text` (UTF-8) to `target` atomically; returns the target path."""
    return write_bytes(target, text.encode("utf-8"))
