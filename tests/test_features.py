"""The feature kernel with automatic relevance (sparse Bayesian learning), and its trajectory fit."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._features import monomial_names, monomial_powers, monomials
from torchmisspec.gp._relevance import _evidence, fit_relevance, unit_information_weights
from torchmisspec.learning.refinement.trajectory_fit import shooting_misfit
from torchmisspec.systems import LinearField, MisspecifiedSystem

DT = torch.float64


def data(n=150, noise=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    F = torch.stack([0.5 * X[:, 0] ** 2 - 0.3 * X[:, 1], 2.0 * X[:, 0] * X[:, 1]], -1)
    return X, F, F + noise * torch.randn(F.shape, generator=g, dtype=DT)


def test_monomials_and_names():
    P = monomial_powers(2, 3)
    assert P.tolist()[:6] == [[0, 0], [1, 0], [0, 1], [2, 0], [1, 1], [0, 2]] and P.shape == (10, 2)
    assert monomial_names(P, ["y", "w"])[:6] == ["1", "y", "w", "y^2", "y w", "w^2"]
    x = torch.tensor([[2.0, 3.0]], dtype=DT)
    assert monomials(x, P)[0].tolist() == [1, 2, 3, 4, 6, 9, 8, 12, 18, 27]


@pytest.mark.parametrize("per_output", [False, True])
def test_posterior_is_bayesian_linear_regression(per_output):
    """Predictions equal the closed-form Bayesian linear regression with the learned weights and noise; the N x N
    log marginal likelihood equals the feature-space evidence."""
    X, _, Y = data(noise=0.05)
    gp = tms.CorrectionGP(kernel="features", degree=2, per_output=per_output).fit(X, Y)
    P = monomial_powers(2, 2)
    Phi = monomials(X, P)
    xs = torch.rand(7, 2, generator=torch.Generator().manual_seed(3), dtype=DT) * 3 - 1.5
    phis = monomials(xs, P)
    post = gp.predict(xs)
    W = gp.weights.reshape(-1, P.shape[0])
    spread = gp.covar_module.base_kernel.spread.reshape(-1, P.shape[0])  # the removed terms' (tested below)
    s = torch.as_tensor(gp.noise_variance, dtype=DT).reshape(-1)
    total = 0.0
    for o in range(2):
        w, noise = W[o if per_output else 0], s[o if per_output else 0]
        act = w > 0
        A = Phi[:, act].T @ Phi[:, act] / noise + torch.diag(1 / w[act])
        Sigma = torch.linalg.inv(A)
        mu = Sigma @ Phi[:, act].T @ Y[:, o] / noise
        torch.testing.assert_close(post.mean[:, o], phis[:, act] @ mu, rtol=1e-7, atol=1e-9)
        var = ((phis[:, act] @ Sigma) * phis[:, act]).sum(-1) + (phis.pow(2) * spread[o if per_output else 0]).sum(-1)
        torch.testing.assert_close(post.variance[:, o], var, rtol=1e-6, atol=1e-10)
        total += _evidence(Phi, Y[:, o : o + 1], noise.expand(len(X), 1), w)
    assert gp.log_marginal_likelihood_ == pytest.approx(total, rel=1e-9)


def test_relevance_removes_absent_terms_and_recovers_present_ones():
    X, F, _ = data()
    gp = tms.CorrectionGP(kernel="features", degree=3, per_output=True).fit(X, F)  # noiseless
    present = {0: {"y2", "y1^2"}, 1: {"y1 y2"}}
    chosen = gp.terms(["y1", "y2"])
    for o in range(2):
        assert {t.name for t in chosen if t.output == o} == present[o]  # the chosen subset: no absent monomial
    for t in gp.terms(["y1", "y2"], all_terms=True):  # a removed term keeps only a small chance of being present
        assert (t.inclusion > 0.5) == (t.name in present[t.output])
    terms = {(t.output, t.name): t for t in gp.terms(["y1", "y2"])}
    assert terms[0, "y1^2"].mean == pytest.approx(0.5, abs=1e-8)
    assert terms[0, "y2"].mean == pytest.approx(-0.3, abs=1e-8)
    assert terms[1, "y1 y2"].mean == pytest.approx(2.0, abs=1e-8)
    assert str(terms[0, "y1^2"]).startswith("+0.5 +- ") and str(terms[0, "y1^2"]).endswith("* y1^2")
    assert len(gp.terms(all_terms=True)) == 2 * len(gp.feature_names())


def test_weights_are_a_stationary_point_of_the_evidence():
    """The fixed point maximises the exact evidence: moving any kept weight by 1 % lowers it (brute force)."""
    X, _, Y = data(noise=0.05, seed=2)
    y = Y[:, :1]
    Phi = monomials(X, monomial_powers(2, 2))
    w, s, _ = fit_relevance(Phi, y, None, floor=None, max_iter=5000)
    best = _evidence(Phi, y, torch.full_like(y, s), w)
    for j in torch.nonzero(w > 0).reshape(-1).tolist():
        for f in (0.99, 1.01):
            v = w.clone()
            v[j] *= f
            assert _evidence(Phi, y, torch.full_like(y, s), v) < best
    for f in (0.99, 1.01):
        assert _evidence(Phi, y, torch.full_like(y, s * f), w) < best


@pytest.mark.parametrize("known", [False, True])
def test_a_kept_term_is_least_squares_under_its_unit_information_slab(known):
    """A term measured at a modest signal-to-noise ratio gets the unit-information slab N / sum phi^2 / D, not
    MacKay's weight ~ its coefficient squared, which shrank it (issue 27: the shrinkage doubled the error against
    SINDy); its coefficient is Bayesian linear regression's with the GP's weights, by hand."""
    g = torch.Generator().manual_seed(0)
    N = 50
    X = torch.rand(N, 1, generator=g, dtype=torch.float64) * 2 - 1
    noise = 0.05 * (1 + X) ** 2 + 1e-3 if known else None  # (N, 1) known variances, or a learned floor
    sd = 0.05 if noise is None else noise.sqrt()
    Y = 0.05 * X**2 + sd * torch.randn(N, 1, generator=g, dtype=torch.float64)
    gp = tms.CorrectionGP(kernel="features").fit(X, Y, noise=noise)
    (term,) = gp.terms()
    assert term.name == "x1^2"
    phi = X[:, 0] ** 2
    floor = float(gp.noise_variance)  # the learned floor (beside the known noise)
    D = torch.full((N,), floor, dtype=torch.float64) if noise is None else noise[:, 0] + floor
    assert term.weight == pytest.approx(N / float((phi * phi / D).sum()), rel=1e-9)  # the unit-information slab
    # the coefficient: Bayesian linear regression by hand with the GP's weights (the removed terms' small ones too)
    Phi = monomials(X, monomial_powers(1, 2))
    W = gp.weights.reshape(-1)
    A = Phi.T @ (Phi / D.unsqueeze(-1)) + torch.diag(1 / W)
    mean = torch.linalg.solve(A, Phi.T @ (Y[:, 0] / D))
    assert term.mean == pytest.approx(float(mean[2]), rel=1e-8)
    lsq = float((phi * Y[:, 0] / D).sum() / (phi * phi / D).sum())  # one kept term: least squares x N / (N + 1)
    assert term.mean == pytest.approx(lsq * N / (N + 1), rel=1e-9)


def test_term_inclusion_is_the_exact_bayes_factor_and_widens_the_bands():
    """Brute force on a tiny problem: each term's chance of being present is the posterior odds (1:1 prior) of the
    models with and without it, from dense Gaussian evidences with the unit-information slab N s / sum phi^2; a
    removed term's spread is that chance times its coefficient's variance in the model with it; predict and the
    draws add that spread to the chosen subset's posterior (hand-written), whose mean they keep."""
    g = torch.Generator().manual_seed(3)
    N = 30
    X = torch.rand(N, 1, generator=g, dtype=torch.float64) * 2 - 1
    Y = 0.5 * X**2 + 0.2 * torch.randn(N, 1, generator=g, dtype=torch.float64)
    gp = tms.CorrectionGP(kernel="features", degree=3).fit(X, Y)
    Phi = monomials(X, monomial_powers(1, 3))
    w = gp.weights.reshape(-1)
    s = float(gp.noise_variance)
    unit = N * s / Phi.pow(2).sum(0)
    y = Y[:, 0]

    def log_evidence(weights):
        C = (Phi * weights) @ Phi.T + s * torch.eye(N, dtype=torch.float64)
        return float(torch.distributions.MultivariateNormal(torch.zeros(N, dtype=torch.float64), C).log_prob(y))

    kept = w > 0
    assert bool(kept.any()) and not bool(kept.all())
    terms = gp.terms(all_terms=True)
    for j in range(4):
        with_j, without_j = w.clone(), w.clone()
        with_j[j], without_j[j] = (w[j] if kept[j] else unit[j]), 0.0
        p = 1 / (1 + math.exp(log_evidence(without_j) - log_evidence(with_j)))
        assert terms[j].inclusion == pytest.approx(p, rel=1e-6)
        if not kept[j]:  # its spread: p times its coefficient's posterior variance in the model with it
            act = with_j > 0
            cov = torch.linalg.inv(Phi[:, act].T @ Phi[:, act] / s + torch.diag(1 / with_j[act]))
            v = float(cov[int(act[:j].sum()), int(act[:j].sum())])
            assert float(gp.covar_module.base_kernel.spread[j]) == pytest.approx(p * v, rel=1e-6)
        else:
            assert float(gp.covar_module.base_kernel.spread[j]) == 0.0
    assert all((t.inclusion > 0.5) == (t.weight > 0) for t in terms)  # here the price and the odds agree
    # the bands and the draws carry the spread; the mean is the chosen subset's
    xs = torch.linspace(-1.5, 1.5, 7, dtype=torch.float64).unsqueeze(-1)
    post = gp.predict(xs)
    phis = monomials(xs, monomial_powers(1, 3))
    A = Phi[:, kept].T @ Phi[:, kept] / s + torch.diag(1 / w[kept])
    cov = torch.linalg.inv(A)
    torch.testing.assert_close(post.mean[:, 0], phis[:, kept] @ (cov @ Phi[:, kept].T @ y / s))
    extra = (phis.pow(2) * gp.covar_module.base_kernel.spread).sum(-1)
    torch.testing.assert_close(post.variance[:, 0], ((phis[:, kept] @ cov) * phis[:, kept]).sum(-1) + extra)
    draws = gp.sample_functions(4000, generator=torch.Generator().manual_seed(0))(xs)[..., 0]
    assert float((draws.var(0) / post.variance[:, 0] - 1).abs().max()) < 0.1
    wide = gp.sample_functions(4000, generator=torch.Generator().manual_seed(0), scale=2.0)(xs)[..., 0]
    assert float((wide.var(0) / (4 * post.variance[:, 0]) - 1).abs().max()) < 0.1  # the spread widens with c too


