"""The RBF kernel in feature space for many samples (``kernel="rbf-features"``, torchmisspec.gp._large).

References: the kernel against the RBF formula within the certified bound; the feature-space posterior against a
hand-written Cholesky posterior with the same (approximate) kernel; the subsample's hyperparameters against an exact
fit on the same subsample; the design's conditioning against the dense formula.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.gp._features import DENSE_LIMIT

DT = torch.float64
SYSTEM = tms.systems.paper_linear()
FIXED = dict(lengthscale=0.8, outputscale=4e-5, noise_variance=1e-6)


def _samples(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    y = SYSTEM.true_correction(x) + 1e-3 * torch.randn(n, 2, generator=g, dtype=DT)
    return x, y


def _rbf(a, b, lengthscale, outputscale):
    return outputscale * np.exp(-((a[:, None, :] - b[None, :, :]) ** 2).sum(-1) / (2 * lengthscale**2))


def test_quadrature_features_stay_within_their_certified_bound_on_the_box():
    x, y = _samples(300)
    gp = tms.CorrectionGP(kernel=tms.gp.RBFFeatures(feature_error=1e-2), exact=False, **FIXED).fit(x, y)
    from torchmisspec.gp._paths import _quadrature_features

    quad = _quadrature_features(x, torch.full((1, 2), 0.8, dtype=DT), torch.ones(1, 1, dtype=DT), 1e-2)
    gp.covar_module.base_kernel.set_fourier(quad._t["omega"][0], quad._t["scale"][0], 0.8, quad.error_bound, quad.box)
    info = gp.covar_module.base_kernel.describe()
    assert info["kind"] == "quadrature" and info["error_bound"] <= 1e-2 and info["bound_holds_on"] == "box"
    lo, hi = torch.tensor(info["box"], dtype=DT)
    pts = lo + (hi - lo) * torch.rand(400, 2, generator=torch.Generator().manual_seed(1), dtype=DT)
    exact = _rbf(pts.numpy(), pts.numpy(), 0.8, 4e-5)
    assert np.abs(gp.covariance(pts).numpy() - exact).max() / 4e-5 <= info["error_bound"]


def test_nystrom_features_stay_within_their_certified_bound_on_the_data():
    x, y = _samples(300)
    gp = tms.CorrectionGP(kernel="rbf-features", **FIXED).fit(x, y)
    info = gp.approximation
    assert info["kind"] == "nystrom" and info["bound_holds_on"] == "training inputs"
    # the default tolerance: a tenth of the noise-to-signal ratio
    assert info["error_bound"] <= 0.1 * 1e-6 / 4e-5 * 1.01 and info["feature_error"] is None
    exact = _rbf(x.numpy(), x.numpy(), 0.8, 4e-5)
    assert np.abs(gp.covariance(x).numpy() - exact).max() / 4e-5 <= info["error_bound"]
    assert gp.lengthscale == pytest.approx(0.8) and gp.kernel == "rbf-features"


def test_four_inputs_use_nystrom_and_two_smooth_ones_quadrature():
    from torchmisspec.benchmarks import large_fit

    s4, s2 = large_fit.quartic4(), tms.systems.paper_linear()
    four = tms.CorrectionGP(exact=False).fit(*large_fit.samples(s4, 600))
    two = tms.CorrectionGP(exact=False).fit(*large_fit.samples(s2, 600))
    assert four.approximation["kind"] == "nystrom" and two.approximation["kind"] == "quadrature"


def test_feature_space_posterior_is_the_cholesky_posterior_of_the_same_kernel():
    """Mean, variance and the design's conditioned kernel equal a hand-written dense computation with
    K_hat = s^2 Phi Phi^T (numpy Cholesky), the approximate kernel's exact posterior."""
    x, y = _samples(200)
    gp = tms.CorrectionGP(kernel="rbf-features", **FIXED).fit(x, y)
    t = torch.rand(50, 2, generator=torch.Generator().manual_seed(2), dtype=DT) * 2 - 1
    phi = gp.covar_module.base_kernel.features
    P, Pt = phi(x).numpy(), phi(t).numpy()
    K = 4e-5 * P @ P.T + 1e-6 * np.eye(200)
    L = np.linalg.cholesky(K)
    kx = 4e-5 * Pt @ P.T
    mean = kx @ np.linalg.solve(L.T, np.linalg.solve(L, y.numpy()))
    V = np.linalg.solve(L, kx.T)
    cov = 4e-5 * Pt @ Pt.T - V.T @ V
    post = gp.predict(t)
    scale = np.abs(mean).max()
    assert np.abs(post.mean.numpy() - mean).max() <= 1e-8 * scale
    assert np.abs(post.variance[:, 0].numpy() - np.diag(cov)).max() <= 1e-9 * 4e-5
    kern = design._common.GPKernel(gp, condition=True)
    assert np.abs(kern(t).numpy() - cov).max() <= 1e-9 * 4e-5
    assert kern.num_conditioned == 200 and kern.chol is None  # no N x N factor was built


