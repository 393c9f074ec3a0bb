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
from .simtrace import read_simtrace
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


def _draw_path(ax, track: Track | None, rows: list, key: str, cmap: str, limits: tuple):
    """The track and the path of `rows` (one or more episodes) coloured by `key`; returns the last scatter."""
    if track is not None:
        for xy, style in ((track.inner, dict(color="0.2", lw=1.2)), (track.outer, dict(color="0.2", lw=1.2)),
                          (track.center, dict(color="goldenrod", lw=0.8, ls="--"))):
            ax.plot(xy[:, 0], xy[:, 1], **style)
    scatter = None
    for episode in sorted({r["episode"] for r in rows}):
        part = [r for r in rows if r["episode"] == episode]
        xs, ys = np.array([r["X"] for r in part]), np.array([r["Y"] for r in part])
        ax.plot(xs, ys, color="0.6", lw=0.4, alpha=0.6)
        scatter = ax.scatter(xs, ys, c=[r[key] for r in part], cmap=cmap, vmin=limits[0], vmax=limits[1], s=6)
    off = [r for r in rows if r["episode_status"] in ("off_track", "crashed")]
    if off:
        ax.scatter([r["X"] for r in off], [r["Y"] for r in off], marker="x", color="red", s=30,
                   label="off track / crash")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return scatter


def plot_simtrace(csv_path, out=None, track: str | Track | None = None, episodes=None) -> Path:
    """Write a PNG of the path(s) in a sim-trace CSV; returns the PNG path.

    `episodes`: only these episode numbers (default: all; in a race log, episode = car slot).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    csv_path = Path(csv_path)
    rows = read_simtrace(csv_path)
    if not rows:
        raise ValueError(f"sim-trace {csv_path}: no rows")
    if episodes is not None:
        wanted = {int(e) for e in episodes}
        rows = [r for r in rows if r["episode"] in wanted]
        if not rows:
            raise ValueError(f"sim-trace {csv_path}: no rows for episodes {sorted(wanted)}")
    if track is None:
        track = guess_track(float(rows[0]["track_len"]))
    elif not isinstance(track, Track):
        track = load_track(track)
    out = Path(out) if out is not None else csv_path.with_suffix(".png")
    out.parent.mkdir(parents=True, exist_ok=True)

    episodes_here = sorted({r["episode"] for r in rows})
    groups = ([(f"episode {e} (car_{e} in a race log)", [r for r in rows if r["episode"] == e]) for e in episodes_here]
              if len(episodes_here) <= MAX_FACETS else [(f"{len(episodes_here)} episodes", rows)])
    fig, axes = plt.subplots(len(groups), 2, figsize=(14, 5.5 * len(groups)), dpi=100, squeeze=False)
    panels = (("throttle", "speed (m/s)", "viridis"), ("reward", "reward", "plasma"))
    for column, (key, label, cmap) in enumerate(panels):
        values = np.array([r[key] for r in rows], dtype=float)
        limits = (float(values.min()), float(values.max()))  # one colour scale for every car: comparable
        for row, (title, part) in enumerate(groups):
            scatter = _draw_path(axes[row][column], track, part, key, cmap, limits)
            fig.colorbar(scatter, ax=axes[row][column], label=label, shrink=0.8)
            axes[row][column].set_title(f"{title}: {label}")
    name = track.name if track is not None else "unknown track"
    fig.suptitle(f"{csv_path.name}: {name}, {len(episodes_here)} episode(s), {len(rows)} steps")
    fig.tight_layout()
    with AtomicOutput(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out
