"""Generic matplotlib figures: trajectories, error heat maps, designs and error-vs-K curves.

Every function takes tensors or arrays (torch tensors are detached and moved to the CPU; a
:class:`~torchmisspec.data.Trajectories` is accepted wherever states ``(K, T, d)`` are expected), optionally saves a
PNG to ``path``, and returns the :class:`matplotlib.figure.Figure`. Figures are built as ``Figure`` objects, not
through ``pyplot``, so nothing here touches pyplot's global state or needs a display; matplotlib is imported only when
a function is called. The one-panel functions draw into a given ``ax`` when asked, so a caller can compose them into
its own layout (the paper's figures are composed that way in :mod:`torchmisspec.paper.figures`).

Figures: :func:`plot_trajectories` (phase plane: true, misspecified, corrected and further sets),
:func:`plot_training_and_test` (training and test panels side by side), :func:`plot_error_map` (a scalar error over a
box), :func:`plot_component_error_maps` (one error map per setting and output component), :func:`plot_design`
(candidates and the picks of several designs), :func:`plot_error_curves` (error against the number of experiments),
:func:`plot_prediction_bands` (uncertainty bands of predicted trajectories against time) and :func:`plot_calibration`
(empirical against nominal coverage of the bands).
:func:`correction_error_fn` builds the error callables the heat maps take from a system with a known F and a fitted
GP.

Styles are explicit: a caller passes ``styles={name: {...}}`` for the names it draws; a name without a style gets
the default for its *position* (:data:`DESIGN_STYLES` for the picks of :func:`plot_design`, :data:`SERIES_STYLES` for
further trajectory sets, matplotlib's colour cycle and :data:`CURVE_MARKERS` for curves), never a style chosen from
what the name says. ``legend`` places the legend: ``True`` / ``"axes"`` inside the axes, ``"right"`` outside on the
right, ``"below"`` one legend for the figure under the panels, ``False`` none.

Heat-map grids follow the image convention: ``grid[i, j]`` is the value at ``x = xs[j]``, ``y = ys[i]``, with ``xs``
and ``ys`` evenly spaced from the domain's lower to upper bounds (both included).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ._errors import InputError, ShapeError, TorchMisspecError
from ._validation import check_domain, check_indices, check_positive_int

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from .gp import CorrectionGP
    from .systems import MisspecifiedSystem

__all__ = [
    "plot_trajectories",
    "plot_training_and_test",
    "plot_error_map",
    "plot_component_error_maps",
    "plot_design",
    "plot_error_curves",
    "plot_prediction_bands",
    "plot_calibration",
    "correction_error_fn",
    "TRAJECTORY_STYLES",
    "SERIES_STYLES",
    "DESIGN_STYLES",
    "CURVE_MARKERS",
    "BAND_LEVELS",
]

PANEL_SIZE = (5.0, 4.0)  # inches per panel
DPI = 100
HEAT_LEVELS = 48  # colour levels of the heat maps
_TRAJ_COLORS = (
    "tab:blue",
    "tab:orange",
    "tab:green",
    "tab:red",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
    "tab:gray",
)
#: Line styles of the three trajectory roles of :func:`plot_trajectories` (``label`` is the legend text). Without a
#: ``color``, trajectory k has colour k of the tab10 cycle in every role; the corrected ones are black, on top.
TRAJECTORY_STYLES = {
    "true": dict(linestyle="-", linewidth=1.3, label="true (G + F)"),
    "misspecified": dict(linestyle="--", linewidth=1.1, label="misspecified (G)"),
    "corrected": dict(linestyle=":", linewidth=1.8, label=r"corrected (G + $\hat F$)", color="black", zorder=2.5),
}
#: Default styles of further trajectory sets (``series=`` of :func:`plot_trajectories`), by position.
SERIES_STYLES = (
    dict(linestyle=(0, (1, 2)), linewidth=1.8, color="tab:red", zorder=2.6),
    dict(linestyle="-.", linewidth=1.5, color="tab:blue", zorder=2.6),
    dict(linestyle=(0, (5, 1)), linewidth=1.5, color="tab:green", zorder=2.6),
    dict(linestyle=(0, (3, 1, 1, 1)), linewidth=1.5, color="tab:purple", zorder=2.6),
)
#: Default styles of the picks of :func:`plot_design`, by position: hollow markers (``size`` is the marker area in
#: points^2) and the colour of the design's trajectories.
DESIGN_STYLES = (
    dict(marker="s", color="black", size=90.0),
    dict(marker="o", color="tab:red", size=45.0),
    dict(marker="D", color="tab:blue", size=55.0),
    dict(marker="^", color="tab:green", size=60.0),
    dict(marker="v", color="tab:purple", size=60.0),
    dict(marker="P", color="tab:brown", size=60.0),
    dict(marker="X", color="tab:pink", size=60.0),
)
_DESIGN_STYLE_KEYS = ("marker", "color", "size", "linestyle")
#: Default markers of the curves of :func:`plot_error_curves`, by position (colours: matplotlib's cycle).
CURVE_MARKERS = ("o", "s", "^", "D", "v", "P")
_LEGENDS = (True, False, None, "axes", "right", "below")


# --------------------------------------------------------------------------------------------------- helpers
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
        if x.is_complex():
            raise InputError(f"{name}: expected real numbers, got a complex tensor")
        return x.to(torch.float64).numpy()
    try:
        arr = np.asarray(x, dtype=np.float64)
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
        path = Path(path)
        if path.suffix.lower() not in ("", ".png"):
            raise InputError(f"path: expected a .png file name, got {str(path)!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=dpi, format="png")
    return fig


def _draw_box(ax: Axes, box, *, label: str | None = None, color: str = "black") -> None:
    from matplotlib.patches import Rectangle

    (x0, x1), (y0, y1) = box
    ax.add_patch(
        Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, linestyle="--", linewidth=1.2, edgecolor=color, label=label)
    )


# ------------------------------------------------------------------------------------------------ trajectories
def _trajectory_styles(series_names: Sequence[str], styles: Any) -> dict[str, dict]:
    """The style of every role and series: defaults (by role, or by position for series) updated by ``styles``."""
    given = _check_styles(styles, [*TRAJECTORY_STYLES, *series_names])
    out = {key: {**TRAJECTORY_STYLES[key], **given.get(key, {})} for key in TRAJECTORY_STYLES}
    for i, name in enumerate(series_names):
        out[name] = {**SERIES_STYLES[i % len(SERIES_STYLES)], "label": name, **given.get(name, {})}
    return out


def plot_trajectories(
    true_states,
    misspecified_states=None,
    corrected_states=None,
    *,
    series: Mapping[str, Any] | None = None,
    styles: Mapping[str, Mapping[str, Any]] | None = None,
    dims: Sequence[int] = (0, 1),
    ax: Axes | None = None,
    title: str | None = None,
    axis_labels: tuple[str, str] | None = None,
    legend: bool | str = True,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Phase-plane plot of K trajectories: true solid, misspecified dashed, corrected dotted, and further sets.

    Trajectory k has the same colour in the true and misspecified styles; the corrected ones are black and on top;
    each further set (``series``) has one colour. The initial conditions ``true_states[:, 0]`` are black dots. The
    legend has one entry per style present, plus the initial conditions.

    Args:
        true_states: ``(K, T, d)`` states of the true system (or a Trajectories, ragged ones included: the
            experiments are NaN-padded to the longest, and the padding is not drawn).
        misspecified_states: optional ``(K, T', d)`` predictions of the misspecified model from the same K initial
            conditions (its time grid may differ from the true one).
        corrected_states: optional ``(K, T', d)`` predictions of the corrected model, likewise.
        series: optional further sets, name -> ``(K, T', d)`` (e.g. a second corrected model), drawn in order after
            the corrected ones; the name is the legend text unless its style has a ``label``.
        styles: optional overrides, key -> Line2D keywords (``label`` is the legend text): keys ``"true"``,
            ``"misspecified"``, ``"corrected"`` (defaults :data:`TRAJECTORY_STYLES`) or a name of ``series``
            (defaults :data:`SERIES_STYLES` by position).
        dims: the two state components to plot on the x and y axes.
        ax: draw into this Axes instead of a new figure.
        title: axes title (default ``"Trajectories (K=...)"``).
        axis_labels: x and y labels (default ``$y_{i+1}$``).
        legend: ``True``/``"axes"``, ``"right"``, ``"below"`` (a figure legend) or ``False``.
        path: save the figure as PNG here.
    """
    true = _states(true_states, "true_states")
    K, _, d = true.shape
    sets = {"true": true}
    if series is not None and not isinstance(series, Mapping):
        raise InputError(f"series: expected a dict name -> (K, T, d) states, got {type(series).__name__}")
    extra = dict(series) if series is not None else {}
    clash = set(map(str, extra)) & set(TRAJECTORY_STYLES)
    if clash:
        raise InputError(f"series: expected names other than {list(TRAJECTORY_STYLES)}, got {sorted(clash)}")
    for key, value in (("misspecified", misspecified_states), ("corrected", corrected_states), *extra.items()):
        if value is None:
            continue
        name = f"{key}_states" if key in TRAJECTORY_STYLES else f"series[{key!r}]"
        arr = _states(value, name)
        if arr.shape[0] != K or arr.shape[2] != d:
            raise ShapeError(f"{name}: expected shape ({K}, T, {d}) to match true_states {true.shape}, got {arr.shape}")
        sets[str(key)] = arr
    dims = _check_dims(dims, d)
    style_of = _trajectory_styles([str(k) for k in extra], styles)
    legend = _check_legend(legend)
    fig, ax = _axes(ax)
    from matplotlib.lines import Line2D

    for key, arr in sets.items():
        style = {k: v for k, v in style_of[key].items() if k != "label"}
        fixed = style.pop("color", None)
        for k in range(K):  # without a fixed colour, trajectory k has colour k in every style
            ax.plot(arr[k, :, dims[0]], arr[k, :, dims[1]], color=fixed or _TRAJ_COLORS[k % len(_TRAJ_COLORS)], **style)
    ax.plot(
        true[:, 0, dims[0]], true[:, 0, dims[1]], linestyle="none", marker="o", markersize=4, color="black", zorder=3
    )
    handles = [Line2D([], [], **{"color": "0.25", **style_of[key]}) for key in sets]
    handles.append(
        Line2D([], [], linestyle="none", marker="o", markersize=4, color="black", label="initial conditions")
    )
    _place_legend(ax, handles, legend)
    xl, yl = axis_labels if axis_labels is not None else (f"$y_{{{dims[0] + 1}}}$", f"$y_{{{dims[1] + 1}}}$")
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    ax.set_title(title if title is not None else f"Trajectories (K={K})")
    ax.grid(True, alpha=0.3)
    return _finish(fig, path, dpi)


