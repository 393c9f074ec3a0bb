"""multirace: multi-car DeepRacer racing for multi-agent reinforcement learning.

The public names are loaded on first use, so that `import multirace` (and the
command line's `--help`) stays light.
"""
from __future__ import annotations

import importlib

_PUBLIC = {
    "RaceEnv": "multirace.environment.race_env",
    "env": "multirace.environment.race_env",
    "parallel_env": "multirace.environment.race_env",
    "Track": "multirace.sim.tracks",
    "TrackError": "multirace.sim.tracks",
    "list_tracks": "multirace.sim.tracks",
    "load_track": "multirace.sim.tracks",
}

__all__ = sorted(_PUBLIC)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'multirace' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
