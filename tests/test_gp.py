import math
import warnings

import numpy as np
import pytest
import torch

import torchmisspec as tms

DT = torch.float64
HYPER = {"lengthscale": 0.7, "outputscale": 2e-3, "noise_variance": 1e-4}


def _data(generator, n=60, d_in=2, d_out=2):
    X = torch.rand(n, d_in, generator=generator, dtype=torch.float64) * 2 - 1
    F = torch.stack([torch.sin(2 * X[:, 0]) * X[:, -1], X.pow(2).sum(-1)], -1)[:, :d_out] * 0.05
    return X, F + 0.01 * torch.randn(n, d_out, generator=generator, dtype=torch.float64)


def _kernel(kind, X1, X2, l, s, degree=2):
    """Independent kernel formulas (not the package's GPyTorch kernels)."""
    if kind == "polynomial":
        return s * (1.0 + X1 @ X2.T) ** degree
    r = torch.cdist(X1, X2) / l
    if kind == "rbf":
        return s * torch.exp(-0.5 * r**2)
    return s * (1 + math.sqrt(5) * r + 5.0 / 3.0 * r**2) * torch.exp(-math.sqrt(5) * r)


def _cholesky_posterior(K, Ks, kss_diag, Y, noise):
    L = torch.linalg.cholesky(K + noise * torch.eye(K.shape[0], dtype=K.dtype))
    alpha = torch.cholesky_solve(Y, L)
    V = torch.linalg.solve_triangular(L, Ks.T, upper=False)
    mean = Ks @ alpha
    var = kss_diag - V.pow(2).sum(0)
    n, d = Y.shape
    lml = -0.5 * (Y * alpha).sum() - d * torch.log(L.diagonal()).sum() - 0.5 * n * d * math.log(2 * math.pi)
    return mean, var, lml


