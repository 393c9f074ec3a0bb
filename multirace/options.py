"""Command-line arguments checked as they are parsed, before any work starts; every error names its option.

The checks are argparse `type=` functions: argparse names the option in the message
(`argument --minutes: must be above 0, got -1`), and `Parser` prints that as one line.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from pathlib import Path


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (`multirace race: error: argument --laps: ...`); the usage
    is one `--help` away. Subcommands' parsers are of this class too."""

    def error(self, message):
        sys.stderr.write(f"{self.prog}: error: {message} (see {self.prog} --help)\n")
        sys.exit(2)


class HelpLater:
    """An argument's help text built only when help is shown, for text whose parts import heavy modules (the bot
    registry's kinds): building the parser stays light. Gives argparse what it uses of a help string."""

    def __init__(self, build):
        self._build = build

    def strip(self) -> str:
        return "(help)"  # argparse only asks whether the text is empty

    def __mod__(self, params) -> str:
        return self._build() % params


def _number(text: str, kind):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                         f"got {text!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def number(kind=float, minimum=None, above=None, maximum=None):
    """A `type=` for a number of `kind` (int or float) in a range: `minimum` and `maximum` inclusive, `above`
    exclusive."""
    def check(text: str):
        value = _number(text, kind)
        if ((minimum is not None and value < minimum) or (above is not None and value <= above)
                or (maximum is not None and value > maximum)):
            low = f"at least {minimum}" if minimum is not None else f"above {above}" if above is not None else ""
            high = f"at most {maximum}" if maximum is not None else ""
            raise argparse.ArgumentTypeError(f"must be {' and '.join(p for p in (low, high) if p)}, got {text}")
        return value
    check.__name__ = "number"
    return check


POSITIVE_INT = number(int, minimum=1)
COUNT = number(int, minimum=0)  # a count that may be 0
SEED = number(int, minimum=0, maximum=2**32 - 1)
POSITIVE = number(float, above=0)
NON_NEGATIVE = number(float, minimum=0)
SHARE = number(float, minimum=0, maximum=1)


def output_file(text: str) -> str:
    """A `type=` for a file to write: refused now if it is a folder, or if its folder (or the nearest one
    that exists: missing ones are made) cannot take a new file (read-only, /proc, no permission)."""
    path = Path(text)
    if not text or path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a folder; give a file name")
    folder = path.absolute().parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {folder} is a file, not a folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot be written (permission denied)")
    try:  # what the filesystem says, not what the mode bits say (root, read-only mounts, /proc)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".multirace-probe-"):
            pass
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"{text}: cannot be written in {folder} "
                                         f"({exc.strerror or exc})") from None
    return text


def input_file(text: str) -> str:
    """A `type=` for a file to read: it must exist and be a file (not a folder)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a folder, not a file")
    return text