def test_hyperparameters_are_an_exact_fit_on_the_subsample():
    x, y = _samples(900)
    gp = tms.CorrectionGP(kernel=tms.gp.RBFFeatures(subsample=300)).fit(x, y)
    sub = torch.linspace(0, 899, 300).round().long()
    exact = tms.CorrectionGP().fit(x[sub], y[sub])
    assert gp.lengthscale == pytest.approx(exact.lengthscale, rel=1e-10)
    assert gp.outputscale == pytest.approx(exact.outputscale, rel=1e-10)
    assert gp.noise_variance == pytest.approx(exact.noise_variance, rel=1e-10)
    assert gp.approximation["subsample"] == 300


def test_save_and_load_predict_exactly(tmp_path):
    x, y = _samples(400)
    gp = tms.CorrectionGP(kernel="rbf-features").fit(x, y)
    again = tms.CorrectionGP.load(gp.save(tmp_path / "large.pt"))
    t = torch.rand(30, 2, generator=torch.Generator().manual_seed(3), dtype=DT) * 2 - 1
    # the stored features are exact; the recomputed feature-space solve may differ by round-off (thread counts
    # change BLAS orders), the tolerance of every model file (tests/test_persistence.py)
    base, loaded = gp.covar_module.base_kernel, again.covar_module.base_kernel
    assert torch.equal(loaded.omega, base.omega) and torch.equal(loaded.mass, base.mass)
    torch.testing.assert_close(again.predict_mean(t), gp.predict_mean(t), rtol=1e-9, atol=1e-13)
    torch.testing.assert_close(again.predict(t).variance, gp.predict(t).variance, rtol=1e-9, atol=1e-15)
    assert again.approximation == gp.approximation


@pytest.mark.slow
def test_many_samples_through_prediction_bands_and_design():
    """25,000 samples: fit, predict, bands and a conditioned design run without an N x N matrix; the paths that need
    the dense factor refuse with a message."""
    x, y = _samples(25_000)
    gp = tms.CorrectionGP(kernel="rbf-features").fit(x, y)
    model = tms.CorrectedODE(SYSTEM, gp)
    y0 = torch.tensor([[0.5, -0.3], [0.2, 0.7]], dtype=DT)
    times = torch.linspace(0, 6, 11, dtype=DT)
    truth = tms.simulate(SYSTEM, y0, times).states
    pred = model.predict(y0, times)
    assert tms.trajectory_rmse(pred, truth) < 0.01
    bands = model.posterior(y0, times, num_samples=8, scale=1.0, generator=torch.Generator().manual_seed(0))
    assert bool(torch.isfinite(bands.samples).all())
    cand = design.candidates.grid(SYSTEM.domain, 10)
    plan = design.greedy(cand, 3, system=SYSTEM, times=times, gp=gp)
    assert plan.diagnostics["conditioned"] == 25_000
    assert 25_000 > DENSE_LIMIT
    with pytest.raises(tms.InputError, match=f"expected at most {DENSE_LIMIT} samples for it, got 25000"):
        gp.posterior().with_targets(y)


def test_posterior_draws_are_drawn_in_feature_space():
    """Draws of a feature-space posterior are phi(x)^T w_s (no update over the N training inputs): their mean and
    variance at test points match the posterior's within 4 standard errors of 4,000 draws."""
    x, y = _samples(500)
    gp = tms.CorrectionGP(kernel="rbf-features").fit(x, y)
    draws = gp.sample_functions(4000, generator=torch.Generator().manual_seed(1))
    assert draws._X.shape[0] == 0
    t = torch.rand(6, 2, generator=torch.Generator().manual_seed(4), dtype=DT) * 2 - 1
    f, post = draws(t), gp.predict(t)
    se = post.stddev / 4000**0.5
    assert bool(((f.mean(0) - post.mean).abs() <= 4 * se).all())
    assert bool(((f.var(0) / post.variance - 1).abs() <= 4 * (2 / 3999) ** 0.5).all())


def test_an_rbf_gp_moves_to_the_feature_space_above_large_n_and_back():
    from torchmisspec.gp._large import LARGE_N

    x, y = _samples(LARGE_N + 50)
    gp = tms.CorrectionGP().fit(x, y)
    assert gp.kernel == "rbf-features" and gp.approximation["kind"] in ("quadrature", "nystrom")
    assert gp.clone().requested_kernel.name == "rbf" and gp.clone().exact is None
    small = gp.clone().fit(x[:300], y[:300])
    assert small.kernel == "rbf" and small.approximation is None
    gp.fit(x[:300], y[:300])  # the same model refitted on few samples: exact again
    assert gp.kernel == "rbf"
    assert tms.CorrectionGP(exact=False).fit(x[:300], y[:300]).kernel == "rbf-features"
    with pytest.raises(tms.InputError, match="exact: expected None or True for this kernel"):
        tms.CorrectionGP(kernel="polynomial", exact=False)
    with pytest.raises(tms.InputError, match="exact: expected True, False or None"):
        tms.CorrectionGP(exact="yes")