def test_unit_information_weights_widen_only_kept_narrow_terms():
    Phi = torch.tensor([[1.0, 2.0, 0.5], [3.0, 1.0, 0.5]], dtype=torch.float64)
    w = torch.tensor([0.0, 1e-6, 10.0], dtype=torch.float64)
    out = unit_information_weights(Phi, w, None, 0.1)
    unit = 2 * 0.1 / Phi.pow(2).sum(0)
    assert out.tolist() == [0.0, pytest.approx(float(unit[1])), 10.0]
    known = torch.tensor([[0.1, 0.3], [0.2, 0.1]], dtype=torch.float64)  # two outputs sharing the weights
    out = unit_information_weights(Phi, w, known, 0.05)
    info = (Phi[:, 1:2].pow(2) / (known + 0.05)).sum()
    assert float(out[1]) == pytest.approx(2 * 2 / float(info))


def test_known_noise_and_a_fixed_floor():
    X, _, Y = data(noise=0.05, seed=4)
    known = torch.linspace(1e-4, 4e-3, len(X), dtype=DT)
    gp = tms.CorrectionGP(kernel="features", degree=2, noise_variance=1e-3).fit(X, Y, noise=known)
    assert gp.noise_variance == pytest.approx(1e-3)
    Phi = monomials(X, monomial_powers(2, 2))
    w = gp.weights
    act = w > 0
    D = known + 1e-3
    Sigma = torch.linalg.inv(Phi[:, act].T @ (Phi[:, act] / D[:, None]) + torch.diag(1 / w[act]))
    mu = Sigma @ Phi[:, act].T @ (Y / D[:, None])
    xs = X[:5] + 0.1
    torch.testing.assert_close(gp.predict_mean(xs), monomials(xs, monomial_powers(2, 2))[:, act] @ mu)


