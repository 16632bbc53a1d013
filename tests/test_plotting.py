"""Tests of torchmisspec.plotting: every figure writes a PNG, draws the expected artists in the styles asked for (or
the documented defaults by position), and rejects bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmisspec._errors import InputError, ShapeError
from torchmisspec.data import Trajectories
from torchmisspec.gp import CorrectionGP
from torchmisspec.plotting import (
    DESIGN_STYLES,
    SERIES_STYLES,
    ColorScale,
    correction_error_fn,
    plot_component_error_maps,
    plot_design,
    plot_error_curves,
    plot_error_map,
    plot_training_and_test,
    plot_trajectories,
)
from torchmisspec.systems import LinearField, MisspecifiedSystem, paper_gravity, paper_linear

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DOMAIN = ((-1.0, 1.0), (-2.0, 2.0))


def assert_png(path) -> None:
    data = path.read_bytes()
    assert len(data) > 1000
    assert data[:8] == PNG_MAGIC


def spirals(K: int, T: int = 15, d: int = 2, *, shift: float = 0.0, seed: int = 0) -> torch.Tensor:
    """K decaying spirals (K, T, d) in float64; extra components are small noise."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 3, T, dtype=torch.float64)
    r0 = 0.3 + 0.7 * torch.rand(K, 1, generator=g, dtype=torch.float64)
    ph = 6.28 * torch.rand(K, 1, generator=g, dtype=torch.float64)
    r = r0 * torch.exp(-0.1 * t)
    xy = torch.stack([r * torch.cos(ph + t + shift), r * torch.sin(ph + t + shift)], dim=-1)
    if d > 2:
        xy = torch.cat([xy, 0.01 * torch.randn(K, T, d - 2, generator=g, dtype=torch.float64)], dim=-1)
    return xy


def legend_labels(ax) -> list[str]:
    return [t.get_text() for t in ax.get_legend().get_texts()]


# ------------------------------------------------------------------------------------------------ trajectories
@pytest.mark.parametrize("as_numpy", [False, True])
def test_plot_trajectories_all_styles(tmp_path, as_numpy):
    true, mis, cor = spirals(3), spirals(3, shift=0.1), spirals(3, shift=0.02)
    if as_numpy:
        true, mis, cor = true.numpy(), mis.numpy(), cor.numpy()
    path = tmp_path / "traj.png"
    fig = plot_trajectories(true, mis, cor, title="demo", path=path)
    assert_png(path)
    (ax,) = fig.axes
    assert len(ax.lines) == 3 * 3 + 1  # K per style + the initial-condition dots
    assert len(legend_labels(ax)) == 4
    assert ax.get_title() == "demo"
    assert ax.get_xlabel() == "$y_{1}$" and ax.get_ylabel() == "$y_{2}$"
    dots = ax.lines[-1]
    np.testing.assert_allclose(dots.get_xdata(), np.asarray(true)[:, 0, 0])


def test_plot_trajectories_true_only_trajectories_object_and_dims(tmp_path):
    states = spirals(4, T=10, d=4)
    traj = Trajectories(torch.linspace(0, 1, 10, dtype=torch.float64), states)
    fig = plot_trajectories(traj, dims=(1, 3), path=tmp_path / "t.png")
    (ax,) = fig.axes
    assert len(ax.lines) == 4 + 1
    assert legend_labels(ax) == ["true (G + F)", "initial conditions"]
    assert ax.get_xlabel() == "$y_{2}$" and ax.get_ylabel() == "$y_{4}$"
    np.testing.assert_allclose(ax.lines[0].get_ydata(), states[0, :, 3].numpy())


def test_plot_trajectories_misspecified_may_use_another_time_grid():
    fig = plot_trajectories(spirals(2, T=10), spirals(2, T=40))
    assert len(fig.axes[0].lines) == 2 * 2 + 1


def test_plot_trajectories_into_given_axes():
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    out = plot_trajectories(spirals(2), ax=ax)
    assert out is fig and len(ax.lines) == 3