@pytest.mark.slow
def test_exact_true_keeps_the_exact_gp_above_large_n(tmp_path):
    from torchmisspec.gp._large import LARGE_N

    x, y = _samples(LARGE_N + 50)
    gp = tms.CorrectionGP(exact=True, lengthscale=0.8, outputscale=4e-5, noise_variance=1e-6).fit(x, y)
    assert gp.kernel == "rbf" and gp.approximation is None
    large = tms.CorrectionGP(lengthscale=0.8, outputscale=4e-5, noise_variance=1e-6).fit(x, y)
    again = tms.CorrectionGP.load(large.save(tmp_path / "m.pt"))
    assert again.kernel == "rbf-features" and again.requested_kernel.name == "rbf"
    t = torch.rand(20, 2, generator=torch.Generator().manual_seed(5), dtype=DT) * 2 - 1
    scale = float(gp.predict_mean(t).abs().max())
    assert float((large.predict_mean(t) - gp.predict_mean(t)).abs().max()) <= 0.02 * scale


def test_conditioning_rebuilds_the_features_for_the_new_inputs():
    """``condition`` keeps the hyperparameters and builds the features for the new inputs: the kernel is within the
    certified bound at them (the old features were certified near the old inputs only), and the posterior is the one
    a fit with those values gives."""
    x, y = _samples(300)
    gp = tms.CorrectionGP(kernel="rbf-features", **FIXED).fit(0.1 * x, y)  # inputs in [-0.1, 0.1]^2
    wide = gp.condition(2 * x, y)  # inputs in [-2, 2]^2
    info = wide.approximation
    assert info != gp.approximation
    exact = _rbf(2 * x.numpy(), 2 * x.numpy(), 0.8, 4e-5)
    assert np.abs(wide.covariance(2 * x).numpy() - exact).max() / 4e-5 <= info["error_bound"]
    old = np.abs(gp.covariance(2 * x).numpy() - exact).max() / 4e-5
    assert old > gp.approximation["error_bound"], "the test needs inputs where the old features are off"
    refit = tms.CorrectionGP(kernel="rbf-features", **FIXED).fit(2 * x, y)
    t = torch.rand(20, 2, generator=torch.Generator().manual_seed(4), dtype=DT) * 4 - 2
    torch.testing.assert_close(wide.predict_mean(t), refit.predict_mean(t), rtol=1e-9, atol=1e-12)


def _matern52(a, b, lengthscale, outputscale):
    r = np.sqrt(5.0 * ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)) / lengthscale
    return outputscale * (1 + r + r**2 / 3) * np.exp(-r)


def test_matern_features_stay_within_their_certified_bound_and_match_the_exact_gp(tmp_path):
    """The Matern 5/2 kernel in feature space (Nystrom pivots): the kernel within the bound at the training inputs
    (against the closed form), the error of F within 5 % of the exact GP's on the same samples, above LARGE_N by
    default, and saved and loaded with its features."""
    from torchmisspec.gp._large import LARGE_N

    x, y = _samples(600)
    gp = tms.CorrectionGP(kernel="matern52", exact=False, lengthscale=0.8, outputscale=4e-5, noise_variance=1e-6)
    gp.fit(x, y)
    info = gp.approximation
    assert (
        gp.kernel == "matern52-features" and info["kind"] == "nystrom" and info["bound_holds_on"] == "training inputs"
    )
    exact = _matern52(x.numpy(), x.numpy(), 0.8, 4e-5)
    assert np.abs(gp.covariance(x).numpy() - exact).max() / 4e-5 <= info["error_bound"] <= 0.1 * 1e-6 / 4e-5 * 1.01
    fitted = tms.CorrectionGP(kernel="matern52", exact=False).fit(x, y)
    reference = tms.CorrectionGP(kernel="matern52").fit(x, y)
    assert reference.kernel == "matern52" and reference.approximation is None
    assert tms.correction_error(fitted, SYSTEM) <= 1.05 * tms.correction_error(reference, SYSTEM)
    again = tms.CorrectionGP.load(fitted.save(tmp_path / "matern.pt"))
    t = torch.rand(30, 2, generator=torch.Generator().manual_seed(3), dtype=DT) * 2 - 1
    torch.testing.assert_close(again.predict_mean(t), fitted.predict_mean(t), rtol=1e-9, atol=1e-13)
    assert again.approximation == fitted.approximation
    big_x, big_y = _samples(LARGE_N + 50)
    given = dict(lengthscale=0.8, outputscale=4e-5, noise_variance=1e-6)
    assert tms.CorrectionGP(kernel="matern52", **given).fit(big_x, big_y).kernel == "matern52-features"
    with pytest.raises(tms.InputError, match="exact: expected None or False with kernel 'matern52-features'"):
        tms.CorrectionGP(kernel="matern52-features", exact=True)