def test_paths_persistence_and_conditioning(tmp_path):
    X, _, Y = data(noise=0.05, seed=5)
    gp = tms.CorrectionGP(kernel="features", degree=2, per_output=True).fit(X, Y)
    xs = torch.rand(4, 2, generator=torch.Generator().manual_seed(9), dtype=DT)
    draws = gp.sample_functions(4000, generator=torch.Generator().manual_seed(0))(xs)  # (S, 4, 2)
    post = gp.predict(xs)
    sd = post.stddev
    assert float(((draws.mean(0) - post.mean).abs() / sd).max()) < 5 / math.sqrt(4000) * 1.5
    ratio = draws.var(0) / post.variance
    assert float((ratio - 1).abs().max()) < 0.1
    path = gp.save(tmp_path / "features.pt")
    loaded = tms.CorrectionGP.load(path)
    assert torch.equal(loaded.weights, gp.weights) and loaded.kernel == "features"
    torch.testing.assert_close(loaded.predict_mean(xs), gp.predict_mean(xs), rtol=1e-12, atol=1e-14)
    gp.samples_ = "the samples of this fit"  # a record of the fit (as fit_correction leaves): not carried over
    part = gp.condition(X[:40], Y[:40])  # the same hyperparameters on other data, nothing re-learned
    assert not hasattr(part, "samples_") and part.n_iterations_ == 0 and part.fixed is not gp.fixed
    assert part.log_marginal_likelihood_ is not None  # recomputed for the new data by the cache
    assert torch.equal(part.weights, gp.weights) and len(part.train_inputs_) == 40
    again = tms.CorrectionGP(kernel="features", degree=2, per_output=True).fit(X[:40], Y[:40])
    assert not torch.equal(again.weights, gp.weights)  # a fit would have re-learned them
    rbf = tms.CorrectionGP().fit(X, Y)
    fixed = tms.CorrectionGP(
        lengthscale=rbf.lengthscale, outputscale=rbf.outputscale, noise_variance=rbf.noise_variance
    ).fit(X[:40], Y[:40])
    torch.testing.assert_close(rbf.condition(X[:40], Y[:40]).predict_mean(xs), fixed.predict_mean(xs))


