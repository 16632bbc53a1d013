"""Generic matplotlib figures: trajectories, error heat maps, designs and error-vs-K curves.

Every function takes tensors or arrays (torch tensors are detached and moved to the CPU; a
:class:`~torchmisspec.data.Trajectories` is accepted wherever states ``(K, T, d)`` are expected), optionally saves a
PNG to ``path``, and returns the :class:`matplotlib.figure.Figure`. Figures are built as ``Figure`` objects, not
through ``pyplot``, so nothing here touches pyplot's global state or needs a display; matplotlib is imported only when
a function is called. The one-panel functions draw into a given ``ax`` when asked, so a caller can compose them into
its own layout (the paper's figures are composed that way in :mod:`torchmisspec.paper.figures`).

Figures: :func:`plot_trajectories` (phase plane: true, misspecified, corrected and further sets),
:func:`plot_training_and_test` (training and test panels side by side), :func:`plot_error_map` (a scalar error over a
box, its colour scale a :class:`ColorScale`), :func:`plot_component_error_maps` (one error map per setting and
output component), :func:`plot_design` (candidates and the picks of several designs), :func:`plot_error_curves`
(error against the number of experiments), :func:`plot_prediction_bands` (uncertainty bands of predicted
trajectories against time) and :func:`plot_calibration` (empirical against nominal coverage of the bands).
:func:`correction_error_fn` builds the error callables the heat maps take from a system with a known F and a fitted
GP.

Styles are explicit: a caller passes ``styles={name: {...}}`` for the names it draws; a name without a style gets
the default for its *position* (:data:`DESIGN_STYLES` for the picks of :func:`plot_design`, :data:`SERIES_STYLES` for
further trajectory sets, matplotlib's colour cycle and :data:`CURVE_MARKERS` for curves), never a style chosen from
what the name says. ``legend`` places the legend: ``True`` / ``"axes"`` inside the axes, ``"right"`` outside on the
right, ``"below"`` one legend for the figure under the panels, ``False`` none.

Heat-map grids follow the image convention: ``grid[i, j]`` is the value at ``x = xs[j]``, ``y = ys[i]``, with ``xs``
and ``ys`` evenly spaced from the domain's lower to upper bounds (both included).

The code is split by concept into private modules: ``_trajectories`` (phase-plane figures), ``_heatmaps`` (error
maps and :func:`correction_error_fn`), ``_design``, ``_curves`` (error against K), ``_uncertainty`` (prediction bands
and calibration) and ``_common`` (array conversion, argument checks, legends, making and saving figures).
"""

from ._common import DPI as DPI  # not in __all__, importable from here as before
from ._common import PANEL_SIZE as PANEL_SIZE
from ._curves import CURVE_MARKERS, plot_error_curves
from ._design import DESIGN_STYLES, plot_design
from ._heatmaps import HEAT_LEVELS as HEAT_LEVELS
from ._heatmaps import ColorScale, correction_error_fn, plot_component_error_maps, plot_error_map
from ._trajectories import SERIES_STYLES, TRAJECTORY_STYLES, plot_training_and_test, plot_trajectories
from ._uncertainty import BAND_LEVELS, plot_calibration, plot_prediction_bands

__all__ = [
    "plot_trajectories",
    "plot_training_and_test",
    "plot_error_map",
    "ColorScale",
    "plot_component_error_maps",
    "correction_error_fn",
    "plot_design",
    "plot_error_curves",
    "plot_prediction_bands",
    "plot_calibration",
    "TRAJECTORY_STYLES",
    "SERIES_STYLES",
    "DESIGN_STYLES",
    "CURVE_MARKERS",
    "BAND_LEVELS",
]
