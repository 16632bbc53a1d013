"""Trajectories in the phase plane: :func:`plot_trajectories` and :func:`plot_training_and_test`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._errors import InputError, ShapeError
from ._common import DPI, _axes, _check_dims, _check_legend, _check_styles, _finish, _new_figure, _place_legend, _states

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

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
