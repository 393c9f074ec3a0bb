"""Names as data: how a name that came from a file (an agent's, an entrant's) is shown anywhere."""
from __future__ import annotations

import re
import unicodedata


_CONTROL = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]|\x1b\][^\x07\x1b]*(?:\x07|\x1b\\)?|[\x00-\x1f\x7f-\x9f]")
# what does not show as itself: controls, format characters (right-to-left overrides and isolates, zero-width
# spaces and joiners, the byte-order mark), lone surrogates, line and paragraph separators
_HIDDEN = {"Cc", "Cf", "Cs", "Zl", "Zp"}
NAME_LENGTH = 64
TEXT_LENGTH = 400  # reasons, events and paths get more room than names


def display_name(name, limit: int = NAME_LENGTH) -> str:
    """A name (or any text from a file) as plain text to show anywhere: terminal escapes (ANSI, OSC), control
    and format characters (U+202E right-to-left override, zero-width characters: Unicode categories Cc, Cf)
    removed, at most `limit` characters; what is shown is what can be read. Names come from agent files,
    replays and leagues, which anyone can write."""
    text = _CONTROL.sub("", str(name))
    text = "".join(ch for ch in text if unicodedata.category(ch) not in _HIDDEN).strip()
    return (text[:limit - 1] + "…") if len(text) > limit else (text or "?")


def laps_text(laps) -> str:
    """"1 lap", "3 laps"."""
    return f"{laps} lap" + ("" if laps == 1 else "s")
