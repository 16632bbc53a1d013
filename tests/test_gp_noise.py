"""Known per-sample noise in the correction GP: ``fit(inputs, targets, noise=...)`` and ``fit(samples)``.

The covariance of output j is C_j = K + diag(known_j + floor). The posterior and the likelihood are compared with a
hand-written Cholesky formula (independent of GPyTorch), the gradient with autograd through the factorization.
"""

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec._errors import InputError, ShapeError
from torchmisspec.gp import _mll

DT = torch.float64
pytestmark = pytest.mark.usefixtures("one_thread")  # exact (atol=0) comparisons: the same thread count throughout
HYPER = {"lengthscale": 0.6, "outputscale": 0.02, "noise_variance": 1e-5}
XS = torch.linspace(-1, 1, 9, dtype=DT).reshape(-1, 1).expand(-1, 2) * torch.tensor([1.0, -0.5], dtype=DT)


def _data(seed=0, n=40):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    noise = torch.stack([1e-4 + 1e-3 * torch.rand(n, generator=g, dtype=DT), 1e-2 * X[:, 0].pow(2)], -1)
    Y = 0.1 * torch.stack([torch.sin(2 * X[:, 0]), X.pow(2).sum(-1)], -1)
    return X, Y + noise.sqrt() * torch.randn(n, 2, generator=g, dtype=DT), noise


def _k(a, b, lengthscale, outputscale):
    return outputscale * torch.exp(-0.5 * torch.cdist(a, b).pow(2) / lengthscale**2)


def _reference(X, Y, noise, Xs, lengthscale, outputscale, floor):
    """Posterior mean, variance of F and log marginal likelihood, one Cholesky per output (noise ``(N, d_out)``)."""
    means, variances, lml = [], [], 0.0
    for j in range(Y.shape[1]):
        C = _k(X, X, lengthscale, outputscale) + torch.diag(noise[:, j] + floor)
        L = torch.linalg.cholesky(C)
        alpha = torch.cholesky_solve(Y[:, j : j + 1], L)
        Ks = _k(Xs, X, lengthscale, outputscale)
        v = torch.linalg.solve_triangular(L, Ks.T, upper=False)
        means.append((Ks @ alpha)[:, 0])
        variances.append(outputscale - v.pow(2).sum(0))
        lml += float(
            -0.5 * (Y[:, j : j + 1] * alpha).sum()
            - torch.log(torch.diagonal(L)).sum()
            - 0.5 * X.shape[0] * math.log(2 * math.pi)
        )
    return torch.stack(means, -1), torch.stack(variances, -1), lml


def _samples(X, Y, noise):
    n = X.shape[0]
    return tms.CorrectionSamples(
        inputs=X, targets=Y, states=X, experiment=torch.zeros(n, dtype=torch.long), noise=noise
    )


