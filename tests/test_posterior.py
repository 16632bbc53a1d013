"""Trajectories under posterior draws of F and differentiable predictions (issue 10, points 2-4)."""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.systems import LinearField, MisspecifiedSystem

DT = torch.float64


@pytest.fixture(scope="module")
def linear():
    """paper 5.1's system, 12 experiments with oracle derivatives (noise std 1e-3: at 1e-2 ML-II picks a nearly
    constant kernel, lengthscale ~2000, for so few experiments), the fitted GP (lengthscale ~1.2)."""
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(0)
    y0 = torch.rand(12, 2, generator=g, dtype=DT) * 2 - 1
    traj = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=DT))
    samples = tms.correction_samples(traj, system, derivative="oracle", noise_std=1e-3, generator=g)
    return system, tms.CorrectionGP().fit(samples)


def test_container_shapes_and_summaries(linear, one_thread):
    system, gp = linear
    ode = tms.CorrectedODE(system, gp)
    y0 = torch.tensor([[0.3, -0.2], [-0.5, 0.4], [0.1, 0.1]], dtype=DT)
    times = torch.linspace(0, 3, 7, dtype=DT)
    post = ode.posterior(y0, times, num_samples=16, generator=torch.Generator().manual_seed(1))
    assert isinstance(post, tms.TrajectoryPosterior)
    assert post.samples.shape == (16, 3, 7, 2) and post.mean.shape == post.stddev.shape == (3, 7, 2)
    assert post.times.shape == (3, 7) and post.support.shape == (3, 7) and post.extrapolating.shape == (3,)
    assert torch.equal(post.samples[:, :, 0], y0.expand(16, -1, -1))  # every draw starts at its initial condition
    assert torch.allclose(post.mean_path, ode.predict(y0, times))
    assert torch.equal(post.quantile(0.5), torch.quantile(post.samples, 0.5, dim=0))
    assert post.quantile([0.05, 0.95]).shape == (2, 3, 7, 2)
    lo, hi = post.interval(0.9)
    assert bool((lo <= post.quantile(0.5)).all() and (post.quantile(0.5) <= hi).all())
    assert post.covers(post.quantile(0.5)).all() and not post.covers(hi + 1.0).any()
    assert float(post.stddev[:, 1:].min()) > 0 and float(post.stddev[:, 0].max()) == 0
    # the same generator seed gives the same draws; another seed, others
    again = ode.posterior(y0, times, num_samples=16, generator=torch.Generator().manual_seed(1))
    assert torch.equal(again.samples, post.samples)
    other = ode.posterior(y0, times, num_samples=16, generator=torch.Generator().manual_seed(2))
    assert not torch.equal(other.samples, post.samples)


def test_bad_arguments(linear):
    system, gp = linear
    ode = tms.CorrectedODE(system, gp)
    y0, times = torch.zeros(1, 2, dtype=DT), torch.linspace(0, 1, 3, dtype=DT)
    for bad in (0, 1.5, "2"):
        with pytest.raises(tms.InputError, match="num_samples"):
            ode.posterior(y0, times, num_samples=bad)
    with pytest.raises(tms.InputError, match=r"generator: expected a torch.Generator or None, got str"):
        ode.posterior(y0, times, generator="seed")
    with pytest.raises(tms.InputError, match=r"support_threshold: expected a ratio of standard deviations in \(0, 1\]"):
        ode.posterior(y0, times, support_threshold=2.0)
    post = ode.posterior(y0, times, num_samples=2)
    for q in (-0.1, 1.5, [[0.5]]):
        with pytest.raises(tms.InputError, match=r"q: expected a quantile or a 1-D list of quantiles in \[0, 1\]"):
            post.quantile(q)
    with pytest.raises(tms.InputError, match=r"level: expected a probability in \[0, 1\], got 1.5"):
        post.interval(1.5)
    with pytest.raises(tms.ShapeError, match=r"states: expected shape \(1, 3, 2\) \(B, T, d\), got \(3, 2\)"):
        post.covers(torch.zeros(3, 2, dtype=DT))


