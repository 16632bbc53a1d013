"""The one factorization layer: jitter only when needed, and then a warning that says how much; NaN refused."""

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec import _linalg

DT = torch.float64


def test_plain_factorization_is_exact_and_silent():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(6, 6, generator=g, dtype=DT)
    A = A @ A.T + 6 * torch.eye(6, dtype=DT)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        L = _linalg.cholesky(A)
    torch.testing.assert_close(L, torch.linalg.cholesky(A), rtol=0, atol=0)
    assert float(_linalg.logdet_from_cholesky(L)) == pytest.approx(float(torch.logdet(A)), rel=1e-12)


def test_jitter_is_announced_with_its_size():
    x = torch.ones(4, 1, dtype=DT)
    with pytest.warns(
        tms.NumericalWarning,
        match=r"rank-one: not numerically positive definite \(size 4\); added "
        r"jitter 1\.00e-10 \(1e-10 x its mean diagonal\)",
    ):
        L = _linalg.cholesky(x @ x.T, what="rank-one")
    torch.testing.assert_close(L @ L.T, x @ x.T + 1e-10 * torch.eye(4, dtype=DT), rtol=0, atol=1e-15)


def test_nan_and_indefinite_matrices_raise_linear_algebra_errors():
    A = torch.eye(3, dtype=DT)
    A[1, 2] = float("nan")
    with pytest.raises(tms.LinearAlgebraError, match=r"K: expected a finite matrix to factorize, got 1 NaN/inf"):
        _linalg.cholesky(A, what="K")
    indefinite = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=DT)
    with pytest.raises(tms.NotPositiveDefiniteError, match="failed even with jitter") as info:
        _linalg.cholesky(indefinite)
    # a linear-algebra error, not a fitting error: the design raises it too
    assert isinstance(info.value, tms.LinearAlgebraError) and not isinstance(info.value, tms.FittingError)


def test_logdet_identity_plus_matches_torch():
    g = torch.Generator().manual_seed(1)
    B = torch.randn(3, 5, 5, generator=g, dtype=DT)
    cov = B @ B.transpose(-1, -2)
    ld, L = _linalg.logdet_identity_plus(cov, 0.3, "cov")
    torch.testing.assert_close(ld, torch.logdet(torch.eye(5, dtype=DT) + cov / 0.3), rtol=1e-12, atol=0)
    assert L.shape == (3, 5, 5)


def test_fit_warns_when_its_final_factorization_needs_jitter():
    X = torch.rand(5, 2, generator=torch.Generator().manual_seed(2), dtype=DT).repeat(20, 1)
    Y = torch.sin(X.sum(-1, keepdim=True)).repeat(1, 2)
    with pytest.warns(tms.NumericalWarning, match=r"K \+ noise_variance \* I: not numerically positive definite"):
        tms.CorrectionGP(lengthscale=0.5, outputscale=1e4, noise_variance=2e-12).fit(X, Y)


def test_warnings_point_at_the_callers_line():
    X = torch.rand(5, 2, generator=torch.Generator().manual_seed(2), dtype=DT).repeat(20, 1)
    Y = torch.sin(X.sum(-1, keepdim=True)).repeat(1, 2)
    with pytest.warns(tms.NumericalWarning) as record:
        tms.CorrectionGP(lengthscale=0.5, outputscale=1e4, noise_variance=2e-12).fit(X, Y)
    assert {w.filename for w in record} == {__file__}


def test_cholesky_or_fail_marks_failures_and_keeps_solves_finite():
    good = torch.eye(2, dtype=DT) * 2
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=DT)
    L, failed = _linalg.cholesky_or_fail(torch.stack([good, bad]))
    assert failed.tolist() == [False, True]
    torch.testing.assert_close(L[0], torch.linalg.cholesky(good), rtol=0, atol=0)
    torch.testing.assert_close(L[1], torch.eye(2, dtype=DT), rtol=0, atol=0)
