"""Small inline SVG charts for the league's pages (no script, no external library): lap times, ratings."""
from __future__ import annotations

import itertools

from markupsafe import Markup, escape

COLOURS = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")
WIDTH, HEIGHT, PAD, LEGEND = 640, 260, 44, 120


def _polyline_chart(series: list[tuple[str, list]], x_label: str, y_label: str, title: str) -> Markup:
    """An SVG line chart of named series of (x, y) points, scaled to fit, with a legend."""
    points = [p for _, pts in series for p in pts if p[1] is not None]
    if not points:
        return Markup("")
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    x0, x1 = min(xs), max(max(xs), min(xs) + 1)
    y0, y1 = min(ys), max(ys)
    if y1 - y0 < 1e-9:
        y0, y1 = y0 - 1, y1 + 1

    def at(x, y):
        return (f"{PAD + (x - x0) / (x1 - x0) * (WIDTH - 2 * PAD - LEGEND):.1f},"
                f"{HEIGHT - PAD - (y - y0) / (y1 - y0) * (HEIGHT - 2 * PAD):.1f}")

    parts = [f'<svg class="chart" viewBox="0 0 {WIDTH} {HEIGHT}" role="img" aria-label="{escape(title)}">',
             f'<rect x="{PAD}" y="{PAD // 2}" width="{WIDTH - 2 * PAD - LEGEND}" height="{HEIGHT - 1.5 * PAD}" '
             'fill="none" stroke="#ccc"/>',
             f'<text x="{WIDTH / 2}" y="{HEIGHT - 8}" text-anchor="middle">{escape(x_label)}</text>',
             f'<text x="12" y="{HEIGHT / 2}" transform="rotate(-90 12 {HEIGHT / 2})" text-anchor="middle">'
             f'{escape(y_label)}</text>',
             f'<text x="{PAD - 4}" y="{PAD // 2 + 10}" text-anchor="end">{y1:.3g}</text>',
             f'<text x="{PAD - 4}" y="{HEIGHT - PAD}" text-anchor="end">{y0:.3g}</text>']
    for i, (name, pts) in enumerate(series):
        colour = COLOURS[i % len(COLOURS)]
        coords = " ".join(at(x, y) for x, y in pts if y is not None)
        parts.append(f'<polyline fill="none" stroke="{colour}" stroke-width="2" points="{coords}"/>')
        parts += [f'<circle r="3" fill="{colour}" cx="{c.split(",")[0]}" cy="{c.split(",")[1]}"/>'
                  for c in coords.split()]
        parts.append(f'<text x="{WIDTH - PAD - LEGEND + 8}" y="{PAD + 14 * i}" fill="{colour}" font-size="11">'
                     f'{escape(name[:16])}</text>')
    parts.append("</svg>")
    return Markup("".join(parts))


def lap_chart_svg(cars: list[dict]) -> Markup:
    """Each car's race time at the end of each lap it completed (from 0 s at the start): the steeper, the
    slower; where lines cross, places changed."""
    series = []
    for c in cars:
        times = list(itertools.accumulate(c.get("lap_times") or []))
        series.append((c["name"], [(0, 0.0)] + [(i + 1, t) for i, t in enumerate(times)]))
    return _polyline_chart(series, "lap", "race time (s)", "race time at each lap")


def rating_chart_svg(history: list[dict]) -> Markup:
    """An entrant's rating (mu - 3 sigma) after each head-to-head round (0 before the first)."""
    points = [(0, 0.0)] + [(h["round"] + 1, h["rating"]) for h in history]
    return _polyline_chart([("rating", points)], "head-to-head round", "rating (mu - 3 sigma)", "rating over rounds")