def test_plot_trajectories_rejects_bad_shapes():
    with pytest.raises(ShapeError, match=r"true_states: expected shape \(K, T, d\), got \(5, 2\)"):
        plot_trajectories(torch.zeros(5, 2))
    with pytest.raises(ShapeError, match=r"misspecified_states: expected shape \(3, T, 2\).*got \(2, 15, 2\)"):
        plot_trajectories(spirals(3), spirals(2))
    with pytest.raises(ShapeError, match=r"corrected_states: expected shape \(3, T, 2\).*got \(3, 15, 3\)"):
        plot_trajectories(spirals(3), corrected_states=spirals(3, d=3))
    with pytest.raises(InputError, match=r"dims: expected indices in \[0, 1\], got 2 in \[0, 2\]"):
        plot_trajectories(spirals(3), dims=(0, 2))
    with pytest.raises(InputError, match=r"dims: expected two component indices \(x, y\), got 3"):
        plot_trajectories(spirals(3, d=3), dims=(0, 1, 2))
    with pytest.raises(InputError, match="distinct"):
        plot_trajectories(spirals(3), dims=(1, 1))
    with pytest.raises(InputError, match=r"path: expected a \.png"):
        plot_trajectories(spirals(3), path="figure.pdf")


def test_plot_training_and_test(tmp_path):
    path = tmp_path / "sub" / "fig1.png"  # parent folders are created
    fig = plot_training_and_test(
        spirals(5),
        spirals(5, shift=0.1).numpy(),
        spirals(2, seed=1),
        spirals(2, seed=1, shift=0.1),
        spirals(2, seed=1, shift=0.01),
        path=path,
    )
    assert_png(path)
    left, right = fig.axes
    assert len(left.lines) == 2 * 5 + 1 and len(right.lines) == 3 * 2 + 1
    assert len(legend_labels(left)) == 3 and len(legend_labels(right)) == 4
    assert "Training" in left.get_title() and "Test" in right.get_title()
    with pytest.raises(ShapeError, match=r"corrected_states: expected shape \(2, T, 2\)"):
        plot_training_and_test(spirals(5), spirals(5), spirals(2), spirals(2), spirals(3))


# -------------------------------------------------------------------------------------------------- heat maps
def test_plot_error_map_callable_and_grid_agree(tmp_path):
    seen = {}

    def fn(x: torch.Tensor) -> torch.Tensor:
        seen["dtype"], seen["shape"] = x.dtype, tuple(x.shape)
        return x[:, 0] + 10 * x[:, 1]

    path = tmp_path / "map.png"
    fig = plot_error_map(fn, DOMAIN, traces=spirals(3), resolution=21, title="err", path=path)
    assert_png(path)
    assert seen == {"dtype": torch.float64, "shape": (21 * 21, 2)}
    ax, cbar = fig.axes  # the map and its colour bar
    assert ax.get_title() == "err" and ax.get_xlabel() == "$y_1$"
    assert len(ax.lines) == 3 and ax.lines[0].get_color() == "white"
    grid = np.asarray(ax.images[0].get_array())
    xs, ys = np.linspace(-1, 1, 21), np.linspace(-2, 2, 21)
    np.testing.assert_allclose(grid, xs[None, :] + 10 * ys[:, None])  # grid[i, j] is at (xs[j], ys[i])
    assert ax.images[0].get_extent() == [-1.0, 1.0, -2.0, 2.0]
    assert cbar.get_ylabel()  # labelled colour bar
    fig2 = plot_error_map(torch.from_numpy(grid), DOMAIN, path=tmp_path / "grid.png")
    np.testing.assert_allclose(np.asarray(fig2.axes[0].images[0].get_array()), grid)


def test_plot_error_map_log_scale_and_dashed_box():
    fig = plot_error_map(
        lambda x: x.pow(2).sum(-1) + 1e-6,
        DOMAIN,
        resolution=11,
        scale=ColorScale(log=True),
        dashed_box=((-0.5, 0.5), (-1.0, 1.0)),
    )
    ax = fig.axes[0]
    assert type(ax.images[0].norm).__name__ == "LogNorm"
    assert len(ax.patches) == 1


