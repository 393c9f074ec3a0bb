"""The project's declared track split: which real DeepRacer tracks training may use and which are held out.

Held-out tracks are never used by a training recipe, so `multirace evaluate`
can judge how an agent drives on roads it never saw. Tracks of one DeepRacer
season that share a layout family (a month's "open" and "pro" tracks, the
arctic pair) are held out together, so no held-out track has a sibling in
training.
"""
from __future__ import annotations

from ..sim.tracks import list_tracks

HELD_OUT_TRACKS = ("2022_april_open", "Canada_Training", "July_2020", "Mexico_track", "arctic_pro", "Aragon",
                   "2022_september_pro", "Virtual_May19_Train_track", "2022_april_pro", "2022_september_open",
                   "arctic_open")
TRAINING_SPLIT = "train-split"  # the word `--tracks` accepts for every bundled track that is not held out


def training_tracks() -> list[str]:
    """Every bundled track outside the held-out split."""
    return [t for t in list_tracks() if t not in HELD_OUT_TRACKS]


def expand_tracks(names) -> list[str]:
    """Track names with the word `train-split` replaced by the training split's tracks."""
    out = []
    for name in names:
        out += training_tracks() if name == TRAINING_SPLIT else [name]
    return list(dict.fromkeys(out))
