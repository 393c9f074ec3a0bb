"""Which training run (track and direction) an env's next episode races on.

``uniform``: every run equally often. ``failures``: runs where the policy leaves the track more often are
raced more often (a failure-prioritised curriculum in the spirit of prioritised level replay, Jiang et
al. 2021): each run's score is a running mean of its off-tracks per lap, a run not raced yet counts as
the hardest seen, and a run is drawn with weight ``floor + score`` so that no run is ever dropped. Each
env worker keeps its own scores (no traffic between processes), so the choice depends only on that
worker's seeded episodes.
"""
from __future__ import annotations

import numpy as np

TRACK_SAMPLINGS = ("uniform", "failures")
FLOOR = 0.25  # weight every run keeps whatever its score (off-tracks per lap)
MEMORY = 0.5  # weight of a run's earlier score when an episode on it ends
CAP = 4.0  # off-tracks per lap above this count as this (one wild episode should not take over)


class RunSampler:
    """Draws run indices by `mode` (one of `TRACK_SAMPLINGS`) and learns each run's off-track rate."""

    def __init__(self, runs: int, mode: str = "uniform"):
        if mode not in TRACK_SAMPLINGS:
            raise ValueError(f"track_sampling: expected one of {', '.join(TRACK_SAMPLINGS)}, got {mode!r}")
        self.mode = mode
        self.scores = np.full(int(runs), np.nan)  # off-tracks per lap, running mean; NaN: not raced yet

    def weights(self) -> np.ndarray:
        """The probability of each run being drawn next."""
        if self.mode == "uniform":
            return np.full(len(self.scores), 1.0 / len(self.scores))
        seen = self.scores[~np.isnan(self.scores)]
        unseen = max(1.0, float(seen.max())) if len(seen) else 1.0
        weights = FLOOR + np.where(np.isnan(self.scores), unseen, self.scores)
        return weights / weights.sum()

    def pick(self, rng: np.random.Generator) -> int:
        """The next episode's run."""
        if self.mode == "uniform":  # as before this module existed: the same draws for the same seeds
            return int(rng.integers(len(self.scores)))
        return int(rng.choice(len(self.scores), p=self.weights()))

    def record(self, run: int, off_tracks: int, laps: float) -> None:
        """An episode on `run` ended with `off_tracks` off-tracks over `laps` laps (all its cars together)."""
        if laps <= 0.0 and off_tracks == 0:
            return
        rate = min(CAP, off_tracks / max(laps, 0.25))
        old = self.scores[run]
        self.scores[run] = rate if np.isnan(old) else MEMORY * old + (1.0 - MEMORY) * rate