def test_sampled_path_of_a_linear_correction_is_the_closed_form(one_thread):
    """Polynomial kernel of degree 1: every draw is an affine F_s(y) = a_s + B_s y (exact features), so each path
    is the closed-form solution of dy/dt = (A + B_s) y + a_s."""
    A = torch.tensor([[0.0, 1.0], [-1.0, -0.1]], dtype=DT)
    system = MisspecifiedSystem(LinearField(A), 2, known_matrix=A, name="oscillator")
    X = torch.rand(20, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    Y = X @ torch.tensor([[0.0, 0.0], [-0.2, 0.1]], dtype=DT).T + 0.01
    gp = tms.CorrectionGP(kernel="polynomial", degree=1).fit(X, Y)
    y0 = torch.tensor([[1.0, 0.0], [0.0, -0.5]], dtype=DT)
    times = torch.linspace(0, 2, 5, dtype=DT)
    post = tms.CorrectedODE(system, gp).posterior(
        y0, times, num_samples=4, generator=torch.Generator().manual_seed(3), solver=tms.Solver(rtol=1e-10, atol=1e-12)
    )
    draws = gp.sample_functions(4, generator=torch.Generator().manual_seed(3))  # the same draws (same seed)
    probe = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=DT)
    values = draws(probe)  # (S, 3, 2)
    for s in range(4):
        a = values[s, 0]
        Bs = torch.stack([values[s, 1] - a, values[s, 2] - a], dim=-1)  # columns: F(e_j) - F(0)
        M = A + Bs
        for b in range(2):  # y(t) = e^{Mt} y0 + M^-1 (e^{Mt} - I) a
            for j, t in enumerate(times):
                E = torch.linalg.matrix_exp(M * t)
                exact = E @ y0[b] + torch.linalg.solve(M, (E - torch.eye(2, dtype=DT)) @ a)
                assert torch.allclose(post.samples[s, b, j], exact, rtol=0, atol=1e-8)


def test_extrapolation_is_flagged_and_warned_once(linear):
    system, gp = linear
    ode = tms.CorrectedODE(system, gp)
    inside = torch.tensor([[0.2, 0.1]], dtype=DT)
    far = torch.tensor([[6.0, -6.0], [5.0, 5.0]], dtype=DT)
    times = torch.linspace(0, 1, 5, dtype=DT)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)
        post = ode.posterior(inside, times, num_samples=4, scale=1.0)
    assert not post.extrapolating.any() and float(post.support.max()) < post.threshold
    with pytest.warns(tms.TorchMisspecWarning, match=r"2 of 3 predicted path\(s\) leave the data's support") as rec:
        post = ode.posterior(torch.cat([inside, far]), times, num_samples=4, scale=1.0)
    assert len([w for w in rec if issubclass(w.category, tms.TorchMisspecWarning)]) == 1
    assert post.extrapolating.tolist() == [False, True, True]
    assert float(post.support[1:].min()) > 0.99  # far from the data: the prior's standard deviation


