"""The PPO policy: the net's outputs as a distribution over the action space, and the net's forward pass."""
from __future__ import annotations

import math

import torch
from torch.distributions import Categorical, Normal


class Policy:
    """Turns the net's outputs into a distribution over the action space (discrete or Gaussian)."""

    def __init__(self, space):
        self.space = space
        self.discrete = space.discrete

    def dist(self, out: torch.Tensor):
        if self.discrete:
            return Categorical(logits=out, validate_args=False)
        return Normal(out[:, :2], torch.exp(torch.clamp(out[:, 2:], -5.0, 2.0)), validate_args=False)

    def sample(self, out: torch.Tensor, generator=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(actions, their log-probabilities) drawn from the distribution of the net's outputs `out`, with
        `generator` (torch's global one if None); the same law as `dist(out).sample()`, without building it."""
        if self.discrete:
            logp = torch.log_softmax(out, -1)
            action = torch.multinomial(logp.exp(), 1, generator=generator)
            return action.squeeze(1), logp.gather(1, action).squeeze(1)
        mean, log_std = out[:, :2], torch.clamp(out[:, 2:], -5.0, 2.0)
        noise = torch.randn(mean.shape, generator=generator)
        logp = -0.5 * noise.square() - log_std - 0.5 * math.log(2 * math.pi)
        return mean + log_std.exp() * noise, logp.sum(-1)

    def log_prob(self, dist, actions):
        lp = dist.log_prob(actions)
        return lp if self.discrete else lp.sum(-1)

    def entropy(self, dist):
        ent = dist.entropy()
        return ent if self.discrete else ent.sum(-1)


def forward(net, x, pooled: bool, bfloat16: bool = False):
    """The net's (outputs, value) for input `x`, images pooled by the workers if `pooled`; with `bfloat16`
    computed in bfloat16 (torch's CPU autocast) and returned as float32."""
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bfloat16):
        out, value = net.forward_all(x, pooled=True) if pooled else net.forward_all(x)
    if bfloat16:
        out, value = out.float(), None if value is None else value.float()
    return out, value
