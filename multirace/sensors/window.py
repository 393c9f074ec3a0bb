"""`render_mode="human"`: the top-down race view shown in a matplotlib window.

On a machine without a display matplotlib draws off screen (its Agg
backend), so a human-mode env still runs, headless, and shows nothing.
"""
from __future__ import annotations

import numpy as np


class RaceWindow:
    """A window that shows one RGB frame at a time, updated in place."""

    def __init__(self, title: str = "multirace"):
        self.title = title
        self.figure = None
        self.image = None

    def show(self, frame: np.ndarray) -> None:
        """Draw `frame` (uint8 RGB) in the window, opening it on the first call."""
        import matplotlib.pyplot as plt

        if self.figure is None:
            plt.ion()
            self.figure, axes = plt.subplots(num=self.title, figsize=(frame.shape[1] / 100, frame.shape[0] / 100))
            axes.set_axis_off()
            self.figure.subplots_adjust(0, 0, 1, 1)
            self.image = axes.imshow(frame)
        else:
            self.image.set_data(frame)
        self.figure.canvas.draw_idle()
        self.figure.canvas.flush_events()

    def close(self) -> None:
        """Close the window if it is open."""
        if self.figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self.figure)
            self.figure = None
