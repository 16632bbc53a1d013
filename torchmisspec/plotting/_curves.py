"""Error against the number of experiments: :func:`plot_error_curves` (and :func:`_curve`, the curve argument
check it shares with :func:`~torchmisspec.plotting.plot_calibration`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._errors import InputError, ShapeError
from ._common import DPI, _as_array, _axes, _check_legend, _check_styles, _finish, _place_legend

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Default markers of the curves of :func:`plot_error_curves`, by position (colours: matplotlib's cycle).
CURVE_MARKERS = ("o", "s", "^", "D", "v", "P")


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
    if err is not None and bool((err < 0).any()):
        raise InputError(f"{name}: expected standard errors >= 0, got {float(err[err < 0][0]):g}")
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
    if logy:
        for name, (mean, _) in data.items():
            if not bool((mean > 0).all()):
                raise InputError(
                    f"curves[{name!r}]: expected positive values on a logarithmic axis, got {float(mean.min()):g}; "
                    "pass logy=False"
                )

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