def test_plot_error_map_colour_scale_limits_and_its_checks():
    grid = np.arange(25, dtype=float).reshape(5, 5)
    fig = plot_error_map(grid, DOMAIN, scale=ColorScale(vmin=2, vmax=10.0))
    assert fig.axes[0].images[0].get_clim() == (2.0, 10.0)
    with pytest.raises(InputError, match=r"scale: expected a ColorScale \(e.g. ColorScale\(log=True"):
        plot_error_map(grid, DOMAIN, scale={"log": True})
    with pytest.raises(InputError, match="ColorScale.log: expected True or False, got 'yes'"):
        ColorScale(log="yes")
    with pytest.raises(InputError, match="ColorScale.vmax: expected a finite number, got nan"):
        ColorScale(vmax=float("nan"))


def test_plot_error_map_colour_scale_ignores_non_finite_values():
    grid = np.arange(25, dtype=float).reshape(5, 5)
    grid[2, 2], grid[0, 0] = np.inf, np.nan  # e.g. F at a point mass
    fig = plot_error_map(grid, DOMAIN)
    assert fig.axes[0].images[0].get_clim() == (1.0, 24.0)


def test_plot_error_map_rejects_bad_inputs():
    with pytest.raises(ShapeError, match=r"expected the callable to return shape \(121,\).*got \(121, 3\)"):
        plot_error_map(lambda x: torch.zeros(x.shape[0], 3), DOMAIN, resolution=11)
    with pytest.raises(ShapeError, match=r"expected a callable or a 2-D grid.*got shape \(10,\)"):
        plot_error_map(np.zeros(10), DOMAIN)
    with pytest.raises(ShapeError, match=r"domain: expected 2 intervals \(lo, hi\), got 3"):
        plot_error_map(np.zeros((5, 5)), ((0, 1), (0, 1), (0, 1)))
    with pytest.raises(InputError, match="lo < hi"):
        plot_error_map(np.zeros((5, 5)), ((1, 0), (0, 1)))
    with pytest.raises(InputError, match="resolution"):
        plot_error_map(lambda x: x[:, 0], DOMAIN, resolution=1)
    with pytest.raises(ShapeError, match=r"traces: expected shape \(K, T, d\)"):
        plot_error_map(np.zeros((5, 5)), DOMAIN, traces=np.zeros((4, 2)))
    with pytest.raises(InputError, match=r"failed: ZeroDivisionError"):
        plot_error_map(lambda x: 1 / 0, DOMAIN, resolution=5)


def test_plot_component_error_maps_layout_and_shared_scale(tmp_path):
    maps = {
        "random": lambda x: torch.stack([x[:, 0].abs(), 2 * x[:, 1].abs()], dim=-1),  # (M, 2)
        "design": [lambda x: 0.5 * x[:, 0].abs(), np.full((11, 11), 0.1)],  # one per component
    }
    path = tmp_path / "fig4.png"
    fig = plot_component_error_maps(maps, DOMAIN, traces={"design": spirals(2)}, resolution=11, path=path)
    assert_png(path)
    maps_axes = [ax for ax in fig.axes if ax.images]
    assert len(maps_axes) == 4 and len(fig.axes) == 4 + 2  # 2 x 2 maps and one colour bar per column
    by_title = {ax.get_title(): ax for ax in maps_axes}

    def panel(setting: str, c: int):
        return by_title[rf"{setting}: $|\hat F_{{{c}}} - F_{{{c}}}|$"]

    assert len(by_title) == 4
    for c in (1, 2):
        assert panel("random", c).images[0].get_clim() == panel("design", c).images[0].get_clim()  # shared scale
    assert panel("random", 2).images[0].get_clim() == pytest.approx((0.0, 4.0))
    assert panel("random", 1).images[0].get_clim() == pytest.approx((0.0, 1.0))
    assert len(panel("design", 1).lines) == 2 and len(panel("random", 1).lines) == 0
    assert path.stat().st_size < 150_000


def test_plot_component_error_maps_grids_transposed_and_labels():
    grids = {"agnostic": torch.rand(1, 9, 9), "design": np.random.default_rng(0).random((9, 9))}
    fig = plot_component_error_maps(grids, DOMAIN, settings_as_columns=True, component_labels=["|err|"])
    maps_axes = [ax for ax in fig.axes if ax.images]
    assert len(maps_axes) == 2
    assert maps_axes[0].get_title() == "agnostic: |err|"


