"""`multirace train --engine rllib`: not built yet.

The plan (see multirace/train/README.md): wrap the env with
``ray.rllib.env.wrappers.pettingzoo_env.ParallelPettingZooEnv``, register it,
and train one shared policy (``policy_mapping_fn=lambda agent_id, *a, **k:
"shared"``) with PPO and ``num_env_runners`` workers; pointing
``ray.init(address=...)`` at a cluster scales it out.
"""
from __future__ import annotations


def train_rllib(args) -> int:
    try:
        import ray  # noqa: F401
        from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv  # noqa: F401
    except ImportError:
        raise ValueError("--engine rllib needs Ray RLlib, which is not installed here "
                         "(pip install 'ray[rllib]'); use --engine local (the default)") from None
    raise ValueError("--engine rllib: the RLlib trainer is not implemented yet in this version; "
                     "use --engine local (the default)")