@pytest.mark.parametrize("kind", ["rbf", "matern52", "polynomial"])
def test_posterior_equals_hand_written_cholesky(kind, generator):
    X, Y = _data(generator)
    Xs = torch.rand(25, 2, generator=generator, dtype=torch.float64) * 3 - 1.5
    hyper = dict(HYPER) if kind != "polynomial" else {"outputscale": 2e-3, "noise_variance": 1e-4}
    gp = tms.CorrectionGP(kernel=kind, **hyper).fit(X, Y)
    l, s, noise = HYPER["lengthscale"], HYPER["outputscale"], HYPER["noise_variance"]
    mean, var, lml = _cholesky_posterior(
        _kernel(kind, X, X, l, s), _kernel(kind, Xs, X, l, s), _kernel(kind, Xs, Xs, l, s).diagonal(), Y, noise
    )
    post = gp.predict(Xs)
    torch.testing.assert_close(post.mean, mean, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(post.variance, var.unsqueeze(-1).expand(-1, 2), rtol=1e-8, atol=1e-14)
    torch.testing.assert_close(gp.predict_mean(Xs), mean, rtol=1e-10, atol=1e-14)
    assert gp.log_marginal_likelihood_ == pytest.approx(float(lml), rel=1e-9)
    # fixed hyperparameters are reported as given
    assert gp.outputscale == pytest.approx(s) and gp.noise_variance == pytest.approx(noise)


def test_posterior_agrees_with_sklearn(generator):
    sk_gp = pytest.importorskip("sklearn.gaussian_process")
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    X, Y = _data(generator, n=80)
    Xs = torch.rand(30, 2, generator=generator, dtype=torch.float64) * 2 - 1
    gp = tms.CorrectionGP(**HYPER).fit(X, Y)
    kernel = ConstantKernel(HYPER["outputscale"]) * RBF(HYPER["lengthscale"])
    sk = sk_gp.GaussianProcessRegressor(kernel, alpha=HYPER["noise_variance"], optimizer=None).fit(X.numpy(), Y.numpy())
    mean, std = sk.predict(Xs.numpy(), return_std=True)
    post = gp.predict(Xs)
    np.testing.assert_allclose(post.mean.numpy(), mean, rtol=1e-8, atol=1e-13)
    np.testing.assert_allclose(post.stddev.numpy(), std, rtol=1e-6, atol=1e-12)
    # scikit-learn's multi-output likelihood sums the outputs' likelihoods under the shared kernel, as ours does
    assert gp.log_marginal_likelihood_ == pytest.approx(sk.log_marginal_likelihood_value_, rel=1e-10)


def test_fit_reaches_at_least_sklearn_marginal_likelihood(generator):
    sk_gp = pytest.importorskip("sklearn.gaussian_process")
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    X, Y = _data(generator, n=150)
    gp = tms.CorrectionGP().fit(X, Y)
    kernel = ConstantKernel(1.0, (1e-8, 1e3)) * RBF(1.0, (1e-3, 1e3)) + WhiteKernel(1.0, (1e-10, 1e1))
    sk = sk_gp.GaussianProcessRegressor(kernel, alpha=0.0, n_restarts_optimizer=3, random_state=0).fit(
        X.numpy(), Y.numpy()
    )
    assert gp.log_marginal_likelihood_ >= sk.log_marginal_likelihood_value_ - 1e-3 * abs(
        sk.log_marginal_likelihood_value_
    )
    # our reported value is the exact likelihood at our hyperparameters, as scikit-learn evaluates it
    theta = np.log([gp.outputscale, gp.lengthscale, gp.noise_variance])
    assert sk.log_marginal_likelihood(theta) == pytest.approx(gp.log_marginal_likelihood_, rel=1e-9)


@pytest.mark.parametrize("fixed", [{}, {"noise_variance": 1e-4}, {"lengthscale": 0.5}, {"outputscale": 1e-3}])
def test_fit_raises_marginal_likelihood_and_keeps_fixed_values(fixed, generator):
    X, Y = _data(generator)
    gp = tms.CorrectionGP(**fixed).fit(X, Y)
    # a sensible non-optimal point (median distance, target variance, 1 % noise), computed here independently
    var = float(Y.var(0, unbiased=False).mean())
    start = {"lengthscale": float(torch.pdist(X).median()), "outputscale": var, "noise_variance": 1e-2 * var}
    init = tms.CorrectionGP(**{**start, **fixed}).fit(X, Y)
    assert gp.log_marginal_likelihood_ > init.log_marginal_likelihood_ + 1.0
    for name, value in fixed.items():
        assert getattr(gp, name) == pytest.approx(value, rel=1e-12)
    # a stationary point: no small step on any learned hyperparameter increases the likelihood
    for name in {"lengthscale", "outputscale", "noise_variance"} - set(fixed):
        for factor in (0.97, 1.03):
            other = {k: getattr(gp, k) for k in ("lengthscale", "outputscale", "noise_variance")}
            other[name] *= factor
            assert tms.CorrectionGP(**other).fit(X, Y).log_marginal_likelihood_ <= gp.log_marginal_likelihood_ + 1e-6


def test_per_output_hyperparameters_equal_separate_fits(generator):
    X, Y = _data(generator, n=70)
    Y = Y * torch.tensor([1.0, 5.0], dtype=torch.float64)
    gp = tms.CorrectionGP(per_output=True).fit(X, Y)
    singles = [tms.CorrectionGP().fit(X, Y[:, i : i + 1]) for i in range(2)]
    assert gp.log_marginal_likelihood_ == pytest.approx(sum(s.log_marginal_likelihood_ for s in singles), rel=1e-5)
    Xs = torch.rand(10, 2, generator=generator, dtype=torch.float64)
    for i, single in enumerate(singles):
        torch.testing.assert_close(gp.predict(Xs).mean[:, i], single.predict(Xs).mean[:, 0], rtol=1e-3, atol=1e-7)
        assert float(gp.outputscale[i]) == pytest.approx(single.outputscale, rel=1e-2)


def test_gpytorch_model_view_matches_cached_posterior(generator):
    X, Y = _data(generator)
    gp = tms.CorrectionGP().fit(X, Y)
    Xs = torch.rand(7, 2, generator=generator, dtype=torch.float64)
    with torch.no_grad():
        dist = gp.model(Xs)
    post = gp.predict(Xs)
    torch.testing.assert_close(dist.mean.T, post.mean, rtol=1e-9, atol=1e-14)
    torch.testing.assert_close(dist.variance.T, post.variance, rtol=1e-7, atol=1e-14)


def test_save_and_load_roundtrip(tmp_path, generator):
    X, Y = _data(generator)
    for gp in (tms.CorrectionGP().fit(X, Y), tms.CorrectionGP(per_output=True, kernel="matern52").fit(X, Y)):
        loaded = tms.CorrectionGP.load(gp.save(tmp_path / "gp.pt"))
        Xs = torch.rand(9, 2, generator=generator, dtype=torch.float64)
        torch.testing.assert_close(loaded.predict(Xs).mean, gp.predict(Xs).mean, rtol=1e-12, atol=0)
        assert loaded.log_marginal_likelihood_ == pytest.approx(gp.log_marginal_likelihood_, rel=1e-12)


def test_one_dimensional_targets_and_float32_inputs(generator, one_thread):
    X, Y = _data(generator)
    gp = tms.CorrectionGP(**HYPER).fit(X.float(), Y[:, 0].float())
    assert gp.train_inputs_.dtype == torch.float64 and gp.output_dim == 1
    assert gp.predict_mean(X[:3]).shape == (3, 1)
    # float32 data are fitted in float64: the same fit as the same numbers given in float64
    learned32 = tms.CorrectionGP().fit(X.float(), Y.float())
    learned64 = tms.CorrectionGP().fit(X.float().double(), Y.float().double())
    for name in ("lengthscale", "outputscale", "noise_variance", "log_marginal_likelihood_"):
        assert getattr(learned32, name) == pytest.approx(getattr(learned64, name), rel=1e-12)
    torch.testing.assert_close(learned32.predict_mean(X.float()), learned64.predict_mean(X), rtol=0, atol=1e-7)


def test_unfitted_model_reports_only_given_values():
    gp = tms.CorrectionGP(lengthscale=0.5)
    assert (gp.lengthscale, gp.outputscale, gp.noise_variance) == (0.5, None, None)


def test_prior_covariance_before_fit():
    gp = tms.CorrectionGP(**HYPER)
    x = torch.tensor([[0.0, 0.0], [0.7, 0.0]], dtype=torch.float64)
    K = gp.covariance(x)
    assert K[0, 0].item() == pytest.approx(2e-3)
    assert K[0, 1].item() == pytest.approx(2e-3 * math.exp(-0.5))


# ------------------------------------------------------------------------------------------------------ bad input
def test_rejects_bad_configuration():
    with pytest.raises(tms.InputError, match=r"kernel: expected a Kernel object or one of .*got 'cubic'"):
        tms.CorrectionGP(kernel="cubic")
    with pytest.raises(tms.InputError, match="lengthscale: expected a positive finite number, got -1"):
        tms.CorrectionGP(lengthscale=-1.0)
    with pytest.raises(tms.InputError, match="polynomial kernel .* has no lengthscale"):
        tms.CorrectionGP(kernel="polynomial", lengthscale=1.0)


def test_rejects_bad_data(generator):
    X, Y = _data(generator)
    gp = tms.CorrectionGP()
    with pytest.raises(tms.ShapeError, match=r"targets: expected 60 rows to match inputs \(60, 2\), got \(59, 2\)"):
        gp.fit(X, Y[:-1])
    Xn = X.clone()
    Xn[3, 1] = float("nan")
    with pytest.raises(
        tms.InputError,
        match=r"inputs: expected finite values, got 1 NaN/inf entry \(first at index "
        r"\(3, 1\)",
    ):
        gp.fit(Xn, Y)
    with pytest.raises(ValueError):  # fitting errors are ValueErrors
        gp.fit(X, Y.unsqueeze(0))
    with pytest.raises(tms.NotFittedError, match="not fitted yet"):
        gp.predict(X)
    gp.fit(X, Y)
    with pytest.raises(tms.ShapeError, match=r"x: expected 2 input columns \(as in training\), got shape \(4, 3\)"):
        gp.predict(torch.zeros(4, 3))


def test_duplicate_inputs_with_tiny_noise_warn_and_stay_close(generator):
    """100 copies of 5 inputs, noise 1e-12: the posterior mean at an input is (almost exactly) the average of its
    copies. The Cholesky succeeds but the solve is inaccurate: a warning says by how much."""
    X = torch.rand(5, 2, generator=generator, dtype=torch.float64).repeat(100, 1)
    Y = torch.sin(X.sum(-1, keepdim=True)).repeat(1, 2) + 0.01 * torch.randn(500, 2, generator=generator, dtype=DT)
    with pytest.warns(tms.NumericalWarning, match=r"posterior solve is inaccurate: the posterior mean at the training"):
        gp = tms.CorrectionGP(lengthscale=0.5, outputscale=1.0, noise_variance=1e-12).fit(X, Y)
    average = Y.reshape(100, 5, 2).mean(0)
    err = float((gp.predict_mean(X[:5]) - average).abs().max() / average.abs().max())
    assert err < 1e-2
    # with a sensible noise there is no warning and the mean is the shrunk average, to round-off
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.NumericalWarning)
        tms.CorrectionGP(lengthscale=0.5, outputscale=1.0, noise_variance=1e-4).fit(X, Y)


