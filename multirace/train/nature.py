"""Nature as an adversary over model uncertainty, after Zhang et al. (NeurIPS 2020).

Robust Markov games with model uncertainty: the agents face a "nature" player
that picks the environment model from an uncertainty set, and a robust policy
maximises its worst-case value over that set. We approximate the inner
minimisation per episode: every env episode draws one perturbation from a
finite uncertainty set (action noise, friction/speed gain, steering offset,
camera pose, lighting, sensor noise), with probabilities biased toward the
perturbations on which the current policy does worst (a softmax over minus the
running mean of laps driven per training episode, mixed with uniform so every
element keeps being visited and its estimate stays fresh).

Also here: `scale_randomization` (shrink a `Randomization` toward the identity)
and `curriculum_scale` (the domain-randomisation curriculum).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..environment.randomize import Randomization

# (name, randomize config): each element is one model the adversary may pick for an episode.
UNCERTAINTY_SET = [
    ("nominal", None),
    ("action_noise", {"steer_noise_scale": (3.0, 5.0), "speed_noise_scale": (2.0, 3.0)}),
    ("low_grip", {"grip": (0.65, 0.8)}),  # a dusty track: the tyres give up earlier
    ("weak_motor", {"motor": (0.6, 0.75), "speed_gain": (0.9, 0.95)}),  # a tired battery
    ("steer_bias_left", {"steer_offset": (2.0, 4.0)}),
    ("steer_bias_right", {"steer_offset": (-4.0, -2.0)}),
    ("camera_pose", {"camera_yaw": (-0.05, 0.05), "camera_pitch": (-0.04, 0.04), "camera_height": (-0.015, 0.015)}),
    ("dark", {"brightness": (-60.0, -35.0), "contrast": (0.6, 0.8)}),
    ("bright", {"brightness": (35.0, 60.0), "contrast": (1.2, 1.5)}),
    ("sensor_noise", {"noise_sigma": (6.0, 12.0), "blur_prob": 0.5, "blur_kernels": (3, 5)}),
    ("shadows", {"shadow_prob": 0.6}),
    ("mild_everything", "mild"),
]
NAMES = [name for name, _ in UNCERTAINTY_SET]


def sample_perturbation(weights: np.ndarray, rng: np.random.Generator) -> int:
    """Index of the perturbation for one episode, drawn with probabilities `weights`."""
    p = np.asarray(weights, dtype=np.float64)
    p = p / p.sum() if p.sum() > 0 else np.full(len(p), 1.0 / len(p))
    return int(rng.choice(len(p), p=p))


class Nature:
    """The adversary: keeps per-perturbation performance, prefers the worst for the current policy."""

    def __init__(self, temperature: float = 1.0, uniform_mix: float = 0.3, decay: float = 0.9, seed: int = 0,
                 size: int | None = None):
        self.size = size or len(UNCERTAINTY_SET)
        self.temperature = float(temperature)
        self.uniform_mix = float(uniform_mix)
        self.decay = float(decay)
        self.score = np.zeros(self.size)  # running mean of laps per training episode
        self.count = np.zeros(self.size)

    def update(self, k: int, laps: float) -> None:
        """Record one finished training episode under perturbation k (laps driven before an off-track)."""
        if self.count[k] == 0:
            self.score[k] = laps
        else:
            self.score[k] = self.decay * self.score[k] + (1 - self.decay) * laps
        self.count[k] += 1

    def weights(self) -> np.ndarray:
        """Sampling probabilities: softmax of minus the normalised score, mixed with uniform."""
        seen = self.count > 0
        if not seen.any():
            return np.full(self.size, 1.0 / self.size)
        score = np.where(seen, self.score, self.score[seen].min())  # unseen: treat as the hardest seen
        spread = max(score.max() - score.min(), 1e-6)
        logits = -(score - score.min()) / spread / max(self.temperature, 1e-3) * 3.0
        soft = np.exp(logits - logits.max())
        soft /= soft.sum()
        return (1 - self.uniform_mix) * soft + self.uniform_mix / self.size

    def summary(self) -> dict:
        w = self.weights()
        worst = int(np.argmax(w))
        return {"worst": NAMES[worst] if worst < len(NAMES) else worst, "p_worst": round(float(w[worst]), 3)}


def scale_randomization(base: Randomization, scale: float) -> Randomization:
    """`base` with every range and probability moved toward the identity by `1 - scale` (0 = off)."""
    identity = Randomization()
    scale = float(min(max(scale, 0.0), 1.0))
    changes = {}
    for f in dataclasses.fields(Randomization):
        kind = f.metadata.get("kind")
        value, neutral = getattr(base, f.name), getattr(identity, f.name)
        if kind == "range":
            if f.name == "shadow_strength":
                continue
            changes[f.name] = tuple(n + scale * (v - n) for v, n in zip(value, neutral))
        elif kind == "scalar":
            changes[f.name] = neutral + scale * (value - neutral)
    return dataclasses.replace(base, **changes)


def curriculum_scale(fraction: float, ramp: float = 0.5) -> float:
    """Randomisation strength at a fraction of the budget: 0 at the start, full after `ramp`."""
    return float(min(1.0, max(0.0, fraction / ramp)))
