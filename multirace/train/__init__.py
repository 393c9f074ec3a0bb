"""Training: PPO with shared parameters (`ppo`; its rollout storage `rollout`, the run's bookkeeping `run`),
its config (`config`), the training env (`envs`), the robust options (`robust`): self-play opponent pools
(`selfplay`) and the nature adversary (`nature`), DAgger imitation (`imitate`), starting from an agent
file (`warmstart`), the declared track split (`splits`) and robustness evaluation (`evaluate`).

`PRESETS`, `TrainConfig` and `make_config` load on first use, so that the command line's parser
(which imports `multirace.train.cli`) does not import torch.
"""
from __future__ import annotations

import importlib

__all__ = ["PRESETS", "TrainConfig", "make_config"]


def __getattr__(name: str):
    if name in __all__:
        value = getattr(importlib.import_module("multirace.train.config"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'multirace.train' has no attribute {name!r}")
