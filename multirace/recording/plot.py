"""Plots of sim-trace logs: the track with the driven path coloured by speed and by reward.

`multirace plot trace.csv [--out trace.png] [--track T]` draws two panels
(speed = the commanded `throttle` in m/s, as DeepRacer's analysis notebooks
do; and `reward`) over the track's borders and centre line. Without
`--track`, the bundled track whose length matches the log's `track_len` is
used. Headless: matplotlib's Agg backend, PNG out.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .simtrace import read_simtrace_columns
from ..sim.tracks import Track, list_tracks, load_track


def guess_track(track_len: float) -> Track | None:
    """The bundled track with this centre-line length (within 1 cm), if any."""
    for name in list_tracks():
        try:
            track = load_track(name)
        except Exception:  # a broken bundled file should not stop a plot
            continue
        if abs(track.length - track_len) < 0.01:
            return track
    return None


MAX_POINTS = 200_000  # steps drawn at the most; a longer log is drawn every k-th step


def _episode_paths(data: dict, order: np.ndarray) -> tuple:
    """X and Y of every episode's path in one array each, episodes apart by NaN (one line, not one per
    episode), in `order` (by episode, then as logged)."""
    episode = data["episode"][order]
    breaks = np.flatnonzero(np.diff(episode)) + 1
    xs = np.insert(data["X"][order], breaks, np.nan)
    ys = np.insert(data["Y"][order], breaks, np.nan)
    return xs, ys


def plot_simtrace(csv_path, out=None, track: str | Track | None = None, episodes=None) -> Path:
    """Write a PNG of the path(s) in a sim-trace CSV; returns the PNG path.

    `episodes`: only these episode numbers (default: all; in a race log, episode = car slot). The CSV is
    streamed into columns and drawn in a few calls whatever its number of episodes; over `MAX_POINTS`
    steps, every k-th step is drawn (the title says so).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    matplotlib.rcParams["agg.path.chunksize"] = 10_000  # long paths drawn in chunks: bounded renderer memory
    csv_path = Path(csv_path)
    data = read_simtrace_columns(csv_path, ("X", "Y", "throttle", "reward", "track_len"))
    if not len(data["episode"]):
        raise ValueError(f"sim-trace {csv_path}: no rows")
    if episodes is not None:
        wanted = sorted({int(e) for e in episodes})
        keep = np.isin(data["episode"], wanted)
        if not keep.any():
            raise ValueError(f"sim-trace {csv_path}: no rows for episodes {wanted}")
        data = {key: column[keep] for key, column in data.items()}
    steps = len(data["episode"])
    stride = -(-steps // MAX_POINTS)
    order = np.argsort(data["episode"], kind="stable")[::stride]
    if track is None:
        track = guess_track(float(data["track_len"][0]))
    elif not isinstance(track, Track):
        track = load_track(track)
    out = Path(out) if out is not None else csv_path.with_suffix(".png")
    out.parent.mkdir(parents=True, exist_ok=True)

    xs, ys = _episode_paths(data, order)
    off = order[data["off"][order]]
    fig, axes = plt.subplots(1, 2, figsize=(14, 6), dpi=100)
    panels = (("throttle", "speed (m/s)", "viridis"), ("reward", "reward", "plasma"))
    for ax, (key, label, cmap) in zip(axes, panels):
        if track is not None:
            for xy, style in ((track.inner, dict(color="0.2", lw=1.2)), (track.outer, dict(color="0.2", lw=1.2)),
                              (track.center, dict(color="goldenrod", lw=0.8, ls="--"))):
                ax.plot(xy[:, 0], xy[:, 1], **style)
        ax.plot(xs, ys, color="0.6", lw=0.4, alpha=0.6)
        scatter = ax.scatter(data["X"][order], data["Y"][order], c=data[key][order], cmap=cmap, s=6)
        fig.colorbar(scatter, ax=ax, label=label, shrink=0.8)
        if len(off):
            ax.scatter(data["X"][off], data["Y"][off], marker="x", color="red", s=30, label="off track / crash")
            ax.legend(loc="upper right", fontsize=8)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(f"{label}")
    name = track.name if track is not None else "unknown track"
    drawn = f", every {stride}th step drawn" if stride > 1 else ""
    fig.suptitle(f"{csv_path.name}: {name}, {len(np.unique(data['episode']))} episode(s), {steps} steps{drawn}")
    fig.tight_layout()
    fig.savefig(out, format="png")
    plt.close(fig)
    return out
