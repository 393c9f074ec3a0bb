"""`--robust`: what it switches on (each can still be set on its own with --set KEY=VALUE)."""
from __future__ import annotations

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
