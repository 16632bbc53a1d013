"""Error heat maps over a box: :func:`plot_error_map` (its colour scale a :class:`ColorScale`),
:func:`plot_component_error_maps`, and :func:`correction_error_fn` (the error callables they take)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .._errors import InputError, ShapeError, TorchMisspecError
from .._validation import check_domain, check_flag, check_positive_int, check_real
from ._common import DPI, PANEL_SIZE, _as_array, _axes, _check_dims, _draw_box, _finish, _new_figure, _states

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from ..gp import CorrectionGP
    from ..systems import MisspecifiedSystem

HEAT_LEVELS = 48  # colour levels of the heat maps


@dataclass(frozen=True)
class ColorScale:
    """The colour scale of :func:`plot_error_map`: linear or logarithmic, its limits fixed or read from the values.

    Attributes:
        log: logarithmic colour scale (non-positive values are left blank).
        vmin: lower limit (default ``None``: the smallest finite value, the smallest positive one when ``log``).
        vmax: upper limit (default ``None``: the largest finite value, the largest positive one when ``log``).

    Example: ``plot_error_map(fn, domain, scale=ColorScale(log=True, vmax=1.0))``.
    """

    log: bool = False
    vmin: float | None = None
    vmax: float | None = None

    def __post_init__(self) -> None:
        check_flag(self.log, "ColorScale.log")
        for name in ("vmin", "vmax"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, check_real(value, f"ColorScale.{name}"))


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
    scale: ColorScale | None = None,
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
        scale: the colour scale, a :class:`ColorScale` (default ``ColorScale()``: linear, from the smallest to the
            largest finite value); e.g. ``ColorScale(log=True)``, ``ColorScale(vmin=0.0, vmax=1.0)``.
        dashed_box: optional ``((x_lo, x_hi), (y_lo, y_hi))`` drawn dashed, e.g. the region D inside a larger map.
    """
    domain = check_domain(domain, dim=2)
    resolution = check_positive_int(resolution, "resolution", minimum=2)
    if scale is None:
        scale = ColorScale()
    elif not isinstance(scale, ColorScale):
        raise InputError(
            f"scale: expected a ColorScale (e.g. ColorScale(log=True, vmin=1e-3)), got {type(scale).__name__}"
        )
    grid = _scalar_grid(error_fn_or_grid, domain, resolution, "error_fn_or_grid")
    fig, ax = _axes(ax, figsize=(PANEL_SIZE[0] + 0.6, PANEL_SIZE[1]))
    im = _draw_heat(ax, grid, domain, vmin=scale.vmin, vmax=scale.vmax, log_scale=scale.log)
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
        log_scale: logarithmic colour scales (non-positive values are left blank), as ``ColorScale(log=True)`` in
            :func:`plot_error_map`.
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