def test_blowing_up_draws_are_named_and_left_out_of_the_band():
    """Quadratic draws (polynomial kernel, degree 2) with a large prior: some blow up in finite time, although the
    posterior mean (near 0: the data are 0) does not. The posterior does not fail as a whole: the diverging draws
    leave the region and are stopped there, are named in one warning, their paths are NaN from where they leave,
    and the band comes from the draws that remain (issue 41: it was infinite; tests/test_bands_bounded.py)."""
    system = MisspecifiedSystem(lambda y: torch.zeros_like(y), 1, name="zero")
    X = torch.linspace(-0.1, 0.1, 5, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(kernel="polynomial", degree=2, outputscale=25.0, noise_variance=1e-2)
    gp.fit(X, torch.zeros(5, 1, dtype=DT))
    ode = tms.CorrectedODE(system, gp)
    y0, times = torch.tensor([[1.0], [2.0]], dtype=DT), torch.linspace(0, 5, 6, dtype=DT)
    kw = dict(num_samples=8, generator=torch.Generator().manual_seed(0), solver=tms.Solver(max_steps=2000), scale=1.0)
    with pytest.warns(tms.TorchMisspecWarning, match=r"of 16 sampled paths left the region .* 0: \d of 8"):
        post = ode.posterior(y0, times, **kw)
    paths = post.samples[..., 0]  # (S, B, T)
    diverged = torch.isnan(paths).any(-1)
    assert bool(diverged.any()) and not bool(diverged.all())
    assert bool(torch.isfinite(paths[..., 0]).all())  # every path starts at its initial condition
    assert bool(torch.isfinite(paths[~diverged]).all())
    # NaN only after the last time each diverged path reached: a prefix of finite values, then NaN
    for path in paths[diverged]:
        finite = torch.isfinite(path)
        assert bool(finite[: int(finite.sum())].all())
    assert torch.allclose(post.fraction_remaining, 1.0 - diverged.double().mean(0))
    lower, upper = post.interval(0.5)  # 8 draws, at least 3 remain: finite
    assert bool(torch.isfinite(lower).all() & torch.isfinite(upper).all())


def test_predict_builds_no_graph_by_default(linear):
    system, gp = linear
    pred = tms.CorrectedODE(system, gp).predict(torch.zeros(2, 2, dtype=DT), torch.linspace(0, 1, 3, dtype=DT))
    assert not pred.requires_grad
    assert not any(p.requires_grad for p in gp.model.parameters())  # frozen outside fitting


def test_predict_gradient_in_the_initial_conditions(linear, one_thread):
    system, gp = linear
    ode = tms.CorrectedODE(system, gp)
    times = torch.linspace(0, 2, 5, dtype=DT)
    y0 = torch.tensor([[0.3, -0.4]], dtype=DT, requires_grad=True)
    ode.predict(y0, times, solver=tms.Solver(rtol=1e-10, atol=1e-12))[:, -1].sum().backward()
    h, fd = 1e-6, []
    for i in range(2):
        e = torch.zeros(1, 2, dtype=DT)
        e[0, i] = h
        plus = ode.predict(y0.detach() + e, times, solver=tms.Solver(rtol=1e-10, atol=1e-12))[:, -1].sum()
        minus = ode.predict(y0.detach() - e, times, solver=tms.Solver(rtol=1e-10, atol=1e-12))[:, -1].sum()
        fd.append(float(plus - minus) / (2 * h))
    assert torch.allclose(y0.grad[0], torch.tensor(fd, dtype=DT), rtol=1e-5, atol=1e-7)


def test_predict_gradient_in_a_hyperparameter(linear, one_thread):
    system, gp = linear
    raw = gp.covar_module.base_kernel.raw_lengthscale
    ode = tms.CorrectedODE(system, gp)
    y0, times = torch.tensor([[0.5, 0.5]], dtype=DT), torch.linspace(0, 4, 3, dtype=DT)

    def value():
        return ode.predict(y0, times, solver=tms.Solver(rtol=1e-10, atol=1e-12))[:, -1].sum()

    try:
        raw.requires_grad_(True)
        out = value()
        assert out.requires_grad
        (grad,) = torch.autograd.grad(out, raw)
    finally:
        raw.requires_grad_(False)
    h = 1e-5
    with torch.no_grad():
        raw += h
        plus = float(value())
        raw -= 2 * h
        minus = float(value())
        raw += h
    assert float(grad) == pytest.approx((plus - minus) / (2 * h), rel=1e-4, abs=1e-9)


def test_posterior_paths_are_differentiable_in_the_initial_conditions(linear):
    system, gp = linear
    ode = tms.CorrectedODE(system, gp)
    y0 = torch.tensor([[0.3, -0.4]], dtype=DT, requires_grad=True)
    post = ode.posterior(
        y0, torch.linspace(0, 1, 3, dtype=DT), num_samples=3, generator=torch.Generator().manual_seed(0)
    )
    post.samples[:, :, -1].sum().backward()
    assert y0.grad is not None and bool(torch.isfinite(y0.grad).all()) and float(y0.grad.abs().sum()) > 0


def test_band_and_calibration_figures(linear, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from torchmisspec.plotting import plot_calibration, plot_prediction_bands

    system, gp = linear
    y0 = torch.tensor([[0.3, -0.2], [-0.5, 0.4]], dtype=DT)
    times = torch.linspace(0, 3, 7, dtype=DT)
    post = tms.CorrectedODE(system, gp).posterior(y0, times, num_samples=8, generator=torch.Generator().manual_seed(0))
    true = tms.simulate(system, y0, times).states
    fig = plot_prediction_bands(
        post, index=1, true_states=true, misspecified_states=true * 0.9, path=tmp_path / "b.png"
    )
    assert len(fig.axes) == 2 and (tmp_path / "b.png").stat().st_size > 0
    lo, hi = post.interval(0.9)
    shaded = fig.axes[0].collections[0].get_paths()[0].vertices[:, 1]  # the 90 % band of component 0
    assert shaded.min() == pytest.approx(float(lo[1, :, 0].min()))
    assert shaded.max() == pytest.approx(float(hi[1, :, 0].max()))
    assert post.state_names == system.state_names is None  # the system names no states: y_1, y_2
    assert [ax.get_ylabel() for ax in fig.axes] == ["$y_{1}$", "$y_{2}$"]
    named = dataclasses.replace(post, state_names=("prey", "predator"))  # as CorrectedODE.posterior of a named system
    assert [ax.get_ylabel() for ax in plot_prediction_bands(named).axes] == ["prey", "predator"]
    with pytest.raises(tms.InputError, match=r"index: expected an initial condition in \[0, 1\], got 2"):
        plot_prediction_bands(post, index=2)
    with pytest.raises(tms.ShapeError, match=r"true_states: expected shape \(2, 7, 2\) as the posterior"):
        plot_prediction_bands(post, true_states=true[:1])
    with pytest.raises(tms.InputError, match=r"posterior: expected a TrajectoryPosterior, got Tensor"):
        plot_prediction_bands(true)
    fig = plot_calibration([0.5, 0.9], {"K = 10": ([0.45, 0.88], [0.01, 0.01]), "K = 40": [0.5, 0.91]})
    assert len(fig.axes[0].get_legend().get_texts()) == 3
    with pytest.raises(tms.InputError, match=r"nominal: expected \(n,\) probabilities in \(0, 1\)"):
        plot_calibration([0.5, 1.5], {"a": [0.5, 0.9]})


@pytest.mark.parametrize("kw", [{}, {"kernel": "matern52", "per_output": True}, {"known_noise": True}])
def test_the_support_ratio_matches_the_exact_posterior_variance(linear, kw):
    """The extrapolation check's truncated eigenbasis (or exact solve): within its certified 1e-3 of the variance
    ratio from predict(), never below it; the basis is kept with the cached factorization."""
    system, gp = linear
    X, Y = gp.train_inputs_, gp.train_targets_
    if kw.pop("known_noise", False):
        gp = tms.CorrectionGP().fit(X, Y, noise=torch.full_like(Y, 1e-6))
    elif kw:
        gp = tms.CorrectionGP(**kw).fit(X, Y)
    x = torch.rand(500, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 4 - 2
    post = gp.predict(x).variance
    prior = gp.covar_module.forward(x, x, diag=True)
    prior = prior.unsqueeze(-1) if prior.dim() == 1 else prior.T
    exact = (post / prior).clamp(0, 1)
    got = gp.posterior().sd_ratio(x).pow(2)
    assert float((got - exact.amax(-1)).min()) > -1e-9  # never understated
    assert float((got - exact.amax(-1)).max()) < 1.001e-3
    posterior = gp.posterior()
    assert posterior._basis is not None and gp.posterior() is posterior