def test_bad_input():
    X, _, Y = data()
    with pytest.raises(
        tms.InputError, match=r"lengthscale: expected None \(the features kernel .* has no lengthscale\), got 1.0"
    ):
        tms.CorrectionGP(kernel="features", lengthscale=1.0)
    with pytest.raises(tms.InputError, match=r"degree: expected"):
        tms.CorrectionGP(kernel="features", degree=0)
    with pytest.raises(tms.InputError, match=r"kernel: expected a Kernel object or one of"):
        tms.CorrectionGP(kernel="sindy")
    with pytest.raises(tms.NotFittedError, match=r"feature kernels are built by fit"):
        tms.CorrectionGP(kernel="features").covariance(X)
    with pytest.raises(tms.FittingError, match=r"expected some non-zero samples"):
        tms.CorrectionGP(kernel="features", noise_variance=1e-3).fit(X, torch.zeros_like(Y))
    gp = tms.CorrectionGP(kernel="features").fit(X, Y)
    with pytest.raises(tms.InputError, match=r"only the feature kernels have named terms"):
        tms.CorrectionGP().fit(X, Y).terms()
    with pytest.raises(tms.ShapeError, match=r"targets: expected \(10, 2\)"):
        gp.condition(X[:10], Y[:10, :1])
    with pytest.raises(tms.InputError, match=r"the feature kernel's weights are learned from data"):
        tms.design.greedy(
            torch.zeros(3, 2, dtype=DT),
            1,
            system=tms.systems.paper_linear(),
            times=torch.linspace(0, 1, 3, dtype=DT),
            gp=tms.CorrectionGP(kernel="features"),
        )