def test_plot_component_error_maps_rejects_inconsistent_inputs():
    with pytest.raises(ShapeError, match=r"same number of components for every setting, got \{'a': 2, 'b': 1\}"):
        plot_component_error_maps({"a": np.zeros((2, 5, 5)), "b": np.zeros((5, 5))}, DOMAIN)
    with pytest.raises(ShapeError, match=r"expected 2 labels \(one per component\), got 1"):
        plot_component_error_maps({"a": np.zeros((2, 5, 5))}, DOMAIN, component_labels=["x"])
    with pytest.raises(InputError, match=r"traces: expected keys among the settings \['a'\]"):
        plot_component_error_maps({"a": np.zeros((5, 5))}, DOMAIN, traces={"b": spirals(2)})
    with pytest.raises(ShapeError, match=r"maps\['a'\]: expected the callable to return shape \(25,\) or \(25, C\)"):
        plot_component_error_maps({"a": lambda x: torch.zeros(3)}, DOMAIN, resolution=5)
    with pytest.raises(InputError, match="non-empty dict"):
        plot_component_error_maps({}, DOMAIN)


# ----------------------------------------------------------------------------------------- correction errors
def fitted_gp(system, n: int = 30) -> CorrectionGP:
    g = torch.Generator().manual_seed(0)
    X = (2 * torch.rand(n, system.input_dim, generator=g, dtype=torch.float64) - 1) * 2
    return CorrectionGP(lengthscale=1.0, outputscale=1e-2, noise_variance=1e-6).fit(X, system.true_correction(X))


@pytest.mark.parametrize("make", [paper_linear, paper_gravity])
def test_correction_error_fn(make):
    system = make()
    gp = fitted_gp(system)
    pts = torch.tensor([[0.3, -0.2], [1.2, 0.9], [-0.7, 1.5]], dtype=torch.float64)
    diff = gp.predict_mean(pts) - system.true_correction(pts)
    torch.testing.assert_close(correction_error_fn(system, gp)(pts), diff.norm(dim=-1))
    torch.testing.assert_close(correction_error_fn(system, gp, component=1)(pts), diff[:, 1].abs())
    torch.testing.assert_close(correction_error_fn(system, gp, component="all")(pts), diff.abs())
    fig = plot_error_map(correction_error_fn(system, gp), system.domain, resolution=15)
    assert np.isfinite(np.asarray(fig.axes[0].images[0].get_array())).all()


def test_correction_error_fn_rejects_bad_inputs():
    system = paper_linear()
    gp = fitted_gp(system)
    with pytest.raises(InputError, match=r"component: expected None, 'all' or an integer in \[0, 1\], got 2"):
        correction_error_fn(system, gp, component=2)
    three = MisspecifiedSystem(LinearField(torch.eye(3)), 3, correction=lambda y: y)
    with pytest.raises(ShapeError, match="expected a correction with 2 inputs.*got 3"):
        correction_error_fn(three, gp)
    unknown = MisspecifiedSystem(LinearField(torch.eye(2)), 2)
    with pytest.raises(InputError, match="no true correction"):
        correction_error_fn(unknown, gp)


# ----------------------------------------------------------------------------------------------------- designs
def grid13() -> torch.Tensor:
    c = torch.linspace(-1, 1, 13, dtype=torch.float64)
    return torch.cartesian_prod(c, c)


def test_plot_design(tmp_path):
    cand = grid13()
    mask = np.zeros(169, dtype=bool)
    mask[[3, 50, 99]] = True
    path = tmp_path / "design.png"
    fig = plot_design(
        cand,
        {"design": torch.tensor([0, 12, 84, 156, 168]), "random": mask},
        proxies={"design": spirals(5, d=4)},
        masses=[(0.0, 0.0, 0.2), (0.5, 0.5, 0.4)],
        domain=((-1, 1), (-1, 1)),
        path=path,
    )
    assert_png(path)
    (ax,) = fig.axes
    assert len(ax.collections) == 1 + 2 + 1  # candidates, the two designs, the masses
    assert len(ax.lines) == 5 and len(ax.patches) == 1
    labels = legend_labels(ax)
    assert labels[0] == "candidates (N=169)"
    assert {"design (K=5)", "random (K=3)", "design trajectories", "point masses", "domain D"} <= set(labels)
    design = next(c for c in ax.collections if c.get_label() == "design (K=5)")
    np.testing.assert_allclose(design.get_offsets(), cand[[0, 12, 84, 156, 168]].numpy())
    sizes = next(c for c in ax.collections if c.get_label() == "point masses").get_sizes()
    assert sizes[1] > sizes[0]  # marker area grows with the mass
    legend = ax.get_legend()
    handle = legend.legend_handles[legend_labels(ax).index("point masses")]
    assert list(handle.get_sizes()) == [70.0]  # but not in the legend


