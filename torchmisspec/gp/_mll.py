"""The exact log marginal likelihood of independent outputs sharing one covariance, and its analytic gradient.

Notation: C = K + diag(s) is an ``(B, N, N)`` batch of covariances (B = 1 for the shared kernel, B = d_out for
per-output kernels), Y the targets arranged as ``(B, N, m)`` (m outputs share each covariance), alpha = C^-1 Y.
The diagonal s is one noise variance per covariance ``(B, 1)``, or per sample ``(B, N)`` with known noise:
s_i = known_i + floor (``(1, N)`` when the known noise is the same for every output, else B = d_out with the shared
kernel expanded). Everything below holds for either diagonal, except the profiled output scale.

    log p(Y) = -1/2 sum(Y * alpha) - (m / 2) sum_b logdet C_b - (N B m / 2) log(2 pi)

**Analytic gradient.** For any hyperparameter theta of C, d log p / d theta = 1/2 sum(Q * dC/dtheta) with
Q = alpha alpha^T - m C^-1 (summed over the m outputs). Q comes from one Cholesky factor, so autograd only has to
differentiate the cheap O(N^2) surrogate ``1/2 sum(Q.detach() * C(theta))`` (:func:`gradient_surrogate`), never the
O(N^3) factorization.

**Profiled output scale** (only without known noise: known variances do not scale with the output scale). With
C = s (R + g I) (unit-scale kernel R, noise ratio g) the likelihood is maximised over s in closed form,
s* = sum(Y * alpha) / (N B m) with alpha = (R + g I)^-1 Y, leaving

    log p_prof = -(N B m / 2) (log(2 pi s*) + 1) - (m / 2) sum_b logdet(R_b + g I),

whose gradient (envelope theorem) is 1/2 sum(Q * d(R + g I)/dtheta) with Q = alpha alpha^T / s* - m (R + g I)^-1.

These are pure functions of tensors; tests compare them with autograd through ``torch.linalg.cholesky``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .._linalg import cholesky, logdet_from_cholesky

__all__ = ["Factorization", "factorize", "exact_mll", "profiled_mll", "gradient_weights", "gradient_surrogate"]


class Factorization(NamedTuple):
    """One factorization of C = K + diag (batch ``(B, N, N)``) and the solve against the targets.

    Attributes:
        chol: ``(B, N, N)`` lower Cholesky factor of C.
        alpha: ``(B, N, m)`` C^-1 Y.
        logdet: scalar, sum over the batch of logdet C_b.
        quad: scalar, sum(Y * alpha).
    """

    chol: torch.Tensor
    alpha: torch.Tensor
    logdet: torch.Tensor
    quad: torch.Tensor


def factorize(
    K: torch.Tensor, diag: torch.Tensor, Y: torch.Tensor, *, what: str = "K + noise_variance * I", warn: bool = True
) -> Factorization:
    """Factorize ``C = K + diag`` once and solve against ``Y``.

    Args:
        K: ``(B, N, N)`` kernel matrices.
        diag: ``(B, 1)`` (one value per batch) or ``(B, N)`` (one per sample): added to the diagonal.
        Y: ``(B, N, m)`` targets.
    """
    C = K + torch.diag_embed(diag.expand(K.shape[0], K.shape[-1]))
    L = cholesky(C, what=what, warn=warn)
    alpha = torch.cholesky_solve(Y, L)
    return Factorization(L, alpha, logdet_from_cholesky(L).sum(), (Y * alpha).sum())


def exact_mll(fac: Factorization, num_samples: int) -> torch.Tensor:
    """Exact log marginal likelihood (nats, summed over outputs) from a :class:`Factorization`."""
    B, N, m = fac.alpha.shape
    return -0.5 * fac.quad - 0.5 * m * fac.logdet - 0.5 * N * B * m * math.log(2 * math.pi)


def profiled_mll(fac: Factorization) -> tuple[torch.Tensor, torch.Tensor]:
    """Log marginal likelihood with the output scale maximised out, from a factorization of ``R + g I``.

    Returns ``(log p_prof, s*)``; the covariance at the optimum is ``s* (R + g I)``.
    """
    B, N, m = fac.alpha.shape
    n = N * B * m
    scale = fac.quad / n
    return -0.5 * n * (torch.log(2 * math.pi * scale) + 1.0) - 0.5 * m * fac.logdet, scale


def gradient_weights(fac: Factorization, scale: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Q = alpha alpha^T / scale - m C^-1 ``(B, N, N)``: d log p / dC = Q / 2 (``scale`` = s* when profiling)."""
    m = fac.alpha.shape[-1]
    Q = torch.cholesky_inverse(fac.chol).mul_(-m)
    return Q.add_(fac.alpha @ fac.alpha.transpose(-1, -2), alpha=1.0 / float(scale))


def gradient_surrogate(Q: torch.Tensor, K: torch.Tensor, diag: torch.Tensor) -> torch.Tensor:
    """``1/2 sum(Q * C)`` with ``C = K + diag``: its gradient in the hyperparameters of K and diag is d log p.

    ``Q`` must be detached; ``K (B, N, N)`` and ``diag`` (``(B, 1)`` or ``(B, N)``) carry the autograd graph.
    """
    q_diag = Q.diagonal(dim1=-2, dim2=-1)
    return 0.5 * (Q * K).sum() + 0.5 * (q_diag * diag).sum()
