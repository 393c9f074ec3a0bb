"""multirace: multi-car DeepRacer racing for multi-agent reinforcement learning.

The public names are loaded on first use, so that `import multirace` (and the
command line's `--help`) stays light.
"""
from __future__ import annotations

import importlib

_PUBLIC = {  # public name: module (and the module's own name for it, where they differ)
    "load_agent": ("multirace.racing.policy", "load_policy"),
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
        module, attribute = _PUBLIC[name] if isinstance(_PUBLIC[name], tuple) else (_PUBLIC[name], name)
        value = getattr(importlib.import_module(module), attribute)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'multirace' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
