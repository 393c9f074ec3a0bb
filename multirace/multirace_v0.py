"""multirace in PettingZoo's module idiom: `from multirace import multirace_v0`.

`multirace_v0.env(**kwargs)` is the AEC form, `multirace_v0.parallel_env(**kwargs)`
the parallel one, `multirace_v0.raw_env` the env class; `max_cycles` sets the
step limit as in PettingZoo's own environments. Keywords: see `RaceEnv`.
"""
from __future__ import annotations

from .environment.race_env import RaceEnv, env, parallel_env

raw_env = RaceEnv
metadata = RaceEnv.metadata

__all__ = ["env", "metadata", "parallel_env", "raw_env"]
