"""The exact log marginal likelihood and its analytic gradient (torchmisspec.gp._mll) against autograd.

The reference differentiates log N(Y; 0, C(theta)) through ``torch.linalg.cholesky`` with autograd; the package's
gradient comes from Q = alpha alpha^T / s - m C^-1 and the surrogate 1/2 sum(Q * C(theta)). Both are compared for
the shared kernel (one covariance, m = d_out outputs) and per-output kernels (a batch of covariances), with and
without the profiled output scale.
"""

import math

import pytest
import torch

from torchmisspec.gp import _mll

DT = torch.float64


def _rbf(X, log_l, log_s):
    """Independent RBF formula, batched over leading dims of the hyperparameters: (B, N, N)."""
    d2 = torch.cdist(X, X).pow(2)
    return log_s.exp().reshape(-1, 1, 1) * torch.exp(-0.5 * d2 / log_l.exp().reshape(-1, 1, 1) ** 2)


def _reference_mll(K, diag, Y):
    """log N(Y_b[:, j]; 0, K_b + diag_b I) summed over b and j, with autograd through torch.linalg.cholesky."""
    B, N, m = Y.shape
    C = K + torch.diag_embed(diag.expand(B, N))
    L = torch.linalg.cholesky(C)
    alpha = torch.cholesky_solve(Y, L)
    logdet = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum()
    return -0.5 * (Y * alpha).sum() - 0.5 * m * logdet - 0.5 * N * B * m * math.log(2 * math.pi)


def _data(B, m, n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    Y = 0.1 * torch.randn(B, n, m, generator=g, dtype=DT) + torch.sin(3 * X[:, :1]).unsqueeze(0)
    return X, Y


@pytest.mark.parametrize(("B", "m"), [(1, 3), (3, 1)], ids=["shared", "per_output"])
def test_analytic_gradient_equals_autograd(B, m):
    X, Y = _data(B, m)
    log_l = torch.linspace(-0.6, 0.2, B, dtype=DT).requires_grad_(True)
    log_s = torch.linspace(-2.0, -1.0, B, dtype=DT).requires_grad_(True)
    log_noise = torch.linspace(-5.0, -4.0, B, dtype=DT).reshape(B, 1).requires_grad_(True)
    params = (log_l, log_s, log_noise)

    ref = _reference_mll(_rbf(X, log_l, log_s), log_noise.exp(), Y)
    ref_grad = torch.autograd.grad(ref, params)

    K, diag = _rbf(X, log_l, log_s), log_noise.exp()
    with torch.no_grad():
        fac = _mll.factorize(K.detach(), diag.detach(), Y)
        value = _mll.exact_mll(fac, X.shape[0])
        Q = _mll.gradient_weights(fac)
    grad = torch.autograd.grad(_mll.gradient_surrogate(Q, K, diag), params)

    assert float(value) == pytest.approx(float(ref.detach()), rel=1e-12)
    for g, r in zip(grad, ref_grad, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-8, atol=0)


@pytest.mark.parametrize(("B", "m"), [(1, 2), (1, 1), (2, 3)])
def test_profiled_likelihood_and_gradient_equal_autograd(B, m):
    """Profiled: C = s (R + g I) with s maximised out. Value = the full likelihood at s*; gradient = autograd of
    the profiled expression written out independently (s*(theta) differentiated through, not held fixed)."""
    X, Y = _data(B, m, seed=1)
    log_l = torch.tensor(-0.3, dtype=DT, requires_grad=True)
    log_g = torch.tensor(-3.0, dtype=DT, requires_grad=True)
    zero = torch.zeros((), dtype=DT)

    R = _rbf(X, log_l, zero).expand(B, -1, -1)
    g = log_g.exp().reshape(1, 1)
    # reference: s*(theta) = y^T (R + g I)^-1 y / (N B m), profiled value = full mll at s*, differentiated whole
    C = R + torch.diag_embed(g.expand(B, X.shape[0]))
    L = torch.linalg.cholesky(C)
    s_star = (Y * torch.cholesky_solve(Y, L)).sum() / Y.numel()
    ref = _reference_mll(s_star * R, s_star * g, Y)
    ref_grad = torch.autograd.grad(ref, (log_l, log_g))

    R = _rbf(X, log_l, zero).expand(B, -1, -1)  # a fresh graph for the package's gradient
    g = log_g.exp().reshape(1, 1)
    with torch.no_grad():
        fac = _mll.factorize(R.detach(), g.detach(), Y)
        value, scale = _mll.profiled_mll(fac)
        Q = _mll.gradient_weights(fac, scale)
    grad = torch.autograd.grad(_mll.gradient_surrogate(Q, R, g), (log_l, log_g))

    assert float(scale) == pytest.approx(float(s_star.detach()), rel=1e-12)
    assert float(value) == pytest.approx(float(ref.detach()), rel=1e-12)
    for a, b in zip(grad, ref_grad, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=0)


def test_profiled_scale_maximises_the_likelihood():
    X, Y = _data(1, 2, seed=2)
    R = _rbf(X, torch.tensor(-0.5, dtype=DT), torch.zeros((), dtype=DT))
    g = torch.full((1, 1), 1e-3, dtype=DT)
    value, scale = _mll.profiled_mll(_mll.factorize(R, g, Y))
    for factor in (0.9, 1.0, 1.1):
        full = _mll.exact_mll(_mll.factorize(factor * scale * R, factor * scale * g, Y), X.shape[0])
        assert float(full) <= float(value) + 1e-9 * abs(float(value))
        if factor == 1.0:
            assert float(full) == pytest.approx(float(value), rel=1e-10)


def test_per_sample_diagonal_matches_dense_reference():
    X, Y = _data(1, 2, seed=3)
    K = _rbf(X, torch.tensor(-0.4, dtype=DT), torch.tensor(-1.0, dtype=DT))
    diag = torch.linspace(1e-4, 1e-2, X.shape[0], dtype=DT).reshape(1, -1)
    fac = _mll.factorize(K, diag, Y)
    assert float(_mll.exact_mll(fac, X.shape[0])) == pytest.approx(float(_reference_mll(K, diag, Y)), rel=1e-12)
