"""Training throughput for `multirace bench`: agent-steps/s of the full PPO loop (sampling + updates)."""
from __future__ import annotations

import tempfile
from pathlib import Path


def training_throughput(seconds: float = 40.0, preset: str = "fast", track: str = "reinvent_base",
                        **overrides) -> dict:
    """Run the default training loop for about `seconds` on 2 worker processes and time it.

    Steady state: the first iteration (worker start-up, first allocations) is left out. Returns
    ``{"agent_steps_per_s", "sampling_agent_steps_per_s", "update_agent_steps_per_s", "sampling_share",
    "update_share", "cpu_us_per_agent_step", "iterations", "num_envs", "cars_per_env", "batch", "network"}``
    (the shares: of the run's wall time; with the overlapped update they add up to more than 1).
    """
    from .config import make_config
    from .ppo import train

    config = make_config(preset, tracks=(track,), minutes=seconds / 60.0, progress=False, eval_every=0,
                         checkpoint_every=1e9, **overrides)
    with tempfile.TemporaryDirectory() as folder:
        summary = train(config, Path(folder) / "bench.pt", log=None)
    history = summary["history"]
    cpu_per_step = None
    if len(history) >= 2:
        steps = history[-1]["agent_steps"] - history[0]["agent_steps"]
        wall = history[-1]["elapsed"] - history[0]["elapsed"]
        rate = steps / max(wall, 1e-9)
        if history[0].get("cpu_seconds") is not None:
            cpu_per_step = (history[-1]["cpu_seconds"] - history[0]["cpu_seconds"]) / max(steps, 1)
    else:
        rate = summary["steps_per_s"]
    steps_total = max(summary["agent_steps"], 1)
    return {"agent_steps_per_s": round(rate, 1),
            "sampling_agent_steps_per_s": round(steps_total / max(summary["sample_seconds"], 1e-9), 1),
            "update_agent_steps_per_s": round(steps_total / max(summary["update_seconds"], 1e-9), 1),
            "sampling_share": round(summary["sample_seconds"] / max(summary["wall_seconds"], 1e-9), 3),
            "update_share": round(summary["update_seconds"] / max(summary["wall_seconds"], 1e-9), 3),
            # CPU time of the learner and the workers per agent-step: what the loop costs, however busy the
            # machine (the wall-clock rate above also depends on how much of the cores the loop got)
            "cpu_us_per_agent_step": None if cpu_per_step is None else round(1e6 * cpu_per_step, 1),
            "iterations": summary["iterations"], "num_envs": config.num_envs,
            "cars_per_env": config.cars_per_env, "batch": config.batch_size, "network": config.network}