@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1e6])
def test_fit_is_equivariant_to_the_units_of_targets_and_inputs(scale, generator):
    """Fitting c * Y predicts c * (the fit of Y); fitting c * X at c * x predicts the same (no absolute floors)."""
    X, Y = _data(generator)
    Xs = torch.rand(10, 2, generator=generator, dtype=DT)
    base = tms.CorrectionGP().fit(X, Y)
    ref = base.predict_mean(Xs).detach()
    scaled_y = tms.CorrectionGP().fit(X, scale * Y)
    torch.testing.assert_close(scaled_y.predict_mean(Xs).detach() / scale, ref, rtol=1e-9, atol=1e-12)
    assert scaled_y.outputscale == pytest.approx(scale**2 * base.outputscale, rel=1e-8)
    scaled_x = tms.CorrectionGP().fit(scale * X, Y)
    torch.testing.assert_close(scaled_x.predict_mean(scale * Xs).detach(), ref, rtol=1e-9, atol=1e-12)
    assert scaled_x.lengthscale == pytest.approx(scale * base.lengthscale, rel=1e-8)


def test_iteration_counts(generator):
    X, Y = _data(generator)
    gp = tms.CorrectionGP().fit(X, Y)
    assert 1 <= gp.n_iterations_ <= gp.n_evaluations_  # line searches evaluate more often than they iterate
    assert not hasattr(gp, "n_iter_")  # the old name, removed: it counted evaluations, not iterations
    assert tms.CorrectionGP(**HYPER).fit(X, Y).n_evaluations_ == 0  # nothing to learn