def plot_training_and_test(
    train_true,
    train_misspecified,
    test_true,
    test_misspecified,
    test_corrected,
    *,
    dims: Sequence[int] = (0, 1),
    titles: tuple[str, str] | None = None,
    axis_labels: tuple[str, str] | None = None,
    styles: Mapping[str, Mapping[str, Any]] | None = None,
    legend: bool | str = True,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Training set (left: true vs misspecified) and test set (right: true, misspecified, corrected), side by side.

    Args:
        train_true: ``(K, T, d)`` training trajectories of the true model.
        train_misspecified: ``(K, T, d)`` the same from the misspecified model.
        test_true: ``(K', T, d)`` test trajectories of the true model.
        test_misspecified: ``(K', T, d)`` the same from the misspecified model.
        test_corrected: ``(K', T, d)`` the same from the corrected model G + mu.
        dims: as in :func:`plot_trajectories`.
        axis_labels: as in :func:`plot_trajectories`.
        styles: as in :func:`plot_trajectories` (they apply to both panels).
        titles: the two panel titles.
        legend: ``True``/``"axes"``: a legend in each panel; ``"below"``: one legend under both panels (every style
            appears in the test panel); ``False``: none.
    """
    legend = _check_legend(legend)
    if legend == "right":
        raise InputError("legend: expected True, 'axes', 'below' or False for two panels, got 'right'")
    fig, axes = _new_figure(1, 2)
    k_train = _states(train_true, "train_true").shape[0]
    k_test = _states(test_true, "test_true").shape[0]
    titles = titles if titles is not None else (f"Training set (K={k_train})", f"Test set (K={k_test})")
    panel_legend = "axes" if legend == "axes" else False
    common = dict(dims=dims, axis_labels=axis_labels, styles=styles, legend=panel_legend)
    plot_trajectories(train_true, train_misspecified, ax=axes[0, 0], title=titles[0], **common)
    plot_trajectories(
        test_true, test_misspecified, test_corrected, ax=axes[0, 1], title=titles[1], **{**common, "legend": legend}
    )
    return _finish(fig, path, dpi)


# -------------------------------------------------------------------------------------------------- heat maps
def _grid_points(domain, resolution: int) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    (x0, x1), (y0, y1) = domain
    xs = np.linspace(x0, x1, resolution)
    ys = np.linspace(y0, y1, resolution)
    X, Y = np.meshgrid(xs, ys, indexing="xy")  # (res_y, res_x): row i is y = ys[i]
    pts = torch.from_numpy(np.stack([X.ravel(), Y.ravel()], axis=-1))  # (M, 2) float64
    return xs, ys, pts


def _evaluate(fn: Callable, pts: torch.Tensor, name: str) -> np.ndarray:
    with torch.no_grad():
        try:
            out = fn(pts)
        except TorchMisspecError:
            raise
        except Exception as exc:  # report which callable failed, on which points
            raise InputError(
                f"{name}: calling it on points of shape {tuple(pts.shape)} (float64) failed: "
                f"{type(exc).__name__}: {exc}"
            ) from exc
    return _as_array(out, f"{name}(points)")


def _scalar_grid(source, domain, resolution: int, name: str) -> np.ndarray:
    """A (res, res) grid from a callable (M, 2) -> (M,) or a precomputed 2-D grid."""
    if callable(source):
        _, _, pts = _grid_points(domain, resolution)
        vals = _evaluate(source, pts, name)
        M = pts.shape[0]
        if vals.shape not in ((M,), (M, 1)):
            raise ShapeError(
                f"{name}: expected the callable to return shape ({M},) for points ({M}, 2), got {vals.shape}"
            )
        return vals.reshape(resolution, resolution)
    grid = _as_array(source, name)
    if grid.ndim != 2 or min(grid.shape) < 2:
        raise ShapeError(
            f"{name}: expected a callable or a 2-D grid (res_y, res_x) with res >= 2, got shape {grid.shape}"
        )
    return grid


def _component_grids(source, domain, resolution: int, name: str) -> list[np.ndarray]:
    """Per-component grids from a callable (M, 2) -> (M,) / (M, C), an array (res, res) / (C, res, res), or a
    sequence of callables / 2-D grids."""
    if callable(source):
        _, _, pts = _grid_points(domain, resolution)
        vals = _evaluate(source, pts, name)
        M = pts.shape[0]
        if vals.ndim == 1:
            vals = vals[:, None]
        if vals.ndim != 2 or vals.shape[0] != M:
            raise ShapeError(
                f"{name}: expected the callable to return shape ({M},) or ({M}, C) for points "
                f"({M}, 2), got {vals.shape}"
            )
        return [vals[:, c].reshape(resolution, resolution) for c in range(vals.shape[1])]
    if isinstance(source, (list, tuple)):
        if len(source) == 0:
            raise InputError(f"{name}: expected at least one component, got an empty sequence")
        if any(callable(s) or np.ndim(s) == 2 for s in source):  # one callable / 2-D grid per component
            return [_scalar_grid(s, domain, resolution, f"{name}[{c}]") for c, s in enumerate(source)]
    arr = _as_array(source, name)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or min(arr.shape[1:]) < 2:
        raise ShapeError(
            f"{name}: expected a callable, a grid (res_y, res_x) or grids (C, res_y, res_x), got shape {arr.shape}"
        )
    return list(arr)


def _draw_heat(ax: Axes, grid: np.ndarray, domain, *, vmin=None, vmax=None, log_scale: bool = False, cmap="viridis"):
    import matplotlib
    from matplotlib.colors import LogNorm, Normalize

    cmap = matplotlib.colormaps[cmap].resampled(HEAT_LEVELS)  # a few dozen levels: smaller PNGs, same reading

    (x0, x1), (y0, y1) = domain
    finite = grid[np.isfinite(grid)]
    if log_scale:
        pos = finite[finite > 0]
        lo = vmin if vmin is not None else (float(pos.min()) if pos.size else 1e-12)
        hi = vmax if vmax is not None else (float(pos.max()) if pos.size else 1.0)
        norm = LogNorm(vmin=lo, vmax=max(hi, lo * (1 + 1e-12)))
        grid = np.where(grid > 0, grid, np.nan)
    else:  # autoscale on the finite values only (F is infinite at a point mass)
        lo = vmin if vmin is not None else (float(finite.min()) if finite.size else 0.0)
        hi = vmax if vmax is not None else (float(finite.max()) if finite.size else 1.0)
        norm = Normalize(vmin=lo, vmax=hi)
    return ax.imshow(
        grid, origin="lower", extent=(x0, x1, y0, y1), aspect="auto", cmap=cmap, norm=norm, interpolation="nearest"
    )


def _overlay_traces(ax: Axes, traces, dims: Sequence[int], name: str) -> None:
    arr = _states(traces, name)
    dims = _check_dims(dims, arr.shape[2], "trace_dims")
    for k in range(arr.shape[0]):
        ax.plot(
            arr[k, :, dims[0]],
            arr[k, :, dims[1]],
            color="white",
            linewidth=1.0,
            marker="o",
            markersize=2.5,
            markeredgewidth=0,
        )


def plot_error_map(
    error_fn_or_grid,
    domain,
    *,
    traces=None,
    trace_dims: Sequence[int] = (0, 1),
    resolution: int = 101,
    title: str | None = None,
    ax: Axes | None = None,
    cbar_label: str = r"$\|\hat F(y) - F(y)\|_2$",
    axis_labels: tuple[str, str] = ("$y_1$", "$y_2$"),
    log_scale: bool = False,
    vmin: float | None = None,
    vmax: float | None = None,
    dashed_box=None,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Heat map of a scalar error over the box ``domain``, training traces overlaid in white.

    Args:
        error_fn_or_grid: a callable mapping points ``(M, 2)`` (float64 tensor) to values ``(M,)``, evaluated on a
            ``resolution x resolution`` grid; or a precomputed grid ``(res_y, res_x)`` over ``domain`` (see the
            module docstring for the orientation).
        domain: ``((x_lo, x_hi), (y_lo, y_hi))``, e.g. ``system.domain``.
        traces: optional ``(K, T, d)`` trajectories drawn as white lines with dots (components ``trace_dims``).
        log_scale: logarithmic colour scale (non-positive values are left blank).
        vmin: lower colour-scale limit (default: the smallest finite value).
        vmax: upper colour-scale limit (default: the largest finite value).
        dashed_box: optional ``((x_lo, x_hi), (y_lo, y_hi))`` drawn dashed, e.g. the region D inside a larger map.
    """
    domain = check_domain(domain, dim=2)
    resolution = check_positive_int(resolution, "resolution", minimum=2)
    grid = _scalar_grid(error_fn_or_grid, domain, resolution, "error_fn_or_grid")
    fig, ax = _axes(ax, figsize=(PANEL_SIZE[0] + 0.6, PANEL_SIZE[1]))
    im = _draw_heat(ax, grid, domain, vmin=vmin, vmax=vmax, log_scale=log_scale)
    fig.colorbar(im, ax=ax, label=cbar_label)
    if traces is not None:
        _overlay_traces(ax, traces, trace_dims, "traces")
    if dashed_box is not None:
        _draw_box(ax, check_domain(dashed_box, "dashed_box", dim=2), color="white")
    ax.set_xlim(domain[0])
    ax.set_ylim(domain[1])
    ax.set_xlabel(axis_labels[0])
    ax.set_ylabel(axis_labels[1])
    ax.set_title(title if title is not None else "Estimation error of the correction")
    return _finish(fig, path, dpi)


def plot_component_error_maps(
    maps: Mapping[str, Any],
    domain,
    *,
    traces: Mapping[str, Any] | None = None,
    trace_dims: Sequence[int] = (0, 1),
    resolution: int = 101,
    component_labels: Sequence[str] | None = None,
    axis_labels: tuple[str, str] = ("$y_1$", "$y_2$"),
    settings_as_columns: bool = False,
    log_scale: bool = False,
    dashed_box=None,
    title: str | None = None,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """A grid of error heat maps, one row per setting and one column per output component.

    Each component (column) shares one colour scale across the settings, so the settings compare at a glance.

    Args:
        maps: setting name (e.g. ``"random"``, ``"design"``) -> the per-component errors, as a callable mapping
            points ``(M, 2)`` to ``(M,)`` or ``(M, C)`` (see :func:`correction_error_fn` with ``component="all"``),
            an array ``(res, res)`` or ``(C, res, res)``, or a sequence of C callables / 2-D grids. Every setting
            must give the same number C of components.
        domain: ``((x_lo, x_hi), (y_lo, y_hi))``.
        traces: optional setting name -> ``(K, T, d)`` training trajectories overlaid on that setting's panels.
        component_labels: the C column titles / colour-bar labels (default ``|F̂_i - F_i|``, i = 1..C).
        settings_as_columns: transpose the layout (settings across, components down).
        log_scale: as in :func:`plot_error_map`.
        dashed_box: as in :func:`plot_error_map`.
    """
    if not isinstance(maps, Mapping) or len(maps) == 0:
        raise InputError(f"maps: expected a non-empty dict setting name -> errors, got {type(maps).__name__}")
    domain = check_domain(domain, dim=2)
    resolution = check_positive_int(resolution, "resolution", minimum=2)
    grids = {name: _component_grids(src, domain, resolution, f"maps[{name!r}]") for name, src in maps.items()}
    counts = {name: len(g) for name, g in grids.items()}
    C = next(iter(counts.values()))
    if any(c != C for c in counts.values()):
        raise ShapeError(f"maps: expected the same number of components for every setting, got {counts}")
    if traces is not None:
        unknown = set(traces) - set(maps)
        if unknown:
            raise InputError(f"traces: expected keys among the settings {list(maps)}, got unknown {sorted(unknown)}")
    if component_labels is None:
        component_labels = [rf"$|\hat F_{{{c + 1}}} - F_{{{c + 1}}}|$" for c in range(C)]
    elif len(component_labels) != C:
        raise ShapeError(f"component_labels: expected {C} labels (one per component), got {len(component_labels)}")
    if dashed_box is not None:
        dashed_box = check_domain(dashed_box, "dashed_box", dim=2)
    S = len(grids)
    nrows, ncols = (C, S) if settings_as_columns else (S, C)
    fig, axes = _new_figure(nrows, ncols, figsize=(3.8 * ncols + 0.8, 3.1 * nrows))
    for c in range(C):
        values = np.concatenate([g[c].ravel() for g in grids.values()])
        finite = values[np.isfinite(values)]
        if log_scale:
            finite = finite[finite > 0]
        vmin = float(finite.min()) if finite.size else None
        vmax = float(finite.max()) if finite.size else None
        col_axes = []
        im = None
        for s, name in enumerate(grids):
            ax = axes[c, s] if settings_as_columns else axes[s, c]
            col_axes.append(ax)
            im = _draw_heat(ax, grids[name][c], domain, vmin=vmin, vmax=vmax, log_scale=log_scale)
            if traces is not None and name in traces:
                _overlay_traces(ax, traces[name], trace_dims, f"traces[{name!r}]")
            if dashed_box is not None:
                _draw_box(ax, dashed_box, color="white")
            ax.set_xlim(domain[0])
            ax.set_ylim(domain[1])
            ax.set_xlabel(axis_labels[0])
            ax.set_ylabel(axis_labels[1])
            ax.set_title(f"{name}: {component_labels[c]}")
        fig.colorbar(im, ax=col_axes, label=component_labels[c], shrink=0.9)
    if title is not None:
        fig.suptitle(title)
    return _finish(fig, path, dpi)


def correction_error_fn(
    system: MisspecifiedSystem,
    gp: CorrectionGP,
    *,
    component: int | str | None = None,
) -> Callable[[torch.Tensor], torch.Tensor]:
    """The error of the GP mean against the system's true F at points ``(M, 2)`` of the correction inputs.

    Args:
        component: ``None`` -> ``||F̂(x) - F(x)||_2`` ``(M,)``; an int i -> ``|F̂_i(x) - F_i(x)|`` ``(M,)`` (i indexes
            the correction outputs); ``"all"`` -> absolute errors of every output ``(M, d_out)``.
    """
    if not system.has_correction:
        raise InputError(f"system '{system.name}' has no true correction F; the error map needs one")
    if system.input_dim != 2:
        raise ShapeError(
            f"system: expected a correction with 2 inputs for a 2-D error map, got "
            f"{system.input_dim} (correction_inputs={list(system.correction_inputs)})"
        )
    if gp.input_dim is not None and gp.input_dim != system.input_dim:
        raise ShapeError(f"gp: expected a GP with {system.input_dim} inputs, got {gp.input_dim}")
    d_out = system.output_dim
    if component is not None and component != "all":
        if isinstance(component, bool) or not isinstance(component, (int, np.integer)) or not 0 <= component < d_out:
            raise InputError(f"component: expected None, 'all' or an integer in [0, {d_out - 1}], got {component!r}")

    def error(x: torch.Tensor) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=gp.dtype, device=gp.device)
        diff = gp.predict_mean(x) - system.true_correction(x)
        if component is None:
            return diff.norm(dim=-1)
        if component == "all":
            return diff.abs()
        return diff[:, int(component)].abs()

    return error


# ----------------------------------------------------------------------------------------------------- designs
def _indices(idx, n: int, name: str) -> np.ndarray:
    if isinstance(idx, torch.Tensor):
        idx = idx.detach().cpu().numpy()
    arr = np.asarray(idx)
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ShapeError(f"{name}: expected a boolean mask of shape ({n},) or integer indices, got {arr.shape}")
        return np.flatnonzero(arr)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
        raise InputError(
            f"{name}: expected a 1-D array of integer indices into the {n} candidates, got dtype "
            f"{arr.dtype} and shape {arr.shape}"
        )
    if arr.size and (arr.min() < 0 or arr.max() >= n):
        raise InputError(
            f"{name}: expected indices in [0, {n - 1}] (there are {n} candidates), got values from "
            f"{int(arr.min())} to {int(arr.max())}"
        )
    return arr.astype(np.int64)


def _masses(masses) -> dict[str, np.ndarray]:
    groups = masses if isinstance(masses, Mapping) else {"point masses": masses}
    out = {}
    for label, value in groups.items():
        arr = _as_array(value, f"masses[{label!r}]" if isinstance(masses, Mapping) else "masses")
        if arr.ndim == 1 and arr.shape[0] == 3:
            arr = arr[None]
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ShapeError(f"masses: expected rows (x, y, m), shape (n, 3), got {arr.shape}")
        out[str(label)] = arr
    return out


def _design_styles(pick_names: Sequence[str], proxy_names: Sequence[str], styles: Any) -> dict[str, dict]:
    """Marker and colour per pick (by position in :data:`DESIGN_STYLES`), trajectory colour and line per name."""
    names = list(dict.fromkeys([*pick_names, *proxy_names]))
    given = _check_styles(styles, names)
    for name, style in given.items():
        unknown = set(style) - set(_DESIGN_STYLE_KEYS)
        if unknown:
            raise InputError(f"styles[{name!r}]: expected keys among {list(_DESIGN_STYLE_KEYS)}, got {sorted(unknown)}")
    out = {}
    for i, name in enumerate(pick_names):
        out[name] = {"linestyle": "-", **DESIGN_STYLES[i % len(DESIGN_STYLES)], **given.get(name, {})}
    others = (dict(color="tab:gray", linestyle="-"), dict(color="tab:olive", linestyle="--"))
    for j, name in enumerate(n for n in proxy_names if n not in out):  # trajectories of no pick: by position
        out[name] = {**others[j % len(others)], **given.get(name, {})}
    return out


def plot_design(
    candidates_xy,
    picks: Mapping[str, Any] | None = None,
    *,
    styles: Mapping[str, Mapping[str, Any]] | None = None,
    proxies: Mapping[str, Any] | None = None,
    proxy_dims: Sequence[int] = (0, 1),
    masses=None,
    domain=None,
    title: str | None = None,
    axis_labels: tuple[str, str] = ("$y_1$", "$y_2$"),
    ax: Axes | None = None,
    legend: bool | str = "right",
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """The candidate initial conditions and the picks of one or more designs among them.

    Args:
        candidates_xy: ``(N, 2)`` plotted coordinates of the candidates (for the gravity set-up, the positions).
        picks: design name -> integer indices (or a boolean mask ``(N,)``) into the candidates, drawn as hollow
            markers so overlapping picks stay visible. Legend text ``"<name> (K=<picks>)"``.
        styles: optional design name -> dict with any of ``marker``, ``color``, ``size`` (marker area, points^2)
            and ``linestyle`` (of its trajectories). A pick without a style gets the one at its position in
            ``picks`` from :data:`DESIGN_STYLES` (black squares, red circles, blue diamonds, ...).
        proxies: optional design name -> ``(K, T, d)`` trajectories (components ``proxy_dims``) drawn thin in the
            design's colour, e.g. the trajectories from the chosen conditions. Trajectories of a name that is not a
            pick are grey (then olive dashed) unless ``styles`` says otherwise.
        masses: optional point masses, rows ``(x, y, m)`` (marker area ~ m), or a dict label -> rows to separate
            e.g. the known mass from the unknown ones.
        domain: optional box ``((x_lo, x_hi), (y_lo, y_hi))`` drawn dashed.
        ax: draw into this Axes instead of a new figure.
        legend: ``"right"`` (default, outside the axes), ``True``/``"axes"``, ``"below"`` or ``False``.
    """
    cand = _as_array(candidates_xy, "candidates_xy")
    if cand.ndim != 2 or cand.shape[1] != 2:
        raise ShapeError(f"candidates_xy: expected shape (N, 2), got {cand.shape}")
    n = cand.shape[0]
    if not isinstance(picks, Mapping):
        raise InputError(f"picks: expected a dict design name -> indices, got {type(picks).__name__}")
    picked = {str(name): _indices(idx, n, f"picks[{name!r}]") for name, idx in picks.items()}
    proxy_arrays = {}
    if proxies is not None:
        if not isinstance(proxies, Mapping):
            raise InputError(f"proxies: expected a dict name -> (K, T, d) trajectories, got {type(proxies).__name__}")
        for name, tr in proxies.items():
            arr = _states(tr, f"proxies[{name!r}]")
            proxy_dims = _check_dims(proxy_dims, arr.shape[2], "proxy_dims")
            proxy_arrays[str(name)] = arr
    style_of = _design_styles(list(picked), list(proxy_arrays), styles)
    mass_groups = _masses(masses) if masses is not None else {}
    box = check_domain(domain, dim=2) if domain is not None else None
    legend = _check_legend(legend)

    fig, ax = _axes(ax, figsize=(PANEL_SIZE[0] + 1.9, PANEL_SIZE[1]))  # room for the legend on the right
    ax.scatter(cand[:, 0], cand[:, 1], s=8, color="0.7", label=f"candidates (N={n})", zorder=1)
    for name, arr in proxy_arrays.items():
        style = style_of[name]
        for k in range(arr.shape[0]):
            ax.plot(
                arr[k, :, proxy_dims[0]],
                arr[k, :, proxy_dims[1]],
                color=style["color"],
                linestyle=style["linestyle"],
                linewidth=0.9,
                alpha=0.7,
                zorder=2,
                label=f"{name} trajectories" if k == 0 else None,
            )
    for name, idx in picked.items():
        style = style_of[name]
        ax.scatter(
            cand[idx, 0],
            cand[idx, 1],
            s=style["size"],
            marker=style["marker"],
            facecolors="none",
            edgecolors=style["color"],
            linewidths=1.6,
            zorder=4,
            label=f"{name} (K={idx.size})",
        )
    mass_colors = ("goldenrod", "tab:red", "tab:purple")
    all_m = np.concatenate([g[:, 2] for g in mass_groups.values()]) if mass_groups else np.ones(1)
    m_max = float(np.abs(all_m).max()) or 1.0
    for j, (label, arr) in enumerate(mass_groups.items()):
        ax.scatter(
            arr[:, 0],
            arr[:, 1],
            s=40 + 360 * np.abs(arr[:, 2]) / m_max,
            marker="o",
            color=mass_colors[j % len(mass_colors)],
            edgecolors="black",
            linewidths=0.8,
            zorder=5,
            label=label,
        )
    if box is not None:
        _draw_box(ax, box, label="domain D")
    ax.set_xlabel(axis_labels[0])
    ax.set_ylabel(axis_labels[1])
    ax.set_title(title if title is not None else "Experimental design")
    ax.set_aspect("equal", adjustable="datalim")
    drawn = _place_legend(ax, ax.get_legend_handles_labels()[0], legend)
    if drawn is not None:
        for handle, text in zip(drawn.legend_handles, drawn.get_texts(), strict=True):
            if text.get_text() in mass_groups:
                handle.set_sizes([70.0])  # mass markers scale with m on the map, not in the legend
    ax.grid(True, alpha=0.3)
    return _finish(fig, path, dpi)


# -------------------------------------------------------------------------------------------------- error curves
def _curve(value, n: int, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    if isinstance(value, tuple):
        if len(value) != 2:
            raise InputError(f"{name}: expected (mean, stderr) or a mean array, got a tuple of {len(value)}")
        mean = _as_array(value[0], f"{name} mean")
        err = None if value[1] is None else _as_array(value[1], f"{name} stderr")
    else:
        mean, err = _as_array(value, f"{name} mean"), None
    if mean.shape != (n,):
        raise ShapeError(f"{name}: expected a mean of shape ({n},) matching ks, got {mean.shape}")
    if err is not None and err.shape != (n,):
        raise ShapeError(f"{name}: expected a stderr of shape ({n},) matching ks, got {err.shape}")
    return mean, err


def plot_error_curves(
    ks,
    curves: Mapping[str, Any],
    *,
    styles: Mapping[str, Mapping[str, Any]] | None = None,
    reference_lines: Mapping[str, float] | None = None,
    ylabel: str = "estimation error",
    xlabel: str = "number of experiments $K$",
    logy: bool = True,
    title: str | None = None,
    ax: Axes | None = None,
    legend: bool | str = True,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Error against the number of experiments, one curve per method with error bars, and reference levels.

    Args:
        ks: ``(n,)`` numbers of experiments.
        curves: method name (the legend text) -> ``(mean, stderr)`` (each ``(n,)``; stderr may be None) or just a
            mean ``(n,)``.
        styles: optional method name -> keywords of ``Axes.errorbar`` (e.g. ``marker``, ``color``, ``linestyle``);
            a curve without one gets marker i of :data:`CURVE_MARKERS` and colour i of matplotlib's cycle, i its
            position in ``curves``.
        reference_lines: label -> level drawn as a horizontal dashed line (e.g. the energy of F, of G + F).
        logy: logarithmic y axis.
        ax: draw into this Axes instead of a new figure.
        legend: ``True``/``"axes"``, ``"right"``, ``"below"`` or ``False``.
    """
    k = _as_array(ks, "ks")
    if k.ndim != 1 or k.size == 0:
        raise ShapeError(f"ks: expected shape (n,) with n >= 1, got {k.shape}")
    if not isinstance(curves, Mapping) or len(curves) == 0:
        raise InputError(f"curves: expected a non-empty dict name -> (mean, stderr), got {type(curves).__name__}")
    data = {str(name): _curve(v, k.size, f"curves[{name!r}]") for name, v in curves.items()}
    given = _check_styles(styles, list(data))
    refs = {}
    for label, level in (reference_lines or {}).items():
        try:
            refs[str(label)] = float(level)
        except (TypeError, ValueError) as exc:
            raise InputError(f"reference_lines[{label!r}]: expected a number, got {level!r}") from exc
    legend = _check_legend(legend)

    fig, ax = _axes(ax)
    for i, (name, (mean, err)) in enumerate(data.items()):
        style = {
            "marker": CURVE_MARKERS[i % len(CURVE_MARKERS)],
            "color": f"C{i % 10}",
            "markersize": 4,
            "capsize": 3,
            "linewidth": 1.3,
            **given.get(name, {}),
        }
        ax.errorbar(k, mean, yerr=err, label=name, **style)
    ref_colors = ("tab:red", "tab:gray", "tab:purple", "tab:brown")
    for i, (label, level) in enumerate(refs.items()):
        ax.axhline(level, linestyle="--", linewidth=1.2, color=ref_colors[i % len(ref_colors)], label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title if title is not None else "Estimation error vs. number of experiments")
    _place_legend(ax, ax.get_legend_handles_labels()[0], legend)
    ax.grid(True, which="both", alpha=0.3)
    return _finish(fig, path, dpi)


# ------------------------------------------------------------------------------------------ uncertainty bands
#: Default central bands of :func:`plot_prediction_bands`, widest first.
BAND_LEVELS = (0.9, 0.5)


def plot_prediction_bands(
    posterior,
    *,
    index: int = 0,
    true_states=None,
    misspecified_states=None,
    levels: Sequence[float] = BAND_LEVELS,
    components: Sequence[int] | None = None,
    component_labels: Sequence[str] | None = None,
    axes=None,
    title: str | None = None,
    legend: bool | str = True,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Predicted uncertainty bands of one initial condition against time, one panel per state component.

    The central ``levels`` bands of the sampled paths of a :class:`~torchmisspec.TrajectoryPosterior` are shaded
    (widest lightest), with the trajectory of the posterior mean (solid), and optionally the true (black) and the
    misspecified (dashed) trajectories from the same initial condition on the same times.

    Args:
        posterior: a :class:`~torchmisspec.TrajectoryPosterior` (``CorrectedODE.posterior``).
        index: which initial condition b of the posterior to draw.
        true_states: optional ``(B, T, d)`` (or a Trajectories) on the posterior's times; row ``index`` is drawn.
        misspecified_states: optional ``(B, T, d)`` likewise.
        levels: central band probabilities in (0, 1).
        components: state components to draw (default: all), one panel each.
        component_labels: y labels of the panels (default ``$y_{j+1}$``).
        axes: draw into these Axes (one per component) instead of a new figure.
        legend: ``True``/``"axes"`` (in the first panel), ``"right"``, ``"below"`` or ``False``.
    """
    samples = getattr(posterior, "samples", None)
    if samples is None or not hasattr(posterior, "interval") or not hasattr(posterior, "mean_path"):
        raise InputError(f"posterior: expected a TrajectoryPosterior, got {type(posterior).__name__}")
    S, B, T, d = samples.shape
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < B:
        raise InputError(f"index: expected an initial condition in [0, {B - 1}], got {index!r}")
    levels = [float(v) for v in levels]
    if not levels or not all(0 < v < 1 for v in levels):
        raise InputError(f"levels: expected band probabilities in (0, 1), got {levels}")
    comps = list(range(d)) if components is None else check_indices(components, d, "components")
    labels = [f"$y_{{{j + 1}}}$" for j in comps] if component_labels is None else list(component_labels)
    if len(labels) != len(comps):
        raise InputError(f"component_labels: expected {len(comps)} labels, got {len(labels)}")
    extra = {}
    for key, value in (("true", true_states), ("misspecified", misspecified_states)):
        if value is not None:
            arr = _states(value, f"{key}_states")
            if arr.shape != (B, T, d):
                raise ShapeError(f"{key}_states: expected shape ({B}, {T}, {d}) as the posterior, got {arr.shape}")
            extra[key] = arr[index]
    legend = _check_legend(legend)
    if axes is None:
        fig, grid = _new_figure(ncols=len(comps))
        panels = list(grid[0])
    else:
        panels = list(np.atleast_1d(axes).ravel())
        if len(panels) != len(comps):
            raise InputError(f"axes: expected {len(comps)} Axes (one per component), got {len(panels)}")
        fig = panels[0].figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    t = _as_array(posterior.times[index], "posterior.times")
    mean = _as_array(posterior.mean_path[index], "posterior.mean_path")
    bands = [
        (level, *(_as_array(q[index], "band") for q in posterior.interval(level)))
        for level in sorted(levels, reverse=True)
    ]
    shades = np.linspace(0.25, 0.55, len(bands))
    for ax, j, label in zip(panels, comps, labels, strict=True):
        for (_, lo, hi), alpha in zip(bands, shades, strict=True):
            ax.fill_between(t, lo[:, j], hi[:, j], color="tab:blue", alpha=float(alpha), linewidth=0)
        ax.plot(t, mean[:, j], color="tab:blue", linewidth=1.5)
        if "true" in extra:
            ax.plot(t, extra["true"][:, j], color="black", linewidth=1.2)
        if "misspecified" in extra:
            ax.plot(t, extra["misspecified"][:, j], color="tab:red", linestyle="--", linewidth=1.2)
        ax.set_xlabel("$t$")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    handles = [
        Patch(color="tab:blue", alpha=float(alpha), label=f"{level:.0%} band ({S} draws)")
        for (level, _, _), alpha in zip(bands, shades, strict=True)
    ]
    handles.append(Line2D([], [], color="tab:blue", linewidth=1.5, label="posterior-mean path"))
    if "true" in extra:
        handles.append(Line2D([], [], color="black", linewidth=1.2, label="true"))
    if "misspecified" in extra:
        handles.append(Line2D([], [], color="tab:red", linestyle="--", linewidth=1.2, label="misspecified"))
    _place_legend(panels[0], handles, legend)
    panels[0].set_title(title if title is not None else f"Predicted bands, initial condition {index}")
    return _finish(fig, path, dpi)


def plot_calibration(
    nominal,
    empirical: Mapping[str, Any],
    *,
    styles: Mapping[str, Mapping[str, Any]] | None = None,
    title: str | None = None,
    ax: Axes | None = None,
    legend: bool | str = True,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Calibration plot: empirical against nominal coverage of central bands, one curve per setting.

    Args:
        nominal: ``(n,)`` nominal band probabilities (e.g. 0.5, 0.9, 0.95).
        empirical: setting name -> ``(mean, stderr)`` (each ``(n,)``; stderr may be None) or a mean ``(n,)``: the
            fraction of true states inside each band.
        styles: optional name -> keywords of ``Axes.errorbar``.
    """
    x = _as_array(nominal, "nominal")
    if x.ndim != 1 or x.size == 0 or not np.all((x > 0) & (x < 1)):
        raise InputError(f"nominal: expected (n,) probabilities in (0, 1), got {x!r:.80}")
    if not isinstance(empirical, Mapping) or not empirical:
        raise InputError(f"empirical: expected a non-empty dict name -> coverage, got {type(empirical).__name__}")
    data = {str(name): _curve(v, x.size, f"empirical[{name!r}]") for name, v in empirical.items()}
    given = _check_styles(styles, list(data))
    legend = _check_legend(legend)
    fig, ax = _axes(ax)
    ax.plot([0, 1], [0, 1], color="0.5", linestyle=":", linewidth=1, label="perfect calibration")
    for i, (name, (mean, err)) in enumerate(data.items()):
        style = {"marker": CURVE_MARKERS[i % len(CURVE_MARKERS)], "capsize": 3, "label": name, **given.get(name, {})}
        ax.errorbar(x, mean, yerr=err, **style)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("nominal coverage of the central band")
    ax.set_ylabel("empirical coverage of the true trajectories")
    ax.set_title(title if title is not None else "Calibration of the predicted bands")
    ax.grid(True, alpha=0.3)
    handles, _ = ax.get_legend_handles_labels()
    _place_legend(ax, handles, legend)
    return _finish(fig, path, dpi)
