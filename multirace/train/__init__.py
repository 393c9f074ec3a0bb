"""Training: PPO with shared parameters (`ppo`), its config (`config`), the training env (`envs`),
self-play opponent pools (`selfplay`), the nature adversary (`nature`) and robustness evaluation
(`evaluate`)."""
from .config import PRESETS, TrainConfig, make_config

__all__ = ["PRESETS", "TrainConfig", "make_config"]