def test_warm_start_reaches_the_same_optimum(generator):
    X, Y = _data(generator, n=700)
    cold = tms.CorrectionGP().fit(X, Y, warm_start=0)
    warm = tms.CorrectionGP().fit(X, Y, warm_start=100)
    assert warm.log_marginal_likelihood_ == pytest.approx(cold.log_marginal_likelihood_, rel=1e-7)
    assert warm.lengthscale == pytest.approx(cold.lengthscale, rel=1e-2)


def test_tiny_and_degenerate_data():
    X = torch.tensor([[0.1, 0.2]], dtype=torch.float64)
    gp = tms.CorrectionGP().fit(X, torch.tensor([[0.01, -0.02]], dtype=torch.float64))  # one sample
    assert torch.isfinite(gp.predict(X).mean).all()
    zeros = torch.zeros(10, 2, dtype=torch.float64)
    with pytest.raises(tms.FittingError, match="got all zeros"):
        tms.CorrectionGP().fit(torch.rand(10, 2, dtype=torch.float64), zeros)
    fixed = tms.CorrectionGP(outputscale=1e-3, noise_variance=1e-4).fit(torch.rand(10, 2, dtype=torch.float64), zeros)
    assert fixed.predict(X).mean.abs().max() == 0


def test_a_failed_fit_leaves_the_model_as_it_was(generator, monkeypatch):
    X, Y = _data(generator)
    gp = tms.CorrectionGP().fit(X, Y)
    Xs = torch.rand(5, 2, generator=generator, dtype=DT)
    before = gp.predict_mean(Xs).clone()
    hyper = (gp.lengthscale, gp.outputscale, gp.noise_variance)

    def broken(*args, **kwargs):
        raise tms.FittingError("optimiser broke down")

    from torchmisspec.gp import _fit

    monkeypatch.setattr(_fit, "optimise", broken)
    with pytest.raises(tms.FittingError, match="optimiser broke down"):
        gp.fit(X[:20] * 3, Y[:20])
    assert (gp.lengthscale, gp.outputscale, gp.noise_variance) == hyper
    assert gp.train_inputs_.shape == X.shape
    torch.testing.assert_close(gp.predict_mean(Xs), before, rtol=0, atol=0)
    unfitted = tms.CorrectionGP()
    with pytest.raises(tms.FittingError):
        unfitted.fit(X, Y)
    assert not unfitted.is_fitted


