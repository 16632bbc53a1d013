"""Experimental designs: the candidates and the picks of several designs, :func:`plot_design`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .._errors import InputError, ShapeError
from .._validation import check_domain
from ._common import (
    DPI,
    PANEL_SIZE,
    _as_array,
    _axes,
    _check_dims,
    _check_legend,
    _check_styles,
    _draw_box,
    _finish,
    _place_legend,
    _states,
)

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

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


def _check_picks(picks, n: int) -> dict[str, np.ndarray]:
    """Each design's picks as integer indices into the ``n`` candidates, keyed by the design's name as text."""
    if not isinstance(picks, Mapping):
        raise InputError(f"picks: expected a dict design name -> indices, got {type(picks).__name__}")
    return {str(name): _indices(idx, n, f"picks[{name!r}]") for name, idx in picks.items()}


def _check_proxies(proxies, proxy_dims: Sequence[int]) -> tuple[dict[str, np.ndarray], Sequence[int]]:
    """The trajectories to draw, as ``(K, T, d)`` arrays by name, and the two components checked against each."""
    proxy_arrays = {}
    if proxies is not None:
        if not isinstance(proxies, Mapping):
            raise InputError(f"proxies: expected a dict name -> (K, T, d) trajectories, got {type(proxies).__name__}")
        for name, tr in proxies.items():
            arr = _states(tr, f"proxies[{name!r}]")
            proxy_dims = _check_dims(proxy_dims, arr.shape[2], "proxy_dims")
            proxy_arrays[str(name)] = arr
    return proxy_arrays, proxy_dims


def _draw_proxies(ax: Axes, proxy_arrays: dict[str, np.ndarray], dims: Sequence[int], style_of: dict) -> None:
    """Each name's trajectories as thin lines in its colour and line style, one legend entry per name."""
    for name, arr in proxy_arrays.items():
        style = style_of[name]
        for k in range(arr.shape[0]):
            ax.plot(
                arr[k, :, dims[0]],
                arr[k, :, dims[1]],
                color=style["color"],
                linestyle=style["linestyle"],
                linewidth=0.9,
                alpha=0.7,
                zorder=2,
                label=f"{name} trajectories" if k == 0 else None,
            )


def _draw_picks(ax: Axes, cand: np.ndarray, picked: dict[str, np.ndarray], style_of: dict) -> None:
    """Each design's picks as hollow markers, so that picks shared by several designs stay visible."""
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


def _draw_masses(ax: Axes, mass_groups: dict[str, np.ndarray]) -> None:
    """The point masses, one colour per group, marker area growing with |m| (relative to the largest of all)."""
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


def _legend_with_even_masses(ax: Axes, legend: bool | str, mass_groups: dict[str, np.ndarray]) -> None:
    """Place the legend; its mass markers get one size, since on the map they scale with m, not in the legend."""
    drawn = _place_legend(ax, ax.get_legend_handles_labels()[0], legend)
    if drawn is not None:
        for handle, text in zip(drawn.legend_handles, drawn.get_texts(), strict=True):
            if text.get_text() in mass_groups:
                handle.set_sizes([70.0])


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
    picked = _check_picks(picks, n)
    proxy_arrays, proxy_dims = _check_proxies(proxies, proxy_dims)
    style_of = _design_styles(list(picked), list(proxy_arrays), styles)
    mass_groups = _masses(masses) if masses is not None else {}
    box = check_domain(domain, dim=2) if domain is not None else None
    legend = _check_legend(legend)

    fig, ax = _axes(ax, figsize=(PANEL_SIZE[0] + 1.9, PANEL_SIZE[1]))  # room for the legend on the right
    ax.scatter(cand[:, 0], cand[:, 1], s=8, color="0.7", label=f"candidates (N={n})", zorder=1)
    _draw_proxies(ax, proxy_arrays, proxy_dims, style_of)
    _draw_picks(ax, cand, picked, style_of)
    _draw_masses(ax, mass_groups)
    if box is not None:
        _draw_box(ax, box, label="domain D")
    ax.set_xlabel(axis_labels[0])
    ax.set_ylabel(axis_labels[1])
    ax.set_title(title if title is not None else "Experimental design")
    ax.set_aspect("equal", adjustable="datalim")
    _legend_with_even_masses(ax, legend, mass_groups)
    ax.grid(True, alpha=0.3)
    return _finish(fig, path, dpi)
