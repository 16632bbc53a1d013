"""Posterior function samples (issue 10, point 1): pathwise conditioning against the exact joint posterior.

The sampler's draws are Gaussian in (prior weights, noise) given its random frequencies, with mean
k(x, X) C^-1 Y and covariance A A^T + B diag(s) B^T, where A = phi(x) - k(x, X) C^-1 phi(X) and B = k(x, X) C^-1.
The tests check (1) the Monte-Carlo moments of the draws against that conditional Gaussian (the implementation,
to Monte-Carlo error), and (2) the conditional moments against the exact posterior from a hand-written solve (the
feature approximation; exact for the polynomial kernel), for random and for quadrature Fourier features; and the
quadrature features' certified bound against the exact kernel on grids over its box.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp import _paths as paths
from torchmisspec.gp._paths import (
    QUADRATURE_FEATURE_ERROR,
    QUADRATURE_MARGIN,
    feature_map,
    frequencies_for,
    gauss_hermite_error,
    hermite_remainder,
    kernel_hyperparameters,
    kernel_matrix,
    quadrature_rule,
)

DT = torch.float64
CASES = [("rbf", {}), ("matern52", {}), ("polynomial", {"degree": 3}), ("rbf", {"per_output": True})]


@pytest.fixture(scope="module")
def data():
    g = torch.Generator().manual_seed(0)
    X = torch.rand(30, 2, generator=g, dtype=DT) * 2 - 1
    F = torch.stack([torch.sin(2 * X[:, 0]) * X[:, 1], X[:, 0] ** 2], -1)
    Y = F + 0.05 * torch.randn(30, 2, generator=g, dtype=DT)
    Xs = torch.rand(5, 2, generator=g, dtype=DT) * 3 - 1.5  # inside and outside the data's box
    return X, Y, Xs


@pytest.fixture(scope="module", params=CASES, ids=lambda c: c[0] + ("-per-output" if c[1].get("per_output") else ""))
def fitted(request, data):
    X, Y, _ = data
    kernel, options = request.param
    return tms.CorrectionGP(kernel=kernel, **options).fit(X, Y)


def exact_posterior(gp, X, Xs):
    """Mean (M, d_out) and covariance (B, M, M) of F at Xs by a hand-written solve (B = 1 or d_out)."""
    K, Kx, Kss = (
        t if t.dim() == 3 else t.unsqueeze(0) for t in (gp.covariance(X), gp.covariance(Xs, X), gp.covariance(Xs))
    )
    noise = torch.as_tensor(gp.noise_variance, dtype=DT).reshape(-1, 1, 1)
    C = K + noise * torch.eye(X.shape[0], dtype=DT)
    Y = gp.train_targets_
    if K.shape[0] == 1:
        mean = Kx[0] @ torch.linalg.solve(C[0], Y)
    else:
        mean = torch.einsum("bmn,bn->mb", Kx, torch.linalg.solve(C, Y.T.unsqueeze(-1)).squeeze(-1))
    return mean, Kss - Kx @ torch.linalg.solve(C, Kx.transpose(-1, -2)), C, Kx


def test_kernel_matrix_equals_the_gpytorch_kernel(fitted, data):
    X, _, Xs = data
    with torch.no_grad():
        ours = kernel_matrix(fitted.kernel_spec, Xs, X, kernel_hyperparameters(fitted), fitted.degree)
    theirs = fitted.covariance(Xs, X)
    assert torch.allclose(ours, theirs if theirs.dim() == 3 else theirs.unsqueeze(0), rtol=1e-12, atol=1e-14)


def test_polynomial_features_are_exact(data):
    X, Y, Xs = data
    gp = tms.CorrectionGP(kernel="polynomial", degree=3).fit(X, Y)
    phi = feature_map(gp)(Xs)[0]
    assert phi.shape[-1] == math.comb(3 + 2, 2)
    assert torch.allclose(phi @ phi.T, gp.covariance(Xs), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("kernel", ["rbf", "matern52"])
def test_fourier_features_meet_the_stated_bound(data, kernel):
    X, Y, _ = data
    gp = tms.CorrectionGP(kernel=kernel).fit(X, Y)
    box = torch.rand(200, 2, generator=torch.Generator().manual_seed(5), dtype=DT) * 2 - 1  # the data's box
    # random features: the Matern kernel's default (bound 0.05), the RBF kernel's when num_features is given
    options = {"num_features": 800} if kernel == "rbf" else {}
    fm = feature_map(gp, generator=torch.Generator().manual_seed(1), **options)
    assert fm.kind == "fourier" and fm.num_features == 2 * frequencies_for(0.05) == 800
    assert fm.error_bound == pytest.approx(0.05) and fm.box is None
    with torch.no_grad():
        phi = fm(box)[0]
        k = gp.covariance(box)
    rms = float((phi @ phi.T - k).pow(2).mean().sqrt()) / float(gp.outputscale)
    assert rms <= 0.05  # the bound is on the root mean square at every pair; measured: 0.02 (rbf), 0.01 (matern)
    assert torch.allclose((phi * phi).sum(-1), k.diagonal(), rtol=1e-12)  # exact prior variance at x = x'


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8, 13, 21, 34])
def test_gauss_hermite_error_bounds_the_one_dimensional_error(m):
    """e_m(rho) >= the measured error on a grid at least 40 times finer than the certification's, <= the
    closed-form remainder m! rho^2m / (2m)!, which is the error's leading term (tight for small rho: the constants
    are right)."""
    z, a = np.polynomial.hermite_e.hermegauss(m)
    a = a / a.sum()
    for rho in (0.1, 0.5, 1.0, 2.0, 4.0, 7.0):
        t = np.linspace(0.0, rho, 40001)
        measured = float(np.abs(np.cos(np.outer(t, z)) @ a - np.exp(-0.5 * t**2)).max())
        bound = gauss_hermite_error(m, rho)
        assert measured <= bound <= hermite_remainder(m, rho) + 1e-12  # plus rounding
        assert bound <= measured + 2e-5  # the grid certificate is tight (slack h^2 / 4 <= 1.6e-5)
    small = 0.2  # the error's series in rho^2 starts with m! rho^2m / (2m)!, the rest O(rho^2) smaller
    t = np.array([small])
    measured = float(np.abs(np.cos(np.outer(t, z)) @ a - np.exp(-0.5 * t**2)).max())
    if measured > 1e-13:
        assert 0.9 <= measured / hermite_remainder(m, small) <= 1.0 + 1e-6


def test_gauss_hermite_error_decreases_with_the_number_of_nodes():
    for rho in (0.5, 2.0, 4.0, 6.0, 9.0):
        bounds = [gauss_hermite_error(m, rho) for m in range(1, 81)]
        useful = [b for b in bounds if 1e-11 < b < 0.5]  # below 1e-11: the rounding allowance (grows with m)
        assert useful and all(b1 <= b0 for b0, b1 in zip(useful, useful[1:], strict=False))
        assert bounds[-1] < 1e-4


def box_grid(box: torch.Tensor, n: int = 41) -> torch.Tensor:
    """An n x n grid over a 2-D box, corners included (the largest differences r)."""
    axes = [torch.linspace(float(box[0, i]), float(box[1, i]), n, dtype=DT) for i in range(2)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)


@pytest.mark.parametrize("per_output", [False, True], ids=["shared", "per-output"])
@pytest.mark.parametrize("error", [None, 0.05, 1e-2, 1e-5])
def test_quadrature_features_meet_their_certified_bound_over_the_box(data, per_output, error):
    X, Y, _ = data
    gp = tms.CorrectionGP(per_output=per_output).fit(X, Y)
    fm = feature_map(gp, feature_error=error)
    target = QUADRATURE_FEATURE_ERROR if error is None else error
    assert fm.kind == "quadrature" and 0 < fm.error_bound <= target
    assert fm.num_features // 2 <= (frequencies_for(0.05) if error is None else math.ceil(1 / error**2))
    # the box: the data's box widened by QUADRATURE_MARGIN times its width on each side
    lo, hi = X.amin(0), X.amax(0)
    assert torch.allclose(fm.box[0], lo - QUADRATURE_MARGIN * (hi - lo))
    assert torch.allclose(fm.box[1], hi + QUADRATURE_MARGIN * (hi - lo))
    grid = box_grid(fm.box)
    with torch.no_grad():
        phi = fm(grid)  # (B, M, F)
        k = gp.covariance(grid)
    k = k if k.dim() == 3 else k.unsqueeze(0)
    s2 = torch.as_tensor(gp.outputscale, dtype=DT).reshape(-1, 1, 1)
    err = ((phi @ phi.transpose(-1, -2) - k).abs() / s2).amax(dim=(-1, -2))  # per output
    assert phi.shape[0] == (2 if per_output else 1)
    assert float(err.max()) <= fm.error_bound
    # measured: within a factor 2-3.5 of the bound (the sum over dimensions of 1-D worst cases)
    assert float(err.max()) >= fm.error_bound / 50
    diag = (phi * phi).sum(-1)  # exact prior variance at x = x' (the pruned weights are renormalized)
    assert torch.allclose(diag, k.diagonal(dim1=-2, dim2=-1), rtol=1e-12)


def test_quadrature_bound_falls_as_its_rules_grow(data):
    """Tighter targets: more frequency pairs, smaller bounds, weights summing to 1 (the data's widened box)."""
    X, Y, _ = data
    gp = tms.CorrectionGP().fit(X, Y)
    rho = [3 * float(w) / gp.lengthscale for w in X.amax(0) - X.amin(0)]
    pairs, bounds = [], []
    for error in (0.3, 0.1, 1e-2, 1e-3, 1e-4, 1e-6, 1e-8):
        Z, c, bound = quadrature_rule(rho, error)
        assert bound <= error and Z.shape == (len(c), 2) and abs(c.sum() - 1) < 1e-12 and (c > 0).all()
        pairs.append(len(c))
        bounds.append(bound)
    assert pairs == sorted(pairs) and pairs[0] < pairs[-1]
    assert bounds == sorted(bounds, reverse=True)
    assert quadrature_rule([40.0, 40.0], 1e-3) is None  # too rough for 128 nodes per dimension


def test_the_choice_of_features(data):
    X, Y, _ = data
    gp = tms.CorrectionGP().fit(X, Y)
    # low input dimension, RBF: quadrature (fewer pairs than random features, a uniform bound 1e-2)
    fm = feature_map(gp)
    assert fm.kind == "quadrature" and fm.num_features <= 200 and fm.error_bound <= 1e-2
    assert feature_map(gp, feature_error=1e-3).kind == "quadrature"  # random features would need 10^6 pairs
    # num_features given: random features, as before
    fm = feature_map(gp, num_features=64, generator=torch.Generator().manual_seed(0))
    assert fm.kind == "fourier" and fm.num_features == 64 and fm.error_bound == pytest.approx(32**-0.5)
    # Matern 5/2: random features
    assert feature_map(tms.CorrectionGP(kernel="matern52").fit(X, Y)).kind == "fourier"
    # high input dimension: the tensor grid needs more pairs than random features; they are used
    g = torch.Generator().manual_seed(3)
    X8 = torch.rand(60, 8, generator=g, dtype=DT) * 2 - 1
    Y8 = torch.stack([torch.sin(X8.sum(-1)), X8[:, 0] * X8[:, 1]], -1)
    Y8 = Y8 + 0.05 * torch.randn(60, 2, generator=g, dtype=DT)
    gp8 = tms.CorrectionGP(lengthscale=1.0).fit(X8, Y8)
    fm8 = feature_map(gp8)
    assert fm8.kind == "fourier" and fm8.num_features == 800
    with pytest.raises(tms.InputError, match=r"feature_error: 0.001 needs 1000000 frequency pairs"):
        feature_map(gp8, feature_error=1e-3)
    # the same data in 2 of the 8 inputs' span: the quadrature again
    assert feature_map(tms.CorrectionGP(lengthscale=1.0).fit(X8[:, :2], Y8)).kind == "quadrature"


def conditional_moments(gp, samples, X, Xs):
    """The sampler's exact mean and covariance given its frequencies (see the module docstring)."""
    mean, _, C, Kx = exact_posterior(gp, X, Xs)
    phi_s, phi_X = samples.features(Xs), samples.features(X)  # (B, M, F), (B, N, F)
    Bm = Kx @ torch.linalg.inv(C)  # (B, M, N)
    A = phi_s - Bm @ phi_X
    noise = torch.as_tensor(gp.noise_variance, dtype=DT).reshape(-1, 1, 1)
    return mean, A @ A.transpose(-1, -2) + noise * Bm @ Bm.transpose(-1, -2)


@pytest.mark.parametrize("features", ["random", "default"])
def test_draws_match_their_conditional_gaussian_to_monte_carlo_error(fitted, data, features):
    X, _, Xs = data
    S = 4000
    if features == "default" and fitted.kernel != "rbf":
        pytest.skip("the default features of this kernel are the random (Matern) or exact (polynomial) ones")
    options = {} if fitted.kernel == "polynomial" or features == "default" else {"num_features": 512}
    samples = fitted.sample_functions(S, generator=torch.Generator().manual_seed(1), **options)
    assert samples.features.kind == {"rbf": "quadrature", "polynomial": "polynomial"}.get(
        fitted.kernel if features == "default" or fitted.kernel == "polynomial" else "", "fourier"
    )
    f = samples(Xs)  # (S, M, d_out)
    assert f.shape == (S, 5, 2) and not f.requires_grad
    assert torch.equal(samples(Xs), f)  # one function per draw: evaluated again, the same values
    assert torch.equal(samples(Xs.expand(S, -1, -1)), f)
    mean, cov = conditional_moments(fitted, samples, X, Xs)
    for j in range(2):
        c = cov[0] if cov.shape[0] == 1 else cov[j]
        sd = c.diagonal().sqrt()
        z_mean = (f[:, :, j].mean(0) - mean[:, j]) / (sd / math.sqrt(S))
        emp = torch.cov(f[:, :, j].T)
        mc_sd = ((c.diagonal().unsqueeze(0) * c.diagonal().unsqueeze(1) + c.pow(2)) / S).sqrt()
        z_cov = (emp - c) / mc_sd
        assert float(z_mean.abs().max()) < 4.5 and float(z_cov.abs().max()) < 4.5


@pytest.mark.parametrize("features", ["random", "default", "quadrature", "tight"])
def test_conditional_moments_approach_the_exact_posterior(fitted, data, features):
    X, _, Xs = data
    if features != "random" and fitted.kernel != "rbf":
        pytest.skip("quadrature features are the RBF kernel's")
    options = {
        "random": {} if fitted.kernel == "polynomial" else {"num_features": 2 * 8192},
        "default": {},
        "quadrature": {"feature_error": 1e-3},
        "tight": {"feature_error": 1e-6},
    }[features]
    samples = fitted.sample_functions(1, generator=torch.Generator().manual_seed(2), **options)
    mean, cov = conditional_moments(fitted, samples, X, Xs)
    _, exact, _, _ = exact_posterior(fitted, X, Xs)
    err = float((cov - exact).abs().max() / exact.diagonal(dim1=-2, dim2=-1).max())
    # relative to the largest posterior variance (~0.4-2 % of the prior's here): the polynomial features are exact;
    # with 8192 random frequency pairs, measured 0.025-0.054; the quadrature at a bound of 1e-3 of the prior
    # variance (34-77 pairs) 0.02-0.026; at 1e-6 (79-174 pairs), 5e-5; the default bound 1e-2, 0.08-0.13
    limit = {"random": 1e-8 if fitted.kernel == "polynomial" else 0.1, "default": 0.2, "quadrature": 0.05}
    limit = limit.get(features, 1e-4)
    assert err < limit


@pytest.mark.parametrize("options", [{}, {"num_features": 64}, {"update_error": 1e-2}])
def test_the_hot_path_matches_the_general_evaluation(data, options, monkeypatch):
    """Shared RBF kernel with Fourier features: buffers in the (draws, features, points) layout, the kernel block
    from one augmented product; the same function as the general path (to rounding), in chunks of draws or of
    points, and the general path with autograd."""
    X, Y, _ = data
    g = torch.Generator().manual_seed(11)
    Xd = torch.rand(200, 2, generator=g, dtype=DT) * 2 - 1  # dense enough for the update to be compressed
    Yd = torch.stack([torch.sin(2 * Xd[:, 0]) * Xd[:, 1], Xd[:, 0] ** 2], -1) + 0.05 * torch.randn(
        200, 2, generator=g, dtype=DT
    )
    gp = tms.CorrectionGP().fit(Xd, Yd)
    x = torch.rand(6, 50, 2, generator=g, dtype=DT) * 4 - 2  # inside and outside the data's box
    samples = gp.sample_functions(6, generator=torch.Generator().manual_seed(3), **options)
    fast = samples(x)
    assert samples._fast and fast.shape == (6, 50, 2) and fast.is_contiguous()
    if "update_error" in options:
        assert samples.update_error > 0
    samples._fast = False  # the general path
    general = samples(x)
    tol = 1e-10 * float(general.abs().max())
    assert float((fast - general).abs().max()) <= tol
    monkeypatch.setattr(paths, "_HOT_CHUNK", 100)  # one draw and a few points per chunk
    samples._fast = None
    assert float((samples(x) - general).abs().max()) <= tol
    assert torch.equal(samples(x[0]), samples(x[0].expand(6, -1, -1)))
    xg = x.clone().requires_grad_(True)
    out = samples(xg)  # autograd: the general path
    assert out.requires_grad and float((out.detach() - general).abs().max()) <= tol
    out.sum().backward()
    assert xg.grad is not None and bool(torch.isfinite(xg.grad).all())
    # per-output kernels and the Matern kernel: the general path
    for other in (tms.CorrectionGP(per_output=True).fit(X, Y), tms.CorrectionGP(kernel="matern52").fit(X, Y)):
        draws = other.sample_functions(2, num_features=16)
        draws(x[:2])
        assert draws._fast is False


@pytest.mark.parametrize("per_output", [False, True], ids=["shared", "per-output"])
def test_scaled_draws_are_the_mean_plus_scaled_deviations(data, per_output):
    """scale c: mu + c (F_s - mu) with the same random numbers, for c < 1 and c > 1."""
    X, Y, Xs = data
    gp = tms.CorrectionGP(per_output=per_output).fit(X, Y)
    x = torch.cat([Xs, X[:3]])
    base = gp.sample_functions(5, generator=torch.Generator().manual_seed(7))
    assert base.scale == 1.0
    mu = gp.predict_mean(x)
    for c in (0.5, 2.0):
        scaled = paths.FunctionSamples(gp, 5, base.features, torch.Generator().manual_seed(7), scale=c)
        assert scaled.scale == c
        expected = mu + c * (base(x) - mu)
        assert torch.allclose(scaled(x), expected, rtol=1e-9, atol=1e-10 * float(expected.abs().max()))


def test_bad_arguments(data):
    X, Y, _ = data
    gp = tms.CorrectionGP().fit(X, Y)
    for bad in (0, -1, 2.5, "3"):
        with pytest.raises(tms.InputError, match="num_samples"):
            gp.sample_functions(bad)
    with pytest.raises(tms.InputError, match=r"num_features: expected an even number"):
        gp.sample_functions(2, num_features=5)
    with pytest.raises(tms.InputError, match=r"expected one of them, got both"):
        gp.sample_functions(2, num_features=8, feature_error=0.1)
    with pytest.raises(tms.InputError, match=r"feature_error: 0.001 needs 1000000 frequency pairs"):
        tms.CorrectionGP(kernel="matern52").fit(X, Y).sample_functions(2, feature_error=1e-3)
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(tms.InputError, match=r"feature_error"):
            gp.sample_functions(2, feature_error=bad)
    with pytest.raises(tms.InputError, match=r"generator: expected a torch.Generator or None, got int"):
        gp.sample_functions(2, generator=3)
    poly = tms.CorrectionGP(kernel="polynomial").fit(X, Y)
    with pytest.raises(tms.InputError, match=r"polynomial kernel has exact finite features"):
        poly.sample_functions(2, num_features=8)
    with pytest.raises(tms.NotFittedError):
        tms.CorrectionGP().sample_functions(2)
    samples = gp.sample_functions(3, num_features=8)
    with pytest.raises(tms.ShapeError, match=r"x: expected \(M, 2\) or \(3, M, 2\) inputs, got \(4, 5, 2\)"):
        samples(torch.zeros(4, 5, 2, dtype=DT))


@pytest.mark.parametrize("kernel", ["rbf", "matern52"])
def test_compressed_update_stays_within_its_certified_bound(data, kernel):
    _, _, Xs = data
    g = torch.Generator().manual_seed(9)
    X = torch.rand(300, 2, generator=g, dtype=DT) * 2 - 1  # dense: far fewer basis points are needed
    Y = torch.stack([torch.sin(2 * X[:, 0]) * X[:, 1], X[:, 0] ** 2], -1) + 0.05 * torch.randn(
        300, 2, generator=g, dtype=DT
    )
    gp = tms.CorrectionGP(kernel=kernel).fit(X, Y)
    exact = gp.sample_functions(64, num_features=64, generator=torch.Generator().manual_seed(4))
    points = torch.cat([Xs, X[:5], 3 * Xs])  # at the data, between, and far away
    sd = float(gp.outputscale) ** 0.5
    compressed = 0
    for target in (1e-1, 1e-2, 1e-3, 1e-5):
        small = gp.sample_functions(
            64, num_features=64, generator=torch.Generator().manual_seed(4), update_error=target
        )
        diff = float((small(points) - exact(points)).abs().max())
        if small.update_error > 0:  # compressed: within the requested bound, and the bound holds
            compressed += 1
            assert small.update_error <= target * sd and small._X.shape[0] < X.shape[0]
            assert diff <= small.update_error
        else:  # the bound cannot be certified with fewer points: the exact basis is kept
            assert small._X.shape[0] == X.shape[0] and diff == 0.0
    # the RBF's eigenvalues decay fast: 56 of 300 points certify 1e-2 (measured); Matern 5/2's decay slowly
    assert compressed >= (2 if kernel == "rbf" else 1)
    with pytest.raises(tms.InputError, match="update_error"):
        gp.sample_functions(2, update_error=-1.0)


def test_sampled_functions_follow_the_models_dtype():
    """Sampled functions evaluated at float32 inputs of a float64 model raised a bare dtype error."""
    g = torch.Generator().manual_seed(0)
    X = torch.rand(30, 2, generator=g, dtype=torch.float64)
    gp = tms.CorrectionGP().fit(X, torch.sin(3 * X) + 0.01 * torch.randn(30, 2, generator=g, dtype=torch.float64))
    f = gp.sample_functions(4, generator=torch.Generator().manual_seed(1))
    x = torch.rand(5, 2, generator=g, dtype=torch.float64)
    torch.testing.assert_close(f(x.float()), f(x.float().double()))
    with pytest.raises(tms.InputError, match="x: expected a floating-point tensor"):
        f(torch.ones(5, 2, dtype=torch.long))