def test_starting_values_are_the_documented_statistics_and_the_fit_starts_there(generator):
    X, Y = _data(generator)
    start = tms.CorrectionGP().starting_values(X, Y)
    i, j = torch.triu_indices(len(X), len(X), 1)
    d = (X[i] - X[j]).norm(dim=-1)  # each pair of distinct inputs once (cdist's matrix form: self-distances ~1e-8)
    assert float(start["lengthscale"]) == pytest.approx(float(d[d > 0].median()), rel=1e-12)  # N < 500: all inputs
    assert float(start["outputscale"]) == pytest.approx(float(Y.pow(2).mean()), rel=1e-12)
    assert float(start["noise_variance"]) == pytest.approx(0.01 * float(Y.pow(2).mean()), rel=1e-12)
    one_step = tms.CorrectionGP(max_iter=1).fit(X, Y, warm_start=0)
    fixed_at_start = tms.CorrectionGP(**{k: float(v) for k, v in start.items()}).fit(X, Y)
    assert one_step.log_marginal_likelihood_ > fixed_at_start.log_marginal_likelihood_  # one step uphill from there


@pytest.mark.parametrize("kind", ["rbf", "matern52", "features+rbf"])
def test_a_prediction_does_not_depend_on_the_rest_of_the_batch(kind, generator):
    """GPyTorch centres both inputs of a distance on the first one's mean: with the query batch first, one far-away
    row (a diverging trajectory's state) changed every other row's prediction. Each row must be its own."""
    X, Y = _data(generator)
    gp = tms.CorrectionGP(kernel=kind).fit(X, Y)
    x = torch.tensor([[0.375, -0.2], [0.1, 0.4]], dtype=DT)
    far = torch.cat([x, torch.tensor([[1e6, 0.0], [0.0, -1e8]], dtype=DT)])
    alone, batched = gp.predict(x), gp.predict(far)
    torch.testing.assert_close(batched.mean[:2], alone.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(batched.variance[:2], alone.variance, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(gp.predict_mean(far)[:2], gp.predict_mean(x), rtol=1e-12, atol=1e-12)
    if kind != "features+rbf":  # far from the data a stationary posterior is the prior: mean 0
        assert float(batched.mean[2:].abs().max()) < 1e-12


@pytest.mark.parametrize("failing", [1, 4])
def test_a_trial_that_cannot_be_factorized_stops_the_fit_at_the_last_that_could(failing, generator, monkeypatch):
    """A line-search trial whose K + noise overflows (a derivative-sample fit of issue 43's population study): the
    fit keeps the last hyperparameters it could factorize, as after a failed line search, instead of raising; only a
    start that cannot be factorized is an error."""
    from torchmisspec._errors import LinearAlgebraError
    from torchmisspec.gp import _mll

    X, Y = _data(generator)
    calls = [0]
    real = _mll.factorize

    def factorize(*args, **kwargs):
        calls[0] += 1
        if calls[0] == failing:
            raise LinearAlgebraError("K + noise_variance * I: expected a finite matrix to factorize")
        return real(*args, **kwargs)

    monkeypatch.setattr(_mll, "factorize", factorize)
    if failing == 1:
        with pytest.raises(tms.FittingError, match="fitting failed"):
            tms.CorrectionGP().fit(X, Y)
        return
    gp = tms.CorrectionGP().fit(X, Y)
    assert gp.n_iterations_ == -1 and gp.n_evaluations_ == failing - 1
    assert all(math.isfinite(getattr(gp, k)) for k in ("lengthscale", "outputscale", "noise_variance"))
    assert math.isfinite(gp.log_marginal_likelihood_)