def linear_problem():
    """y' = A y + F(y), F = [0.05 y1^2, 0] unknown; states observed without noise at T = 21."""
    A = torch.tensor([[-0.1, 1.0], [-1.0, -0.1]], dtype=DT)
    system = MisspecifiedSystem(
        LinearField(A),
        2,
        correction=lambda y: 0.05 * y[..., :1] ** 2,
        correction_outputs=[0],
        known_matrix=A,
        name="linear_square",
    )
    y0 = torch.tensor([[1.0, 0.0], [-0.5, 0.8], [0.3, -1.0], [-1.0, -0.4]], dtype=DT)
    return system, tms.simulate(system, y0, torch.linspace(0, 6, 21, dtype=DT))


def test_trajectory_relevance_recovers_the_term(one_thread):
    system, traj = linear_problem()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        samples = tms.correction_samples(traj, system, derivative="smooth", window=7, degree=2)  # biased samples
    gp = tms.CorrectionGP(kernel="features", degree=2).fit(samples)
    refined = tms.fit_trajectories(gp, system, traj, state_noise=1e-8)
    assert refined.n_rhs_evaluations_ > refined.n_evaluations_ >= refined.n_iterations_ >= 1
    terms = {t.name: t.mean for t in refined.terms(["y1", "y2"])}
    assert terms["y1^2"] == pytest.approx(0.05, rel=1e-3)
    assert all(abs(v) < 1e-4 for k, v in terms.items() if k != "y1^2")
    # the pseudo-targets reproduce the fitted coefficients exactly: the posterior mean is phi(x)^T beta
    xs = torch.rand(6, 2, generator=torch.Generator().manual_seed(1), dtype=DT) * 2 - 1
    beta = torch.zeros(6, dtype=DT)
    for j, t in enumerate(refined.terms(all_terms=True)):
        beta[j] = t.mean
    torch.testing.assert_close(refined.predict_mean(xs)[:, 0], monomials(xs, monomial_powers(2, 2)) @ beta)
    assert shooting_misfit(refined, system, traj) < 0.1 * shooting_misfit(gp, system, traj)
    with pytest.raises(tms.InputError, match=r"relevance: expected a feature kernel"):
        tms.fit_trajectories(tms.CorrectionGP().fit(samples), system, traj, relevance=True)


def test_fit_correction_chooses_the_feature_kernel_for_a_polynomial_correction(one_thread):
    system, traj = linear_problem()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system)
    cv = gp.cross_validation_
    assert cv.best == "features degree=3 per_output" and gp.kernel == "features"
    assert cv.candidates[-1] == cv.best and cv.lengthscales[-1] is None and cv.best_lengthscale is None
    assert {t.name for t in gp.terms(["y1", "y2"])} >= {"y1^2"}
    y0 = torch.tensor([[0.7, 0.7], [-0.8, 0.2]], dtype=DT)
    times = torch.linspace(0, 6, 31, dtype=DT)
    true = tms.simulate(system, y0, times).states
    pred = tms.CorrectedODE(system, gp).predict(y0, times)
    known = tms.simulate(system, y0, times, known_only=True).states
    assert tms.trajectory_rmse(pred, true) < 0.05 * tms.trajectory_rmse(known, true)