@pytest.mark.parametrize("per_output", [False, True], ids=["shared_kernel", "per_output_kernels"])
@pytest.mark.parametrize("kind", ["shared_noise", "per_output_noise"])
def test_posterior_and_likelihood_match_hand_written_cholesky(kind, per_output):
    X, Y, noise = _data()
    given = noise[:, 0] if kind == "shared_noise" else noise
    full = given.unsqueeze(-1).expand(-1, 2) if given.dim() == 1 else given
    gp = tms.CorrectionGP(per_output=per_output, **HYPER).fit(X, Y, noise=given)
    mean, var, lml = _reference(X, Y, full, XS, HYPER["lengthscale"], HYPER["outputscale"], HYPER["noise_variance"])
    post = gp.predict(XS)
    torch.testing.assert_close(post.mean, mean, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(gp.predict_mean(XS), mean, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(post.variance, var, rtol=1e-10, atol=1e-13)
    assert gp.log_marginal_likelihood_ == pytest.approx(lml, rel=1e-10)
    torch.testing.assert_close(gp.train_noise_, full, rtol=0, atol=0)
    assert gp.train_noise_.data_ptr() != given.data_ptr()  # a copy, not the caller's tensor
    assert "with known noise" in repr(gp)
    # one factorization for noise shared by the outputs (shared kernel), one per output otherwise
    batch = gp.posterior().factor.chol.shape[0]
    assert batch == (1 if (kind == "shared_noise" and not per_output) else 2)


def test_zero_known_noise_is_the_model_without_noise():
    X, Y, _ = _data()
    plain = tms.CorrectionGP(**HYPER).fit(X, Y)
    zero = tms.CorrectionGP(**HYPER).fit(X, Y, noise=torch.zeros(X.shape[0], 2, dtype=DT))
    torch.testing.assert_close(zero.predict(XS).mean, plain.predict(XS).mean, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(zero.predict(XS).variance, plain.predict(XS).variance, rtol=1e-12, atol=1e-15)
    assert zero.log_marginal_likelihood_ == pytest.approx(plain.log_marginal_likelihood_, rel=1e-12)


@pytest.mark.parametrize("shared", [True, False], ids=["diag_1xN", "diag_dout_x_N"])
def test_gradient_with_known_noise_equals_autograd(shared):
    X, Y, noise = _data(seed=1)
    Yb = Y.unsqueeze(0) if shared else Y.T.unsqueeze(-1)
    known = noise[:, 0].unsqueeze(0) if shared else noise.T  # (1, N) or (d_out, N)
    log_l = torch.tensor(-0.4, dtype=DT, requires_grad=True)
    log_s = torch.tensor(-3.0, dtype=DT, requires_grad=True)
    log_floor = torch.tensor(-9.0, dtype=DT, requires_grad=True)
    params = (log_l, log_s, log_floor)

    def parts():
        K = _k(X, X, log_l.exp(), log_s.exp()).unsqueeze(0).expand(known.shape[0], -1, -1)
        return K, known + log_floor.exp()

    K, diag = parts()
    C = K + torch.diag_embed(diag)
    L = torch.linalg.cholesky(C)
    alpha = torch.cholesky_solve(Yb, L)
    m = Yb.shape[-1]
    ref = -0.5 * (Yb * alpha).sum() - m * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum()
    ref = ref - 0.5 * Yb.numel() * math.log(2 * math.pi)
    ref_grad = torch.autograd.grad(ref, params)

    K, diag = parts()
    with torch.no_grad():
        fac = _mll.factorize(K.detach(), diag.detach(), Yb)
        value = _mll.exact_mll(fac, X.shape[0])
        Q = _mll.gradient_weights(fac)
    grad = torch.autograd.grad(_mll.gradient_surrogate(Q, K, diag), params)
    assert float(value) == pytest.approx(float(ref.detach()), rel=1e-12)
    for a, b in zip(grad, ref_grad, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=0)


@pytest.mark.parametrize("given", [{}, {"lengthscale": 0.5}, {"noise_variance": 1e-6}])
def test_learned_hyperparameters_raise_the_likelihood_and_fixed_ones_are_kept(given):
    X, Y, noise = _data(seed=2, n=60)
    gp = tms.CorrectionGP(**given).fit(X, Y, noise=noise)
    start = {k: float(v) for k, v in gp.starting_values(X, Y).items()}
    start.update(given)
    at_start = tms.CorrectionGP(**start).fit(X, Y, noise=noise)
    assert gp.log_marginal_likelihood_ > at_start.log_marginal_likelihood_
    assert gp.n_iterations_ > 0
    for name, value in given.items():
        assert getattr(gp, name) == pytest.approx(value, rel=1e-14)  # stored in log space
    # a maximum: moving any learned hyperparameter by 20 % either way lowers the likelihood
    fitted = {name: getattr(gp, name) for name in HYPER}
    for name in set(HYPER) - set(given):
        for factor in (0.8, 1.25):
            moved = tms.CorrectionGP(**{**fitted, name: fitted[name] * factor}).fit(X, Y, noise=noise)
            assert moved.log_marginal_likelihood_ < gp.log_marginal_likelihood_
    # the fitted values are a stationary point of the likelihood with known noise: the hand formula agrees
    _, _, lml = _reference(X, Y, noise, XS, gp.lengthscale, gp.outputscale, gp.noise_variance)
    assert gp.log_marginal_likelihood_ == pytest.approx(lml, rel=1e-10)


def test_per_output_kernels_learn_with_known_noise():
    X, Y, noise = _data(seed=3)
    gp = tms.CorrectionGP(per_output=True, kernel="matern52").fit(X, Y, noise=noise)
    assert gp.noise_variance.shape == (2,) and gp.train_noise_.shape == (40, 2)
    assert math.isfinite(gp.log_marginal_likelihood_)


def test_warm_start_subsamples_the_noise_too():
    X, Y, noise = _data(seed=12, n=50)
    warm = tms.CorrectionGP().fit(X, Y, noise=noise, warm_start=10)
    cold = tms.CorrectionGP().fit(X, Y, noise=noise, warm_start=0)
    assert warm.log_marginal_likelihood_ == pytest.approx(cold.log_marginal_likelihood_, rel=1e-6)


def test_fit_samples_equals_fit_arrays():
    X, Y, noise = _data(seed=4)
    for n in (noise, None):
        a = tms.CorrectionGP().fit(_samples(X, Y, n))
        b = tms.CorrectionGP().fit(X, Y, noise=n)
        torch.testing.assert_close(a.predict(XS).mean, b.predict(XS).mean, rtol=0, atol=0)
        torch.testing.assert_close(a.predict(XS).variance, b.predict(XS).variance, rtol=0, atol=0)
        assert (a.lengthscale, a.outputscale, a.noise_variance) == (b.lengthscale, b.outputscale, b.noise_variance)
    # samples without noise give the old fit exactly (no known noise, the profiled path)
    old = tms.CorrectionGP().fit(X, Y)
    assert a.train_noise_ is None and isinstance(a.likelihood, type(old.likelihood))
    assert a.log_marginal_likelihood_ == old.log_marginal_likelihood_
    torch.testing.assert_close(a.predict_mean(XS), old.predict_mean(XS), rtol=0, atol=0)


def test_refit_without_noise_drops_the_known_noise():
    X, Y, noise = _data(seed=5)
    gp = tms.CorrectionGP(**HYPER).fit(X, Y, noise=noise)
    gp.fit(X, Y)
    assert gp.train_noise_ is None
    mean, _, _ = _reference(X, Y, torch.zeros_like(noise), XS, *HYPER.values())
    torch.testing.assert_close(gp.predict_mean(XS), mean, rtol=1e-10, atol=1e-13)


def test_cache_follows_the_known_noise():
    X, Y, noise = _data(seed=6)
    gp = tms.CorrectionGP(**HYPER).fit(X, Y, noise=noise)
    before = gp.predict_mean(XS)
    with torch.no_grad():
        gp.train_noise_[:, 1] *= 100.0  # in place, through the public view
    after = gp.predict_mean(XS)
    assert (after - before).abs().max() > 1e-3 * before.abs().max()
    edited = noise.clone()
    edited[:, 1] *= 100.0
    mean, var, lml = _reference(X, Y, edited, XS, *HYPER.values())
    torch.testing.assert_close(after, mean, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(gp.predict(XS).variance, var, rtol=1e-10, atol=1e-13)
    assert gp.log_marginal_likelihood_ == pytest.approx(lml, rel=1e-10)
    # a new tensor in the GPyTorch likelihood is seen too
    gp.likelihood.noise_covar.noise = noise.T.contiguous()
    mean, _, _ = _reference(X, Y, noise, XS, *HYPER.values())
    torch.testing.assert_close(gp.predict_mean(XS), mean, rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("per_output", [False, True])
def test_gpytorch_model_view_matches_cached_posterior_heteroscedastic(per_output):
    X, Y, noise = _data(seed=7)
    gp = tms.CorrectionGP(per_output=per_output).fit(X, Y, noise=noise)
    assert isinstance(gp.likelihood, tms.gp._model.gpytorch.likelihoods.FixedNoiseGaussianLikelihood)
    with torch.no_grad():
        dist = gp.model(XS)
    post = gp.predict(XS)
    torch.testing.assert_close(dist.mean.T, post.mean, rtol=1e-9, atol=1e-14)
    torch.testing.assert_close(dist.variance.T, post.variance, rtol=1e-7, atol=1e-14)


def test_tiny_known_noise_is_not_rounded_by_gpytorch():
    X, Y, noise = _data(seed=8)
    tiny = torch.full_like(noise, 1e-9)
    gp = tms.CorrectionGP(**{**HYPER, "noise_variance": 1e-4}).fit(X, Y, noise=tiny)
    assert float(gp.train_noise_.max()) == 1e-9


def test_save_load_round_trip_with_noise(tmp_path):
    X, Y, noise = _data(seed=9)
    for gp in (
        tms.CorrectionGP().fit(X, Y, noise=noise),
        tms.CorrectionGP(per_output=True).fit(X, Y, noise=noise[:, 0]),
    ):
        path = gp.save(tmp_path / "gp.pt")
        blob = torch.load(path, weights_only=True)
        torch.testing.assert_close(blob["train_noise"], gp.train_noise_, rtol=0, atol=0)
        loaded = tms.CorrectionGP.load(path)
        torch.testing.assert_close(loaded.train_noise_, gp.train_noise_, rtol=0, atol=0)
        torch.testing.assert_close(loaded.predict(XS).mean, gp.predict(XS).mean, rtol=0, atol=0)
        torch.testing.assert_close(loaded.predict(XS).variance, gp.predict(XS).variance, rtol=0, atol=0)
        assert loaded.log_marginal_likelihood_ == gp.log_marginal_likelihood_
        assert loaded.noise_variance is not None


def test_load_refuses_bad_saved_noise(tmp_path):
    X, Y, noise = _data(seed=9)
    path = tms.CorrectionGP(**HYPER).fit(X, Y, noise=noise).save(tmp_path / "gp.pt")
    blob = torch.load(path, weights_only=True)
    for bad in (noise[:5], -noise):
        torch.save({**blob, "train_noise": bad}, tmp_path / "bad.pt")
        with pytest.raises(InputError, match="train_noise"):
            tms.CorrectionGP.load(tmp_path / "bad.pt")


def test_condition_on_new_noise_keeps_the_hyperparameters():
    X, Y, noise = _data(seed=10)
    gp = tms.CorrectionGP().fit(X, Y, noise=noise)
    copy = gp.condition(X, Y, noise=noise)
    assert copy.noise_variance == gp.noise_variance
    assert copy.n_iterations_ == 0
    torch.testing.assert_close(copy.predict_mean(XS), gp.predict_mean(XS), rtol=1e-12, atol=1e-15)


def test_bad_noise_is_refused_and_the_model_is_unchanged():
    X, Y, noise = _data(seed=11)
    gp = tms.CorrectionGP(**HYPER).fit(X, Y, noise=noise)
    before = gp.predict_mean(XS)
    n = X.shape[0]
    cases = [
        (torch.ones(n + 1, dtype=DT), ShapeError, rf"\({n},\) .*\({n}, 2\).*got shape \({n + 1},\)"),
        (torch.ones(n, 3, dtype=DT), ShapeError, rf"got shape \({n}, 3\)"),
        (torch.ones(n, 2, 1, dtype=DT), ShapeError, "got shape"),
        (-noise, InputError, "non-negative"),
        (noise.clone().index_fill_(0, torch.tensor([3]), float("nan")), InputError, "noise"),
        (noise.clone().index_fill_(0, torch.tensor([3]), float("inf")), InputError, "noise"),
    ]
    for bad, error, match in cases:
        with pytest.raises(error, match=match):
            gp.fit(X, Y, noise=bad)
    torch.testing.assert_close(gp.predict_mean(XS), before, rtol=0, atol=0)
    samples = _samples(X, Y, noise)
    with pytest.raises(InputError, match="CorrectionSamples object and targets"):
        gp.fit(samples, Y)
    with pytest.raises(InputError, match="CorrectionSamples object and noise"):
        gp.fit(samples, noise=noise)
    with pytest.raises(InputError, match="targets: expected"):
        gp.fit(X)
    with pytest.raises(ShapeError, match="noise"):
        gp.fit(_samples(X, Y, noise[:, :1]))


def test_one_output_with_known_noise():
    X, Y, noise = _data(seed=13)
    gp = tms.CorrectionGP(**HYPER).fit(X, Y[:, 0], noise=noise[:, 0])
    mean, var, lml = _reference(X, Y[:, :1], noise[:, :1], XS, *HYPER.values())
    torch.testing.assert_close(gp.predict(XS).mean, mean, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(gp.predict(XS).variance, var, rtol=1e-10, atol=1e-13)
    assert gp.log_marginal_likelihood_ == pytest.approx(lml, rel=1e-10)
