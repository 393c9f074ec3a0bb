"""Opponent pool for self-play (placeholder, see below)."""
from __future__ import annotations


class OpponentPool:
    def __init__(self, *args, **kwargs):
        raise NotImplementedError("the opponent pool is not built yet")