def test_plot_design_grouped_masses_numpy_and_other_names():
    cand = np.random.default_rng(0).uniform(-3, 3, (300, 2))
    fig = plot_design(
        cand,
        {"agnostic": [1, 2, 3], "misspecified": np.array([4, 5]), "other": [6]},
        masses={"known (G)": [(0, 0, 0.2)], "unknown (F)": np.array([[0, 4, 0.1], [0.5, 3.8, 0.4]])},
    )
    (ax,) = fig.axes
    assert len(ax.collections) == 1 + 3 + 2
    assert {"known (G)", "unknown (F)"} <= set(legend_labels(ax))


def test_plot_design_rejects_bad_inputs():
    cand = grid13()
    with pytest.raises(ShapeError, match=r"candidates_xy: expected shape \(N, 2\), got \(169, 3\)"):
        plot_design(torch.zeros(169, 3), {"design": [0]})
    with pytest.raises(InputError, match=r"picks\['design'\]: expected indices in \[0, 168\].*from 0 to 169"):
        plot_design(cand, {"design": [0, 169]})
    with pytest.raises(InputError, match="integer indices"):
        plot_design(cand, {"design": [0.5, 1.0]})
    with pytest.raises(ShapeError, match=r"boolean mask of shape \(169,\)"):
        plot_design(cand, {"design": np.zeros(10, dtype=bool)})
    with pytest.raises(ShapeError, match=r"masses: expected rows \(x, y, m\), shape \(n, 3\), got \(2, 2\)"):
        plot_design(cand, {"design": [0]}, masses=[(0, 0), (1, 1)])
    with pytest.raises(ShapeError, match=r"proxies\['design'\]: expected shape \(K, T, d\)"):
        plot_design(cand, {"design": [0]}, proxies={"design": np.zeros((3, 2))})


# ------------------------------------------------------------------------------------------------ error curves
def test_plot_error_curves(tmp_path):
    ks = torch.arange(1, 6)
    path = tmp_path / "curves.png"
    fig = plot_error_curves(
        ks,
        {"random": (1 / ks, 0.1 / ks), "design": (np.full(5, 0.1), None), "data-driven": [0.9, 0.8, 0.7, 0.6, 0.5]},
        reference_lines={"energy of F": 2.0, "energy of G + F": 5.0},
        ylabel="MSE",
        path=path,
    )
    assert_png(path)
    (ax,) = fig.axes
    assert len(ax.containers) == 3  # one errorbar container per curve
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "MSE"
    assert "experiments" in ax.get_xlabel()
    labels = legend_labels(ax)
    assert set(labels) == {"random", "design", "data-driven", "energy of F", "energy of G + F"}
    dashed = [ln for ln in ax.lines if ln.get_linestyle() == "--"]
    assert sorted(ln.get_ydata()[0] for ln in dashed) == [2.0, 5.0]
    assert plot_error_curves([1, 2], {"a": [1.0, 2.0]}, logy=False).axes[0].get_yscale() == "linear"


def test_plot_error_curves_rejects_bad_inputs():
    with pytest.raises(ShapeError, match=r"curves\['a'\]: expected a mean of shape \(5,\) matching ks, got \(4,\)"):
        plot_error_curves(np.arange(5), {"a": np.ones(4)})
    with pytest.raises(ShapeError, match=r"curves\['a'\]: expected a stderr of shape \(5,\).*got \(2,\)"):
        plot_error_curves(np.arange(5), {"a": (np.ones(5), np.ones(2))})
    with pytest.raises(ShapeError, match=r"ks: expected shape \(n,\)"):
        plot_error_curves(np.ones((2, 2)), {"a": np.ones(2)})
    with pytest.raises(InputError, match=r"reference_lines\['F'\]: expected a number"):
        plot_error_curves(np.arange(2), {"a": np.ones(2)}, reference_lines={"F": "high"})
    with pytest.raises(InputError, match=r"expected \(mean, stderr\)"):
        plot_error_curves(np.arange(2), {"a": (np.ones(2), np.ones(2), np.ones(2))})


