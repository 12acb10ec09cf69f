"""Headless figures for the report: a matplotlib Figure on its own Agg canvas, saved by Pillow.

No pyplot: a report is written while the node shuts down (``ros2 launch`` escalates to SIGTERM
5 s after SIGINT), so nothing here goes through pyplot's figure registry or ``savefig``'s general
machinery, and the PNGs are compressed for speed (a plot compresses well at any level).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: zlib level of the PNGs: level 1 takes half the time of Pillow's default 6 for ~10 % more bytes
PNG_COMPRESS_LEVEL = 1


def _matplotlib():
    """matplotlib's Figure class and Agg canvas (imported on first use)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    return Figure, FigureCanvasAgg


def warm_up() -> None:
    """Import matplotlib, its 3-D axes and Pillow, load the fonts and build the mathtext parser now
    (the labels of log axes are mathtext), so that a report written later does not wait for them
    (about a second)."""
    import mpl_toolkits.mplot3d  # noqa: F401 -- registers the '3d' projection
    import PIL.Image  # noqa: F401

    fig = new_figure((4, 3), 100)
    ax = fig.add_subplot()
    ax.set_yscale('log')
    ax.set_ylim(1e-3, 1e6)          # labels 10^-3 .. 10^6, parsed once and cached
    ax.set_title('0')
    fig.canvas.draw()


def new_figure(figsize: tuple[float, float], dpi: float):
    """An empty Figure drawn on an Agg canvas."""
    figure, canvas = _matplotlib()
    fig = figure(figsize=figsize, dpi=dpi)
    canvas(fig)
    return fig


def render(fig) -> np.ndarray:
    """Draw ``fig`` and return its pixels, (height, width, 3) uint8 (the figure is opaque)."""
    fig.canvas.draw()
    return pixels(fig)


def pixels(fig) -> np.ndarray:
    """The canvas as it was last drawn (or blitted), (height, width, 3) uint8, copied."""
    return np.array(np.asarray(fig.canvas.buffer_rgba())[..., :3])


def save_png(fig, path: Path) -> None:
    """Draw ``fig`` once and write it as an RGB PNG."""
    write_png(render(fig), path)


def write_png(rgb: np.ndarray, path: Path) -> None:
    from PIL import Image
    Image.fromarray(rgb).save(path, format='PNG', compress_level=PNG_COMPRESS_LEVEL)
