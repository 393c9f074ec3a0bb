"""Robust training: what `--robust` switches on (each can still be set on its own with --set KEY=VALUE),
and `RobustKnobs`, the hooks of those options in the PPO loop."""
from __future__ import annotations

import numpy as np

ROBUST = {
    "curriculum": True,  # domain randomisation ramped from none to `randomize` over the first half
    "randomize": "mild",  # the randomisation reached at the end of the curriculum
    "opponent_pool": True,  # a quarter of the cars driven by past snapshots / shipped agents, PFSP
    "nature": True,  # half the episodes: a perturbation chosen by the nature adversary
    "procedural_tracks": 6,  # seeded generated tracks added to the training tracks
    "reverse": "both",  # both directions
}


def apply_robust(config, explicit=()) -> None:
    """Turn on the robust options in `config`, leaving settings given explicitly alone."""
    config.robust = True
    for key, value in ROBUST.items():
        if key in explicit:
            continue
        if key == "reverse" and config.reverse != "no":
            continue
        setattr(config, key, value)


class RobustKnobs:
    """The robust options' hooks in the PPO loop: the randomisation curriculum and nature's choice of
    perturbations (knobs shared with the env workers), and the opponent pool (which drives some cars)."""

    def __init__(self, config, seed: int):
        from .nature import Nature

        self.config = config
        self.nature = Nature(temperature=config.nature_temperature, seed=seed) if config.nature else None
        self.shared = None
        self.pool = None
        if config.curriculum or self.nature is not None:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            self.shared = {"scale": ctx.Value("d", 0.0 if config.curriculum else 1.0)}
            if self.nature is not None:
                self.shared["nature"] = ctx.Array("d", self.nature.weights().tolist())

    def start_pool(self, space, image_shape, rng, vector_inputs: dict) -> None:
        """The opponent pool, once the observation shape (and the sensors beside the camera) is known."""
        if self.config.opponent_pool:
            from .selfplay import OpponentPool

            self.pool = OpponentPool(self.config, space, image_shape, rng, vector_inputs=vector_inputs)

    def before_iteration(self, fraction: float, envs: int, cars: int):
        """Set this iteration's knobs; returns which cars the learner drives (the pool drives the rest)."""
        from .nature import curriculum_scale

        if self.shared is not None and self.config.curriculum:
            self.shared["scale"].value = curriculum_scale(fraction)
        if self.nature is not None:
            self.shared["nature"][:] = self.nature.weights().tolist()
        return self.pool.assign(envs, cars) if self.pool is not None else np.ones((envs, cars), bool)

    def opponent_commands(self, obs, learner_mask):
        """The pool's opponents' commands for their cars (`OpponentPool.commands`), None without a pool."""
        return self.pool.commands(obs, learner_mask) if self.pool is not None else None

    def after_step(self, infos, rewards, env_done) -> None:
        """Let the pool score its opponents."""
        if self.pool is None:
            return
        for e, env_infos in enumerate(infos):
            for a, info in enumerate(env_infos):
                self.pool.observe(e, a, info, float(rewards[e, a]))
        if env_done.any():
            self.pool.episode_end(env_done)

    def after_iteration(self, episodes) -> dict:
        """Tell nature how the learner fared under each perturbation; the knobs' summaries for the history."""
        extra = {}
        if self.nature is not None:
            for ep in episodes:
                if ep["learner"] and ep["perturbation"] >= 0:
                    self.nature.update(ep["perturbation"], ep["laps"])
        if self.pool is not None:
            extra["pool"] = self.pool.summary()
        if self.nature is not None:
            extra["nature"] = self.nature.summary()
        return extra

    def snapshot(self, net, elapsed: float, iteration: int) -> None:
        """Add the learner to the pool when a snapshot is due."""
        if self.pool is not None and self.pool.due(elapsed):
            self.pool.add_snapshot(net, f"snapshot_{iteration}")