# ------------------------------------------------------------------------------------------ explicit styles
def test_plot_trajectories_series_and_styles():
    import matplotlib.colors as mcolors

    K = 3
    fig = plot_trajectories(
        spirals(K),
        spirals(K, shift=0.1),
        spirals(K, shift=0.02),
        series={"second model": spirals(K, shift=0.05), "third": spirals(K, shift=0.07)},
        styles={"corrected": {"label": "mine", "color": "tab:green"}, "second model": {"linestyle": "-."}},
    )
    (ax,) = fig.axes
    assert len(ax.lines) == 5 * K + 1
    assert legend_labels(ax) == [
        "true (G + F)",
        "misspecified (G)",
        "mine",
        "second model",
        "third",
        "initial conditions",
    ]
    true, mis, cor, second, third = (ax.lines[i * K : (i + 1) * K] for i in range(5))
    assert [ln.get_color() for ln in true] == ["tab:blue", "tab:orange", "tab:green"]  # trajectory k: colour k
    assert [ln.get_color() for ln in mis] == [ln.get_color() for ln in true]
    assert {ln.get_color() for ln in cor} == {"tab:green"}
    assert {ln.get_color() for ln in second} == {SERIES_STYLES[0]["color"]}  # default colour of series 0 ...
    assert {ln.get_linestyle() for ln in second} == {"-."}  # ... with the line style asked for
    assert {ln.get_color() for ln in third} == {SERIES_STYLES[1]["color"]}
    handle = ax.get_legend().legend_handles[2]
    assert mcolors.same_color(handle.get_color(), "tab:green")


@pytest.mark.parametrize("legend", [False, None])
def test_plot_trajectories_without_legend(legend):
    fig = plot_trajectories(spirals(2), legend=legend)
    assert fig.axes[0].get_legend() is None and not fig.legends


def test_legend_places():
    right = plot_trajectories(spirals(2), legend="right").axes[0].get_legend()
    assert right.get_bbox_to_anchor().x0 > right.axes.bbox.x1  # anchored outside, right of the axes
    fig = plot_training_and_test(spirals(4), spirals(4), spirals(2), spirals(2), spirals(2), legend="below")
    left, rightax = fig.axes
    assert left.get_legend() is None and rightax.get_legend() is None
    (below,) = fig.legends  # one legend for both panels, every style of the test panel
    assert [t.get_text() for t in below.get_texts()] == [
        "true (G + F)",
        "misspecified (G)",
        r"corrected (G + $\hat F$)",
        "initial conditions",
    ]


def test_styles_and_legend_reject_bad_input():
    with pytest.raises(InputError, match=r"styles: expected keys among \['true', 'misspecified', 'corrected'\]"):
        plot_trajectories(spirals(2), styles={"model": {"color": "red"}})
    with pytest.raises(InputError, match=r"styles\['true'\]: expected a dict of style keywords, got str"):
        plot_trajectories(spirals(2), styles={"true": "red"})
    with pytest.raises(InputError, match=r"series: expected names other than .*got \['true'\]"):
        plot_trajectories(spirals(2), series={"true": spirals(2)})
    with pytest.raises(ShapeError, match=r"series\['b'\]: expected shape \(2, T, 2\)"):
        plot_trajectories(spirals(2), series={"b": spirals(3)})
    with pytest.raises(InputError, match=r"legend: expected one of \[True, False, None, 'axes', 'right', 'below'\]"):
        plot_trajectories(spirals(2), legend="top")
    with pytest.raises(InputError, match="legend: expected True, 'axes', 'below' or False for two panels"):
        plot_training_and_test(spirals(2), spirals(2), spirals(2), spirals(2), spirals(2), legend="right")


def _marker_vertices(marker: str) -> np.ndarray:
    from matplotlib.markers import MarkerStyle

    style = MarkerStyle(marker)
    return style.get_path().transformed(style.get_transform()).vertices


