"""The one linear-algebra layer: every factorization in the package goes through :func:`cholesky`.

* :func:`cholesky` refuses non-finite matrices (:class:`LinearAlgebraError`), adds growing jitter only when the plain
  factorization fails, and then says so with a :class:`NumericalWarning` that names the matrix and the jitter (as
  linear_operator's ``psd_safe_cholesky`` does); it raises :class:`NotPositiveDefiniteError` when even the largest
  jitter fails.
* :func:`logdet_from_cholesky`, :func:`logdet_identity_plus`: log-determinants from a factor.
"""

from __future__ import annotations

import math

import torch

from ._errors import LinearAlgebraError, NotPositiveDefiniteError
from ._errors import warn as warn_user

__all__ = ["cholesky", "cholesky_or_fail", "logdet_from_cholesky", "logdet_identity_plus", "JITTER_RANGE"]

#: jitter tried, relative to the mean absolute diagonal: 1e-10, 1e-9, ..., 1e-5
JITTER_RANGE = (-10, -5)


def cholesky(A: torch.Tensor, *, what: str = "covariance", warn: bool = True) -> torch.Tensor:
    """Lower Cholesky factor of ``A (..., n, n)``, with jitter only when needed.

    Args:
        A: symmetric positive (semi-)definite matrices.
        what: the matrix's name, used in warnings and errors.
        warn: issue a :class:`NumericalWarning` when jitter had to be added.

    Raises:
        LinearAlgebraError: ``A`` has NaN or inf entries.
        NotPositiveDefiniteError: the factorization fails even with jitter ``1e-5 * mean |diag A|``.
    """
    if not bool(torch.isfinite(A).all()):
        n_bad = int((~torch.isfinite(A)).sum())
        raise LinearAlgebraError(
            f"{what}: expected a finite matrix to factorize, got {n_bad} NaN/inf entries of {A.numel()} (shape "
            f"{tuple(A.shape)}); check the hyperparameters and the scale of the data"
        )
    L, info = torch.linalg.cholesky_ex(A)
    if not bool((info != 0).any()):
        return L
    scale = A.diagonal(dim1=-2, dim2=-1).abs().mean().clamp_min(torch.finfo(A.dtype).tiny)
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    lo, hi = JITTER_RANGE
    for exponent in range(lo, hi + 1):
        jitter = scale * 10.0**exponent
        L, info = torch.linalg.cholesky_ex(A + jitter * eye)
        if not bool((info != 0).any()):
            if warn:
                warn_user(
                    f"{what}: not numerically positive definite (size {A.shape[-1]}); added jitter "
                    f"{float(jitter):.2e} (1e{exponent} x its mean diagonal) to factorize it. Results are "
                    "approximate: raise the noise variance or remove repeated inputs"
                )
            return L
    raise NotPositiveDefiniteError(
        f"{what}: expected a positive definite matrix of size {A.shape[-1]}, but its Cholesky factorization failed "
        f"even with jitter {float(jitter):.1e} added to the diagonal (is the noise variance zero with repeated "
        "inputs?); use a larger noise_variance or remove duplicate inputs"
    )


def cholesky_or_fail(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower factors of a batch ``A (..., n, n)`` without jitter, and which matrices failed ``(...)`` (bool).

    For searches over hyperparameters where a failed candidate is simply discarded: the failed entries' factors are
    the identity (so later solves stay finite), and the caller gives those candidates an infinite cost.
    """
    L, info = torch.linalg.cholesky_ex(A)
    failed = info != 0
    if bool(failed.any()):
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        L = torch.where(failed[..., None, None], eye, L)
    return L, failed


def logdet_from_cholesky(L: torch.Tensor) -> torch.Tensor:
    """log det(A) from its lower factor ``L (..., n, n)``: ``(...)``."""
    return 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)


def logdet_identity_plus(
    cov: torch.Tensor, noise: float, what: str, *, warn: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log det(I + cov / noise), L)`` for ``cov (..., m, m)``; L is the Cholesky factor of ``I + cov / noise``."""
    m = cov.shape[-1]
    A = cov / noise
    A.diagonal(dim1=-2, dim2=-1).add_(1.0)
    L = cholesky(A, what=what, warn=warn)
    if m == 0:
        return cov.new_zeros(cov.shape[:-2]), L
    return logdet_from_cholesky(L), L


def pivots(kern, X: torch.Tensor, max_rank: int, tol: float, *, factor: bool = False) -> tuple:
    """Greedy pivoted Cholesky of a kernel ``kern`` (``kern(A, B)`` a block, ``kern.diag(A)`` its diagonal) on the
    points ``X (M, d_in)``: up to ``max_rank`` pivot indices (the design's screening and data term, and the Nystrom
    features of :mod:`torchmisspec.gp._large`, use this one).

    Stops when the largest residual variance is at most ``tol``. Returns the pivots and that largest residual, and
    with ``factor`` the rows ``R (r, M)`` of the partial factor (K(X, X) ~ R^T R; ``R[:, pivots]`` is upper
    triangular with ``R[:, pivots]^T R[:, pivots] = K(Z, Z)``).
    """
    M = X.shape[0]
    resid = kern.diag(X).clone()
    R = X.new_empty(min(max_rank, M), M)
    piv = []
    for i in range(R.shape[0]):
        j = int(torch.argmax(resid))
        dj = float(resid[j])
        if dj <= tol:
            break
        col = kern(X[j : j + 1], X)[0]
        if i:
            col = col - R[:i, j] @ R[:i]
        if float(col[j]) < 0.5 * dj:  # the residual is round-off: further pivots would only add noise
            break
        R[i] = col / math.sqrt(dj)
        R[i, j] = math.sqrt(dj)  # consistent with the residual the pivot was chosen by
        resid -= R[i] ** 2
        resid[j] = 0.0
        piv.append(j)
    out = torch.tensor(piv, dtype=torch.long, device=X.device), float(resid.max())
    return (*out, R[: len(piv)]) if factor else out