@pytest.mark.parametrize(("per_output", "known"), [(False, False), (True, False), (False, True), (True, True)])
def test_feature_space_posterior_equals_the_dense_one(per_output, known):
    """The feature kernel's posterior is computed in feature space (Woodbury, never N x N); it equals the dense GP
    algebra (a hand-written Cholesky of K + D) in mean, variance, likelihood, alpha and the on-demand factor."""
    gen = torch.Generator().manual_seed(5)
    X = torch.rand(60, 2, dtype=DT, generator=gen) * 2 - 1
    Y = torch.stack([0.5 * X[:, 0] ** 2, X[:, 1] - X[:, 0] * X[:, 1]], -1) + 0.05 * torch.randn(
        60, 2, dtype=DT, generator=gen
    )
    noise = (0.001 + 0.002 * torch.rand(60, 2, dtype=DT, generator=gen)) if known else None
    gp = tms.CorrectionGP(kernel="features", degree=2, per_output=per_output).fit(X, Y, noise=noise)
    base = gp.covar_module.base_kernel
    W = base.weights.detach().reshape(-1, 6) * gp.covar_module.outputscale.detach().reshape(-1, 1)
    floor = gp._floor(gp.likelihood).noise.detach().reshape(-1)
    x = torch.rand(15, 2, dtype=DT, generator=gen) * 3 - 1.5
    post = gp.predict(x)
    lml = 0.0
    for o in range(2):
        w = W[o if W.shape[0] > 1 else 0]
        d = floor[o if floor.numel() > 1 else 0] + (noise[:, o] if known else 0.0)

        def k(a, b, w=w):
            return (base.features(a) * w) @ base.features(b).T

        C = k(X, X) + torch.diag(torch.as_tensor(d, dtype=DT).expand(60))
        L = torch.linalg.cholesky(C)
        alpha = torch.cholesky_solve(Y[:, o : o + 1], L)
        mean = k(x, X) @ alpha
        var = k(x, x).diagonal() - (torch.linalg.solve_triangular(L, k(X, x), upper=False) ** 2).sum(0)
        spread = base.spread.reshape(-1, 6)[o if W.shape[0] > 1 else 0]  # the removed terms' (not conditioned)
        var = var + (base.features(x).pow(2) * spread).sum(-1)
        torch.testing.assert_close(post.mean[:, o], mean[:, 0], rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(post.variance[:, o], var, rtol=1e-7, atol=1e-12)
        lml += float(-0.5 * Y[:, o] @ alpha[:, 0] - L.diagonal().log().sum() - 30 * math.log(2 * math.pi))
    assert gp.log_marginal_likelihood_ == pytest.approx(lml, rel=1e-10)
    fac = gp.posterior().factor
    C0 = fac.chol[0] @ fac.chol[0].T  # the dense factor, on request
    d0 = floor[0] + (noise[:, 0] if known else 0.0)
    w0 = W[0]
    torch.testing.assert_close(
        C0, (base.features(X) * w0) @ base.features(X).T + torch.diag(torch.as_tensor(d0).expand(60))
    )


def _library():
    return [lambda x: x[..., 0] ** 2, lambda x: torch.sin(x[..., 1]), lambda x: x[..., 0] * x[..., 1]]


def test_user_library_posterior_is_bayesian_linear_regression(tmp_path):
    """A library of user callables replaces the monomials: the posterior is Bayesian linear regression on them."""
    gen = torch.Generator().manual_seed(7)
    X = torch.rand(80, 2, dtype=DT, generator=gen) * 2 - 1
    y = 0.3 * X[:, 0] ** 2 - 0.7 * torch.sin(X[:, 1]) + 0.02 * torch.randn(80, dtype=DT, generator=gen)
    gp = tms.CorrectionGP(kernel="features", library=_library(), library_names=["a^2", "sin b", "a b"]).fit(X, y)
    base = gp.covar_module.base_kernel
    w = base.weights.detach() * gp.covar_module.outputscale.detach()
    Phi = torch.stack([f(X) for f in _library()], -1)
    s2 = gp.noise_variance
    act = w > 0
    A = torch.diag(1 / w[act]) + Phi[:, act].T @ Phi[:, act] / s2
    mean = torch.linalg.solve(A, Phi[:, act].T @ y / s2)
    cov = torch.linalg.inv(A)
    x = torch.rand(9, 2, dtype=DT, generator=gen)
    phi = torch.stack([f(x) for f in _library()], -1)[:, act]
    post = gp.predict(x)
    torch.testing.assert_close(post.mean[:, 0], phi @ mean, rtol=1e-8, atol=1e-12)
    spread = (torch.stack([f(x) for f in _library()], -1).pow(2) * base.spread).sum(-1)
    torch.testing.assert_close(post.variance[:, 0], ((phi @ cov) * phi).sum(-1) + spread, rtol=1e-7, atol=1e-14)
    terms = {t.name: t for t in gp.terms()}
    assert terms["a^2"].mean == pytest.approx(0.3, abs=0.05) and terms["sin b"].mean == pytest.approx(-0.7, abs=0.05)
    draws = gp.sample_functions(8, generator=torch.Generator().manual_seed(0))(x)
    assert draws.shape == (8, 9, 1) and bool(torch.isfinite(draws).all())
    with pytest.raises(tms.InputError, match="never holds code"):
        gp.save(tmp_path / "lib.pt")


def test_user_library_bad_input():
    X = torch.zeros(5, 2, dtype=DT)
    with pytest.raises(tms.InputError, match="at least one feature"):
        tms.CorrectionGP(kernel="features", library=[])
    with pytest.raises(tms.InputError, match="expected callables"):
        tms.CorrectionGP(kernel="features", library=[lambda x: x[..., 0], 3.0])
    with pytest.raises(tms.InputError, match="'features' or 'features\\+rbf'"):
        tms.CorrectionGP(kernel="rbf", library=_library())
    with pytest.raises(tms.InputError, match="3 distinct strings"):
        tms.CorrectionGP(kernel="features", library=_library(), library_names=["a", "a", "b"])
    with pytest.raises(tms.ShapeError, match="feature 'f1' must map inputs \\(5, 2\\) to \\(5,\\)"):
        tms.CorrectionGP(kernel="features", library=[lambda x: x]).fit(X, X[:, :1] + 1)
    with pytest.raises(tms.InputError, match="feature 'f1' returned NaN"):
        tms.CorrectionGP(kernel="features", library=[lambda x: x[..., 0] / 0.0]).fit(X, X[:, :1] + 1)
    with pytest.raises(tms.InputError, match="degree"):
        tms.CorrectionGP(kernel="features", degree=0)


def test_removal_and_readmission_do_not_cycle():
    """Shared weights, degree 8: the removal test and the re-admission test once disagreed near the boundary and a
    term cycled out and in until the iteration cap (4,000 posterior solves instead of ~100)."""
    g = torch.Generator().manual_seed(0)
    X = torch.rand(2000, 2, dtype=DT, generator=g) * 2 - 1
    F = torch.stack([0.01 * X[:, 0] ** 2, 0.01 * X[:, 1] ** 2 + 0.003 * X[:, 0]], -1)
    Y = F + 1e-2 * torch.randn(2000, 2, dtype=DT, generator=g)
    Phi = monomials(X, monomial_powers(2, 8))
    w, s, iterations = fit_relevance(Phi, Y, None, floor=None, max_iter=2000)
    assert iterations < 500
    best = _evidence(Phi, Y, torch.full_like(Y, s), w)
    for j in torch.nonzero(w > 0).reshape(-1).tolist():  # still a stationary point in every kept weight
        for f in (0.98, 1.02):
            v = w.clone()
            v[j] *= f
            assert _evidence(Phi, Y, torch.full_like(Y, s), v) < best + 1e-9


def test_sum_kernel_terms_use_each_outputs_factor_with_known_noise():
    """features+rbf terms(): with known noise that differs between outputs the dense factor is one per output, but
    the coefficients' standard deviations used output 0's for every output (understated up to 2.4x)."""
    g = torch.Generator().manual_seed(0)
    N = 40
    X = torch.randn(N, 2, generator=g, dtype=torch.float64)
    F = torch.stack([1 + 0.5 * X[:, 0] + 0.2 * torch.sin(2 * X[:, 1]), -0.7 * X[:, 0] + 0.3 * X[:, 1] ** 2], -1)
    noise = torch.stack([torch.full((N,), 1e-4), torch.full((N,), 0.25)], -1).to(torch.float64)
    Y = F + noise.sqrt() * torch.randn(N, 2, generator=g, dtype=torch.float64)
    gp = tms.CorrectionGP(kernel="features+rbf").fit(X, Y, noise=noise)
    w, Phi = gp.weights, gp.covar_module.base_kernel.features(X).detach()
    K = gp.covariance(X)  # the whole prior kernel: library and RBF term
    terms = gp.terms(all_terms=True)
    for o in range(2):
        Ci = torch.linalg.inv(K + torch.diag(noise[:, o] + float(gp.noise_variance)))
        mean = w * (Phi.T @ (Ci @ Y[:, o]))
        std = (w - w * w * ((Phi.T @ Ci) * Phi.T).sum(-1)).clamp_min(0).sqrt()
        got = [t for t in terms if t.output == o]
        torch.testing.assert_close(torch.tensor([t.mean for t in got], dtype=torch.float64), mean, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(torch.tensor([t.std for t in got], dtype=torch.float64), std, rtol=1e-6, atol=1e-9)


def test_feature_fit_says_when_it_stops_at_its_cap_and_which_output_is_all_zeros():
    g = torch.Generator().manual_seed(1)
    X = torch.randn(50, 3, generator=g, dtype=torch.float64)
    F = torch.stack([1 + 0.5 * X[:, 0] - 0.3 * X[:, 0] * X[:, 1], torch.sin(X[:, 2]), 0.1 * X[:, 1] ** 2], -1)
    Y = F + 0.3 * torch.randn(50, 3, generator=g, dtype=torch.float64)
    with pytest.warns(tms.NumericalWarning, match="did not converge in 20 iterations"):
        tms.CorrectionGP(kernel="features", degree=3, per_output=True, max_iter=2).fit(X, Y)
    Y[:, 1] = 0.0
    with pytest.raises(tms.FittingError, match="output 1: targets: expected some non-zero samples"):
        tms.CorrectionGP(kernel="features", per_output=True).fit(X, Y)


def test_refinement_through_the_ode_keeps_only_the_samples_chance_of_the_terms_both_removed(one_thread):
    """After fit_trajectories: a kept term is present (chance 1, no spread); a term the samples' fit removed too keeps
    the samples' chance and spread; a term the samples kept but the trajectories removed counts as absent."""
    system = tms.systems.paper_linear()
    y0 = torch.rand(5, 2, generator=torch.Generator().manual_seed(7), dtype=DT) * 2 - 1
    trajs = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=DT))
    samples = tms.correction_samples(trajs, system, derivative="central")
    gp = tms.CorrectionGP(kernel="features", degree=3, per_output=True).fit(samples)
    refined = tms.fit_trajectories(gp, system, trajs)
    before, after = gp.covar_module.base_kernel, refined.covar_module.base_kernel
    kept, was_kept = after.weights.detach() > 0, before.weights.detach() > 0
    assert bool((after.inclusion[kept] == 1).all()) and bool((after.spread[kept] == 0).all())
    both = ~kept & ~was_kept
    assert bool(both.any())
    torch.testing.assert_close(after.inclusion[both], before.inclusion[both])
    torch.testing.assert_close(after.spread[both], before.spread[both])
    dropped = ~kept & was_kept
    assert bool((after.inclusion[dropped] == 0).all()) and bool((after.spread[dropped] == 0).all())
