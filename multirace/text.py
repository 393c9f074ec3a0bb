"""Names as data: how a name that came from a file (an agent's, an entrant's) is shown anywhere."""
from __future__ import annotations

import re


_CONTROL = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]|\x1b\][^\x07\x1b]*(?:\x07|\x1b\\)?|[\x00-\x1f\x7f-\x9f]")
NAME_LENGTH = 64


def display_name(name, limit: int = NAME_LENGTH) -> str:
    """A name (or any text from a file) as plain text to show anywhere: terminal escapes (ANSI, OSC) and
    control characters removed, at most `limit` characters. Names come from agent files, which anyone can
    write."""
    text = _CONTROL.sub("", str(name)).strip()
    return (text[:limit - 1] + "…") if len(text) > limit else (text or "?")


def laps_text(laps) -> str:
    """"1 lap", "3 laps"."""
    return f"{laps} lap" + ("" if laps == 1 else "s")
