"""Layout of the paper's figures: sizes, side-by-side panels, the paper's design markers, saving.

The panels themselves are drawn by the generic functions of :mod:`torchmisspec.plotting` into axes made here; nothing
here rearranges a figure after it is drawn.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from .. import plotting

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["DPI", "PANEL_HEIGHT", "DESIGN_STYLES", "SECOND_CORRECTED", "side_by_side", "curves_figure", "save"]

DPI = 100
PANEL_HEIGHT = 4.0  # inches
#: How the paper's designs are drawn in Figs 3 and 6 (by the paper's names for them).
DESIGN_STYLES = {
    "design": dict(marker="s", color="black", size=90.0),
    "misspecified-aided": dict(marker="s", color="black", size=90.0),
    "random": dict(marker="o", color="tab:red", size=45.0),
    "agnostic": dict(marker="D", color="tab:blue", size=55.0),
}
#: How a second corrected model is drawn on a test panel (Figs 3 and 6), in its design's colour.
SECOND_CORRECTED = dict(linestyle=(0, (1, 2)), linewidth=1.8, zorder=2.6)


def side_by_side(width: float, width_ratios: tuple[float, float]) -> tuple[Figure, Axes, Axes]:
    """A new figure ``width`` inches wide with two panels (left, right) in the given width ratio."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, PANEL_HEIGHT), layout="constrained")
    left, right = fig.subplots(1, 2, width_ratios=width_ratios)
    return fig, left, right


def curves_figure(
    ks, curves: Mapping, *, references: Mapping[str, float], ylabel: str, title: str, labels: Mapping[str, str]
) -> Figure:
    """Error-vs-K curves (Figs 5 and 8): wide, legend outside on the right, ``labels`` renaming the strategies."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.6, 4.6), layout="constrained")
    ax = fig.subplots()
    plotting.plot_error_curves(
        ks,
        {labels.get(name, name): value for name, value in curves.items()},
        reference_lines=references,
        ylabel=ylabel,
        title=title,
        ax=ax,
        legend="right",
    )
    return fig


def save(fig: Figure, path: Path, files: list[str]) -> None:
    """Write ``fig`` as PNG to ``path`` and record its file name in ``files``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, format="png")
    files.append(path.name)
