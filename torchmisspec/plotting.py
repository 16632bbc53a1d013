"""Matplotlib figures of the paper's §5: trajectories, error heat maps, designs and error-vs-K curves.

Every function takes tensors or arrays (torch tensors are detached and moved to the CPU; a
:class:`~torchmisspec.data.Trajectories` is accepted wherever states ``(K, T, d)`` are expected), optionally saves a
PNG to ``path``, and returns the :class:`matplotlib.figure.Figure`. Figures are built as ``Figure`` objects, not
through ``pyplot``, so nothing here touches pyplot's global state or needs a display; matplotlib is imported only when
a function is called.

Paper figures: :func:`plot_training_and_test` (Fig. 1 and the right panels of Figs. 3 and 6), :func:`plot_error_map`
(Fig. 2), :func:`plot_component_error_maps` (Figs. 4 and 7), :func:`plot_design` (left panels of Figs. 3 and 6),
:func:`plot_error_curves` (Figs. 5 and 8). :func:`correction_error_fn` builds the error callables the heat maps take
from a system with a known F and a fitted GP.

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
    "correction_error_fn",
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
_STYLE = {  # one legend entry per style
    "true": dict(linestyle="-", linewidth=1.3, label="true (G + F)"),
    "misspecified": dict(linestyle="--", linewidth=1.1, label="misspecified (G)"),
    "corrected": dict(linestyle=":", linewidth=1.8, label=r"corrected (G + $\hat F$)", color="black", zorder=2.5),
}


# --------------------------------------------------------------------------------------------------- helpers
def _as_array(x: Any, name: str) -> np.ndarray:
    """A float64 numpy array from a tensor, array, nested sequence or Trajectories (its states)."""
    if hasattr(x, "states") and hasattr(x, "times"):  # Trajectories
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
    try:
        out = tuple(int(i) for i in dims)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected two component indices, got {dims!r}") from exc
    if len(out) != 2:
        raise InputError(f"{name}: expected two component indices (x, y), got {len(out)}: {list(out)}")
    for i in out:
        if not 0 <= i < d:
            raise InputError(f"{name}: expected indices in [0, {d - 1}] for states with d={d}, got {list(out)}")
    if out[0] == out[1]:
        raise InputError(f"{name}: expected two distinct components, got {list(out)}")
    return out  # type: ignore[return-value]


def _check_domain(domain: Any, name: str = "domain") -> tuple[tuple[float, float], tuple[float, float]]:
    try:
        arr = np.asarray(domain, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected ((x_lo, x_hi), (y_lo, y_hi)), got {domain!r}") from exc
    if arr.shape != (2, 2):
        raise ShapeError(f"{name}: expected shape (2, 2) as ((x_lo, x_hi), (y_lo, y_hi)), got {arr.shape}")
    if not np.isfinite(arr).all() or not (arr[:, 0] < arr[:, 1]).all():
        raise InputError(f"{name}: expected finite bounds with lo < hi, got {arr.tolist()}")
    return (float(arr[0, 0]), float(arr[0, 1])), (float(arr[1, 0]), float(arr[1, 1]))


def _new_figure(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float] | None = None):
    from matplotlib.figure import Figure

    if figsize is None:
        figsize = (PANEL_SIZE[0] * ncols, PANEL_SIZE[1] * nrows)
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


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
def plot_trajectories(
    true_states,
    misspecified_states=None,
    corrected_states=None,
    *,
    dims: Sequence[int] = (0, 1),
    ax: Axes | None = None,
    title: str | None = None,
    axis_labels: tuple[str, str] | None = None,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Phase-plane plot of K trajectories: true solid, misspecified dashed, corrected dotted.

    Trajectory k has the same colour in every style; the initial conditions ``true_states[:, 0]`` are black dots.
    The legend has one entry per style present, plus the initial conditions.

    Args:
        true_states: ``(K, T, d)`` states of the true system (or a Trajectories).
        misspecified_states, corrected_states: optional ``(K, T', d)`` predictions from the same K initial
            conditions (their time grids may differ from the true one).
        dims: the two state components to plot on the x and y axes.
        ax: draw into this Axes instead of a new figure.
        title: axes title (default ``"Trajectories (K=...)"``).
        axis_labels: x and y labels (default ``$y_{i+1}$``).
        path: save the figure as PNG here.
    """
    true = _states(true_states, "true_states")
    K, _, d = true.shape
    series = {"true": true}
    for key, value in (("misspecified", misspecified_states), ("corrected", corrected_states)):
        if value is None:
            continue
        arr = _states(value, f"{key}_states")
        if arr.shape[0] != K or arr.shape[2] != d:
            raise ShapeError(
                f"{key}_states: expected shape ({K}, T, {d}) to match true_states {true.shape}, got {arr.shape}"
            )
        series[key] = arr
    dims = _check_dims(dims, d)
    if ax is None:
        fig, axes = _new_figure()
        ax = axes[0, 0]
    else:
        fig = ax.figure
    from matplotlib.lines import Line2D

    for key, arr in series.items():
        style = {k: v for k, v in _STYLE[key].items() if k != "label"}
        fixed = style.pop("color", None)  # the corrected ones are black, on top, so they stay visible
        for k in range(K):  # otherwise trajectory k has one colour in every style
            ax.plot(arr[k, :, dims[0]], arr[k, :, dims[1]], color=fixed or _TRAJ_COLORS[k % len(_TRAJ_COLORS)], **style)
    ax.plot(
        true[:, 0, dims[0]], true[:, 0, dims[1]], linestyle="none", marker="o", markersize=4, color="black", zorder=3
    )
    handles = [Line2D([], [], **{"color": "0.25", **_STYLE[key]}) for key in series]
    handles.append(
        Line2D([], [], linestyle="none", marker="o", markersize=4, color="black", label="initial conditions")
    )
    ax.legend(handles=handles, loc="best", fontsize="small", framealpha=0.8)
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
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Paper Fig. 1: training set (left: true vs misspecified) and test set (right: true, misspecified, corrected).

    Args:
        train_true, train_misspecified: ``(K, T, d)`` training trajectories of the true and the misspecified model.
        test_true, test_misspecified, test_corrected: ``(K', T, d)`` test trajectories, the last from the
            corrected model G + mu.
        dims, axis_labels: as in :func:`plot_trajectories`.
        titles: the two panel titles.
    """
    fig, axes = _new_figure(1, 2)
    k_train = _states(train_true, "train_true").shape[0]
    k_test = _states(test_true, "test_true").shape[0]
    titles = titles if titles is not None else (f"Training set (K={k_train})", f"Test set (K={k_test})")
    plot_trajectories(
        train_true, train_misspecified, dims=dims, ax=axes[0, 0], title=titles[0], axis_labels=axis_labels
    )
    plot_trajectories(
        test_true, test_misspecified, test_corrected, dims=dims, ax=axes[0, 1], title=titles[1], axis_labels=axis_labels
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


def _check_resolution(resolution: Any) -> int:
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 2:
        raise InputError(f"resolution: expected an integer >= 2, got {resolution!r}")
    return int(resolution)


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
    """Paper Fig. 2: heat map of a scalar error over the box ``domain``, training traces overlaid in white.

    Args:
        error_fn_or_grid: a callable mapping points ``(M, 2)`` (float64 tensor) to values ``(M,)``, evaluated on a
            ``resolution x resolution`` grid; or a precomputed grid ``(res_y, res_x)`` over ``domain`` (see the
            module docstring for the orientation).
        domain: ``((x_lo, x_hi), (y_lo, y_hi))``, e.g. ``system.domain``.
        traces: optional ``(K, T, d)`` trajectories drawn as white lines with dots (components ``trace_dims``).
        log_scale: logarithmic colour scale (non-positive values are left blank).
        vmin, vmax: colour-scale limits.
        dashed_box: optional ``((x_lo, x_hi), (y_lo, y_hi))`` drawn dashed, e.g. the region D inside a larger map.
    """
    domain = _check_domain(domain)
    resolution = _check_resolution(resolution)
    grid = _scalar_grid(error_fn_or_grid, domain, resolution, "error_fn_or_grid")
    if ax is None:
        fig, axes = _new_figure(figsize=(PANEL_SIZE[0] + 0.6, PANEL_SIZE[1]))
        ax = axes[0, 0]
    else:
        fig = ax.figure
    im = _draw_heat(ax, grid, domain, vmin=vmin, vmax=vmax, log_scale=log_scale)
    fig.colorbar(im, ax=ax, label=cbar_label)
    if traces is not None:
        _overlay_traces(ax, traces, trace_dims, "traces")
    if dashed_box is not None:
        _draw_box(ax, _check_domain(dashed_box, "dashed_box"), color="white")
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
    """Paper Figs. 4 and 7: a grid of error heat maps, one row per setting and one column per output component.

    Each component (column) shares one colour scale across the settings, so the settings compare at a glance.

    Args:
        maps: setting name (e.g. ``"random"``, ``"design"``) -> the per-component errors, as a callable mapping
            points ``(M, 2)`` to ``(M,)`` or ``(M, C)`` (see :func:`correction_error_fn` with ``component="all"``),
            an array ``(res, res)`` or ``(C, res, res)``, or a sequence of C callables / 2-D grids. Every setting
            must give the same number C of components.
        domain: ``((x_lo, x_hi), (y_lo, y_hi))``.
        traces: optional setting name -> ``(K, T, d)`` training trajectories overlaid on that setting's panels.
        component_labels: the C column titles / colour-bar labels (default ``|F̂_i - F_i|``, i = 1..C).
        settings_as_columns: transpose the layout (settings across, components down), as in paper Fig. 7.
        log_scale, dashed_box: as in :func:`plot_error_map`.
    """
    if not isinstance(maps, Mapping) or len(maps) == 0:
        raise InputError(f"maps: expected a non-empty dict setting name -> errors, got {type(maps).__name__}")
    domain = _check_domain(domain)
    resolution = _check_resolution(resolution)
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
        dashed_box = _check_domain(dashed_box, "dashed_box")
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
def _marker_for(name: str, i: int) -> tuple[str, str, float]:
    low = name.lower()
    if "random" in low:
        return "o", "tab:red", 45.0
    if "agnostic" in low:
        return "D", "tab:blue", 55.0
    if "design" in low or "misspec" in low:
        return "s", "black", 90.0
    others = (("^", "tab:green"), ("v", "tab:purple"), ("P", "tab:brown"), ("X", "tab:pink"))
    m, c = others[i % len(others)]
    return m, c, 60.0


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


def plot_design(
    candidates_xy,
    chosen: Mapping[str, Any],
    *,
    proxies: Mapping[str, Any] | None = None,
    proxy_dims: Sequence[int] = (0, 1),
    masses=None,
    domain=None,
    title: str | None = None,
    axis_labels: tuple[str, str] = ("$y_1$", "$y_2$"),
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Paper Fig. 3 (left) and Fig. 6 (left): the candidate initial conditions and the designs picked among them.

    Args:
        candidates_xy: ``(N, 2)`` plotted coordinates of the candidates (for the gravity set-up, the positions).
        chosen: design name -> integer indices (or a boolean mask) into the candidates. Names containing
            ``"design"``/``"misspec"`` get black squares, ``"random"`` red circles, ``"agnostic"`` blue diamonds,
            others further markers; markers are hollow so overlapping picks stay visible.
        proxies: optional design name -> ``(K, T, d)`` trajectories (components ``proxy_dims``) drawn thin in the
            design's colour, e.g. the misspecified model's proxy trajectories from the chosen conditions.
        masses: optional point masses, rows ``(x, y, m)`` (marker area ~ m), or a dict label -> rows to separate
            e.g. the known mass from the unknown ones.
        domain: optional box ``((x_lo, x_hi), (y_lo, y_hi))`` drawn dashed.
    """
    cand = _as_array(candidates_xy, "candidates_xy")
    if cand.ndim != 2 or cand.shape[1] != 2:
        raise ShapeError(f"candidates_xy: expected shape (N, 2), got {cand.shape}")
    n = cand.shape[0]
    if not isinstance(chosen, Mapping):
        raise InputError(f"chosen: expected a dict design name -> indices, got {type(chosen).__name__}")
    picks = {str(name): _indices(idx, n, f"chosen[{name!r}]") for name, idx in chosen.items()}
    styles = {name: _marker_for(name, i) for i, name in enumerate(picks)}
    proxy_arrays = {}
    if proxies is not None:
        for name, tr in proxies.items():
            arr = _states(tr, f"proxies[{name!r}]")
            proxy_dims = _check_dims(proxy_dims, arr.shape[2], "proxy_dims")
            proxy_arrays[str(name)] = arr
    mass_groups = _masses(masses) if masses is not None else {}
    box = _check_domain(domain) if domain is not None else None

    fig, axes = _new_figure(figsize=(PANEL_SIZE[0] + 1.9, PANEL_SIZE[1]))  # room for the legend on the right
    ax = axes[0, 0]
    ax.scatter(cand[:, 0], cand[:, 1], s=8, color="0.7", label=f"candidates (N={n})", zorder=1)
    extra = (("-", "tab:gray"), ("--", "tab:olive"))
    for j, (name, arr) in enumerate(proxy_arrays.items()):
        color = styles[name][1] if name in styles else extra[j % 2][1]
        ls = "-" if name in styles else extra[j % 2][0]
        for k in range(arr.shape[0]):
            ax.plot(
                arr[k, :, proxy_dims[0]],
                arr[k, :, proxy_dims[1]],
                color=color,
                linestyle=ls,
                linewidth=0.9,
                alpha=0.7,
                zorder=2,
                label=f"{name} trajectories" if k == 0 else None,
            )
    for name, idx in picks.items():
        marker, color, size = styles[name]
        ax.scatter(
            cand[idx, 0],
            cand[idx, 1],
            s=size,
            marker=marker,
            facecolors="none",
            edgecolors=color,
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
    legend = ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small", borderaxespad=0.0)
    for handle, text in zip(legend.legend_handles, legend.get_texts(), strict=True):
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
    reference_lines: Mapping[str, float] | None = None,
    ylabel: str = "estimation error",
    xlabel: str = "number of experiments $K$",
    logy: bool = True,
    title: str | None = None,
    path: str | Path | None = None,
    dpi: int = DPI,
) -> Figure:
    """Paper Figs. 5 and 8: error against the number of experiments, with error bars and reference levels.

    Args:
        ks: ``(n,)`` numbers of experiments.
        curves: method name -> ``(mean, stderr)`` (each ``(n,)``; stderr may be None) or just a mean ``(n,)``.
        reference_lines: label -> level drawn as a horizontal dashed line (e.g. the energy of F, of G + F).
        logy: logarithmic y axis.
    """
    k = _as_array(ks, "ks")
    if k.ndim != 1 or k.size == 0:
        raise ShapeError(f"ks: expected shape (n,) with n >= 1, got {k.shape}")
    if not isinstance(curves, Mapping) or len(curves) == 0:
        raise InputError(f"curves: expected a non-empty dict name -> (mean, stderr), got {type(curves).__name__}")
    data = {str(name): _curve(v, k.size, f"curves[{name!r}]") for name, v in curves.items()}
    refs = {}
    for label, level in (reference_lines or {}).items():
        try:
            refs[str(label)] = float(level)
        except (TypeError, ValueError) as exc:
            raise InputError(f"reference_lines[{label!r}]: expected a number, got {level!r}") from exc

    fig, axes = _new_figure()
    ax = axes[0, 0]
    markers = ("o", "s", "^", "D", "v", "P")
    for i, (name, (mean, err)) in enumerate(data.items()):
        ax.errorbar(
            k, mean, yerr=err, marker=markers[i % len(markers)], markersize=4, capsize=3, linewidth=1.3, label=name
        )
    ref_colors = ("tab:red", "tab:gray", "tab:purple", "tab:brown")
    for i, (label, level) in enumerate(refs.items()):
        ax.axhline(level, linestyle="--", linewidth=1.2, color=ref_colors[i % len(ref_colors)], label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title if title is not None else "Estimation error vs. number of experiments")
    ax.legend(loc="best", fontsize="small", framealpha=0.85)
    ax.grid(True, which="both", alpha=0.3)
    return _finish(fig, path, dpi)