def test_plot_design_styles_are_by_position_not_by_name():
    """A pick named "random" first gets the first default style: names carry no meaning."""
    import matplotlib.colors as mcolors

    fig = plot_design(grid13(), {"random": [0, 1], "design": [2, 3], "other": [4]}, legend=False)
    picks = {c.get_label(): c for c in fig.axes[0].collections}
    for i, label in enumerate(["random (K=2)", "design (K=2)", "other (K=1)"]):
        style = DESIGN_STYLES[i]
        assert mcolors.same_color(picks[label].get_edgecolor()[0], style["color"]), label
        assert picks[label].get_sizes()[0] == style["size"]
        np.testing.assert_allclose(picks[label].get_paths()[0].vertices, _marker_vertices(style["marker"]))
    assert fig.axes[0].get_legend() is None


def test_plot_design_explicit_styles_picks_and_trajectory_colours():
    import matplotlib.colors as mcolors
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    fig = plot_design(
        grid13(),
        picks={"a": [0, 5], "b": [7]},
        styles={"b": {"marker": "^", "color": "tab:olive", "size": 30.0, "linestyle": ":"}},
        proxies={"b": spirals(1), "seen from G": spirals(2)},
        ax=ax,
    )
    assert fig is ax.figure
    picks = {c.get_label(): c for c in ax.collections}
    assert mcolors.same_color(picks["b (K=1)"].get_edgecolor()[0], "tab:olive")
    assert picks["b (K=1)"].get_sizes()[0] == 30.0
    np.testing.assert_allclose(picks["b (K=1)"].get_paths()[0].vertices, _marker_vertices("^"))
    assert mcolors.same_color(picks["a (K=2)"].get_edgecolor()[0], DESIGN_STYLES[0]["color"])
    b_line, *others = ax.lines  # b's trajectory in b's colour and line style; the others grey
    assert mcolors.same_color(b_line.get_color(), "tab:olive") and b_line.get_linestyle() == ":"
    assert len(others) == 2 and {ln.get_color() for ln in others} == {"tab:gray"}
    assert "seen from G trajectories" in legend_labels(ax)


def test_plot_design_rejects_bad_styles():
    with pytest.raises(
        InputError, match=r"styles\['a'\]: expected keys among \['marker', 'color', 'size', 'linestyle'\]"
    ):
        plot_design(grid13(), {"a": [0]}, styles={"a": {"edgecolor": "red"}})
    with pytest.raises(InputError, match=r"styles: expected keys among \['a'\], got unknown 'b'"):
        plot_design(grid13(), {"a": [0]}, styles={"b": {"color": "red"}})
    fig = plot_design(grid13(), {"a": [0, 1, 2]})
    assert "a (K=3)" in legend_labels(fig.axes[0])
    with pytest.raises(InputError, match=r"picks: expected a dict design name -> indices, got NoneType"):
        plot_design(grid13())


def test_plot_error_curves_styles_defaults_and_axes():
    import matplotlib.colors as mcolors
    from matplotlib.figure import Figure

    from torchmisspec.plotting import CURVE_MARKERS

    ax = Figure().add_subplot()
    fig = plot_error_curves(
        [1, 2, 3],
        {"first": [3.0, 2.0, 1.0], "second": ([2.0, 1.0, 0.5], [0.1, 0.1, 0.1])},
        styles={"second": {"color": "tab:pink", "marker": "x", "linestyle": "--"}},
        ax=ax,
        legend="right",
        title="t",
    )
    assert fig is ax.figure and ax.get_title() == "t"
    first, second = (container.lines[0] for container in ax.containers)
    assert first.get_marker() == CURVE_MARKERS[0] and mcolors.same_color(first.get_color(), "C0")
    assert second.get_marker() == "x" and mcolors.same_color(second.get_color(), "tab:pink")
    assert second.get_linestyle() == "--"
    np.testing.assert_allclose(second.get_ydata(), [2.0, 1.0, 0.5])
    assert legend_labels(ax) == ["first", "second"]
    with pytest.raises(InputError, match=r"styles: expected keys among \['first'\], got unknown 'x'"):
        plot_error_curves([1], {"first": [1.0]}, styles={"x": {}})
