"""What every figure of :mod:`torchmisspec.plotting` shares: turning tensors, arrays and Trajectories into numpy
arrays, checking dims / styles / legend arguments, placing legends, making and saving figures."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .._errors import InputError, ShapeError
from .._validation import check_indices, check_path

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

PANEL_SIZE = (5.0, 4.0)  # inches per panel
DPI = 100
_LEGENDS = (True, False, None, "axes", "right", "below")


def _as_array(x: Any, name: str) -> np.ndarray:
    """A float64 numpy array from a tensor, array, nested sequence or Trajectories (its states)."""
    if hasattr(x, "states") and hasattr(x, "times"):  # Trajectories
        if getattr(x, "is_ragged", False):  # NaN-padded: matplotlib leaves the padding out
            _, states, mask = x.padded()
            x = states.detach().to(torch.float64).masked_fill(~mask.unsqueeze(-1), float("nan"))
        else:
            x = x.states
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        if x.is_complex() or x.dtype == torch.bool:
            raise InputError(f"{name}: expected real numbers, got a {x.dtype} tensor")
        return x.to(torch.float64).numpy()
    try:
        arr = np.asarray(x)
        if arr.dtype.kind in "cb":  # complex or bool: converting would drop the imaginary part or turn True into 1
            raise InputError(f"{name}: expected real numbers, got an array of dtype {arr.dtype}")
        arr = arr.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected an array of numbers, got {type(x).__name__} ({exc})") from exc
    return arr


def _states(x: Any, name: str) -> np.ndarray:
    arr = _as_array(x, name)
    if arr.ndim != 3:
        raise ShapeError(f"{name}: expected shape (K, T, d), got {arr.shape}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ShapeError(f"{name}: expected at least one trajectory and one time, got shape {arr.shape}")
    return arr


def _check_dims(dims: Sequence[int], d: int, name: str = "dims") -> tuple[int, int]:
    """Two distinct component indices in [0, d) (x axis, y axis)."""
    if dims is None:
        raise InputError(f"{name}: expected two component indices (x, y), got None")
    out = check_indices(dims, d, name)
    if len(out) != 2:
        raise InputError(f"{name}: expected two component indices (x, y), got {len(out)}: {list(out)}")
    return out  # type: ignore[return-value]


def _check_styles(styles: Any, allowed: Sequence[str], name: str = "styles") -> dict[str, dict]:
    """``styles``: a dict name -> dict of keyword arguments, with names among ``allowed``."""
    if styles is None:
        return {}
    if not isinstance(styles, Mapping):
        raise InputError(f"{name}: expected a dict name -> style dict, got {type(styles).__name__}")
    out = {}
    for key, style in styles.items():
        if str(key) not in allowed:
            raise InputError(f"{name}: expected keys among {list(allowed)}, got unknown {key!r}")
        if not isinstance(style, Mapping):
            raise InputError(f"{name}[{key!r}]: expected a dict of style keywords, got {type(style).__name__}")
        out[str(key)] = dict(style)
    return out


def _check_legend(legend: Any) -> str | None:
    if not any(legend is option or (isinstance(legend, str) and legend == option) for option in _LEGENDS):
        raise InputError(f"legend: expected one of {list(_LEGENDS)}, got {legend!r}")
    if legend is True:
        return "axes"
    return legend or None


def _place_legend(ax: Axes, handles: list, legend: str | None):
    """Draw the legend of ``handles`` where ``legend`` says ("axes", "right", "below" or None); returns it."""
    if legend is None or not handles:
        return None
    if legend == "axes":
        return ax.legend(handles=handles, loc="best", fontsize="small", framealpha=0.85)
    if legend == "right":
        return ax.legend(
            handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small", borderaxespad=0.0
        )
    return ax.figure.legend(
        handles=handles, loc="outside lower center", ncol=len(handles), fontsize="small", frameon=False
    )


def _new_figure(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float] | None = None):
    from matplotlib.figure import Figure

    if figsize is None:
        figsize = (PANEL_SIZE[0] * ncols, PANEL_SIZE[1] * nrows)
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _axes(ax: Axes | None, figsize: tuple[float, float] | None = None) -> tuple[Figure, Axes]:
    """The given axes and its figure, or a new one-panel figure."""
    if ax is None:
        fig, axes = _new_figure(figsize=figsize)
        return fig, axes[0, 0]
    if not hasattr(ax, "figure") or not hasattr(ax, "plot"):
        raise InputError(f"ax: expected a matplotlib Axes, got {type(ax).__name__}")
    return ax.figure, ax


def _finish(fig: Figure, path: str | Path | None, dpi: int) -> Figure:
    if path is not None:
        path = Path(check_path(path))
        if path.suffix.lower() not in ("", ".png"):
            raise InputError(f"path: expected a .png file name, got {str(path)!r}")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fig.savefig(path, dpi=dpi, format="png")
        except OSError as exc:
            raise InputError(
                f"path: expected a .png file in a folder that can be written, got {str(path)!r} ({exc.strerror or exc})"
            ) from None
    return fig


def _draw_box(ax: Axes, box, *, label: str | None = None, color: str = "black") -> None:
    from matplotlib.patches import Rectangle

    (x0, x1), (y0, y1) = box
    ax.add_patch(
        Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, linestyle="--", linewidth=1.2, edgecolor=color, label=label)
    )
