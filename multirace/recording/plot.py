"""Plots of sim-trace logs: the track with the driven path coloured by speed and by reward.

`multirace plot trace.csv [--out trace.png] [--track T]` draws two panels
(speed = the commanded `throttle` in m/s, as DeepRacer's analysis notebooks
do; and `reward`) over the track's borders and centre line, one row of them
per episode (in a race's log, per car) up to 8 episodes, one shared row for
more (a training log). Without
`--track`, the bundled track whose length matches the log's `track_len` is
used. Headless: matplotlib's Agg backend, PNG out.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import AtomicOutput
from .simtrace import read_simtrace_columns
from ..sim.tracks import Track, list_tracks, load_track

MAX_FACETS = 8  # up to this many episodes (a race's cars) get a row of panels each; more share one row


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


def _draw_path(ax, track: Track | None, data: dict, part: np.ndarray, key: str, cmap: str, limits: tuple):
    """The track and the steps `part` of the log's columns (one or more episodes) coloured by `key`, off-tracks
    and crashes marked; returns the scatter."""
    if track is not None:
        for xy, style in ((track.inner, dict(color="0.2", lw=1.2)), (track.outer, dict(color="0.2", lw=1.2)),
                          (track.center, dict(color="goldenrod", lw=0.8, ls="--"))):
            ax.plot(xy[:, 0], xy[:, 1], **style)
    xs, ys = _episode_paths(data, part)
    ax.plot(xs, ys, color="0.6", lw=0.4, alpha=0.6)
    scatter = ax.scatter(data["X"][part], data["Y"][part], c=data[key][part], cmap=cmap, vmin=limits[0],
                         vmax=limits[1], s=6)
    off = part[data["off"][part]]
    if len(off):
        ax.scatter(data["X"][off], data["Y"][off], marker="x", color="red", s=30, label="off track / crash")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return scatter


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

    episodes_here = np.unique(data["episode"])
    groups = ([(f"episode {e} (car_{e} in a race log)", order[data["episode"][order] == e]) for e in episodes_here]
              if len(episodes_here) <= MAX_FACETS else [(f"{len(episodes_here)} episodes", order)])
    fig, axes = plt.subplots(len(groups), 2, figsize=(14, 5.5 * len(groups)), dpi=100, squeeze=False)
    panels = (("throttle", "speed (m/s)", "viridis"), ("reward", "reward", "plasma"))
    for column, (key, label, cmap) in enumerate(panels):
        limits = (float(data[key].min()), float(data[key].max()))  # one colour scale for every car: comparable
        for row, (title, part) in enumerate(groups):
            scatter = _draw_path(axes[row][column], track, data, part, key, cmap, limits)
            fig.colorbar(scatter, ax=axes[row][column], label=label, shrink=0.8)
            axes[row][column].set_title(f"{title}: {label}")
    name = track.name if track is not None else "unknown track"
    drawn = f", every {stride}th step drawn" if stride > 1 else ""
    fig.suptitle(f"{csv_path.name}: {name}, {len(np.unique(data['episode']))} episode(s), {steps} steps{drawn}")
    fig.tight_layout()
    with AtomicOutput(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out
