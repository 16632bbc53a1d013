"""Uncertainty: the predicted bands of trajectories against time (:func:`plot_prediction_bands`) and how well they
cover (:func:`plot_calibration`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._errors import InputError, ShapeError
from .._validation import check_indices
from ._common import DPI, _as_array, _axes, _check_legend, _check_styles, _finish, _new_figure, _place_legend, _states
from ._curves import CURVE_MARKERS, _curve

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

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
        component_labels: y labels of the panels (default: the system's state names the posterior carries, else
            ``$y_{j+1}$``).
        axes: draw into these Axes (one per component) instead of a new figure.
        legend: ``True``/``"axes"`` (in the first panel), ``"right"``, ``"below"`` or ``False``.
    """
    samples = getattr(posterior, "samples", None)
    if samples is None or not hasattr(posterior, "interval") or not hasattr(posterior, "mean_path"):
        raise InputError(f"posterior: expected a TrajectoryPosterior, got {type(posterior).__name__}")
    S, B, T, d = samples.shape
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < B:
        raise InputError(f"index: expected an initial condition in [0, {B - 1}], got {index!r}")
    given = levels
    levels = [float(v) for v in _as_array(levels, "levels").reshape(-1)] if levels is not None else []
    if not levels or not all(0 < v < 1 for v in levels):
        raise InputError(f"levels: expected band probabilities in (0, 1), got {given!r:.60}")
    comps = list(range(d)) if components is None else check_indices(components, d, "components")
    names = getattr(posterior, "state_names", None)
    default = [names[j] if names else f"$y_{{{j + 1}}}$" for j in comps]
    labels = default if component_labels is None else list(component_labels)
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
