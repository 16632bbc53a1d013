"""Posterior function samples (issue 10, point 1): pathwise conditioning against the exact joint posterior.

The sampler's draws are Gaussian in (prior weights, noise) given its random frequencies, with mean
k(x, X) C^-1 Y and covariance A A^T + B diag(s) B^T, where A = phi(x) - k(x, X) C^-1 phi(X) and B = k(x, X) C^-1.
The tests check (1) the Monte-Carlo moments of the draws against that conditional Gaussian (the implementation,
to Monte-Carlo error), and (2) the conditional moments against the exact posterior from a hand-written solve (the
feature approximation; exact for the polynomial kernel).
"""

from __future__ import annotations

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._paths import feature_map, frequencies_for, kernel_hyperparameters, kernel_matrix

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
        ours = kernel_matrix(fitted.kernel, Xs, X, kernel_hyperparameters(fitted), fitted.degree)
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
    fm = feature_map(gp, generator=torch.Generator().manual_seed(1))  # default bound 0.05
    assert fm.num_features == 2 * frequencies_for(0.05) == 800
    with torch.no_grad():
        phi = fm(box)[0]
        k = gp.covariance(box)
    rms = float((phi @ phi.T - k).pow(2).mean().sqrt()) / float(gp.outputscale)
    assert rms <= 0.05  # the bound is on the root mean square at every pair; measured: 0.02 (rbf), 0.01 (matern)
    assert torch.allclose((phi * phi).sum(-1), k.diagonal(), rtol=1e-12)  # exact prior variance at x = x'


def conditional_moments(gp, samples, X, Xs):
    """The sampler's exact mean and covariance given its frequencies (see the module docstring)."""
    mean, _, C, Kx = exact_posterior(gp, X, Xs)
    phi_s, phi_X = samples.features(Xs), samples.features(X)  # (B, M, F), (B, N, F)
    Bm = Kx @ torch.linalg.inv(C)  # (B, M, N)
    A = phi_s - Bm @ phi_X
    noise = torch.as_tensor(gp.noise_variance, dtype=DT).reshape(-1, 1, 1)
    return mean, A @ A.transpose(-1, -2) + noise * Bm @ Bm.transpose(-1, -2)


def test_draws_match_their_conditional_gaussian_to_monte_carlo_error(fitted, data):
    X, _, Xs = data
    S = 4000
    options = {} if fitted.kernel == "polynomial" else {"num_features": 512}
    samples = fitted.sample_functions(S, generator=torch.Generator().manual_seed(1), **options)
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


def test_conditional_moments_approach_the_exact_posterior(fitted, data):
    X, _, Xs = data
    options = {} if fitted.kernel == "polynomial" else {"num_features": 2 * 8192}
    samples = fitted.sample_functions(1, generator=torch.Generator().manual_seed(2), **options)
    mean, cov = conditional_moments(fitted, samples, X, Xs)
    _, exact, _, _ = exact_posterior(fitted, X, Xs)
    err = float((cov - exact).abs().max() / exact.diagonal(dim1=-2, dim2=-1).max())
    # relative to the largest posterior variance (~0.4-2 % of the prior's here): the polynomial features are exact;
    # with 8192 frequency pairs, measured 0.025-0.054
    assert err < (1e-8 if fitted.kernel == "polynomial" else 0.1)


def test_bad_arguments(data):
    X, Y, _ = data
    gp = tms.CorrectionGP().fit(X, Y)
    for bad in (0, -1, 2.5, "3"):
        with pytest.raises(tms.InputError, match="num_samples"):
            gp.sample_functions(bad)
    with pytest.raises(tms.InputError, match=r"num_features: expected an even number"):
        gp.sample_functions(2, num_features=5)
    with pytest.raises(tms.InputError, match=r"pass one of them, not both"):
        gp.sample_functions(2, num_features=8, feature_error=0.1)
    with pytest.raises(tms.InputError, match=r"feature_error: 0.001 needs 1000000 frequency pairs"):
        gp.sample_functions(2, feature_error=1e-3)
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
