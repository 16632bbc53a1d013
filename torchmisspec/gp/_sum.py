"""The sum of a feature library and an RBF kernel: a sparse polynomial correction plus a smooth remainder.

    k(x, x') = sum_j w_j phi_j(x) phi_j(x') + a exp(-||x - x'||^2 / (2 l^2))

The monomials ``phi_j`` (up to ``degree``, one weight ``w_j >= 0`` each: automatic relevance) capture what a low-degree
polynomial explains, and the RBF term (output scale ``a``, lengthscale ``l``) what the library misses. With ``a -> 0``
it is the feature kernel, with every ``w_j -> 0`` the RBF kernel, so the marginal likelihood decides between them.

Fitting (:func:`fit_sum`): every hyperparameter (the weights, ``a``, ``l`` and the noise floor unless fixed) maximises
the exact log marginal likelihood, by L-BFGS in log space with autograd through one Cholesky factorization per
evaluation (O(N^3): the RBF term has no finite features). It starts from the feature kernel's sparse Bayesian fit
(:func:`~torchmisspec.gp._relevance.fit_relevance`); weights whose share of the prior variance falls below
:data:`PRUNE_SUM` of the targets' second moment are then set to exactly 0 (the term removed).
"""

from __future__ import annotations

import math

import gpytorch
import torch

from .._errors import FittingError, LinearAlgebraError
from .._linalg import cholesky_or_fail
from .._optim import maximise
from . import _mll
from ._exact import median_distance
from ._features import FeatureKernel
from ._relevance import fit_relevance, noise_groups, term_gain

__all__ = ["FeaturesPlusRBF", "fit_sum", "PRUNE_SUM"]

#: A monomial is removed when ``w_j mean(phi_j^2)`` falls below this fraction of the targets' second moment. Log-space
#: gradients shrink irrelevant weights only slowly towards 0, so the threshold is larger than the feature kernel's.
PRUNE_SUM = 1e-8
_LOG_FLOOR = math.log(1e-14)  # weights below this share (relative, log) stop moving: they are pruned anyway


class FeaturesPlusRBF(gpytorch.kernels.Kernel):
    """``sum_j w_j x^a_j x'^a_j + a exp(-||x - x'||^2 / (2 l^2))``; shared by the outputs (no batch)."""

    is_stationary = False

    def __init__(self, d_in: int, degree: int, library=None, library_names=None, **kwargs) -> None:
        super().__init__(**kwargs)
        self.features_kernel = FeatureKernel(d_in, degree, library=library, library_names=library_names)
        positive = gpytorch.constraints.GreaterThan(0.0, transform=torch.exp, inv_transform=torch.log)
        self.rbf = gpytorch.kernels.RBFKernel(lengthscale_constraint=positive)
        self.register_parameter("raw_rbf_scale", torch.nn.Parameter(torch.zeros(1)))

    # the feature part, as the feature kernel exposes it (terms(), path sampling)
    @property
    def powers(self) -> torch.Tensor:
        return self.features_kernel.powers

    @property
    def weights(self) -> torch.nn.Parameter:
        return self.features_kernel.weights

    def features(self, x: torch.Tensor) -> torch.Tensor:
        return self.features_kernel.features(x)

    @property
    def library(self):
        return self.features_kernel.library

    def names(self, input_names=None) -> list[str]:
        return self.features_kernel.names(input_names)

    # the RBF part
    @property
    def lengthscale(self) -> torch.Tensor:
        return self.rbf.lengthscale

    @lengthscale.setter
    def lengthscale(self, value) -> None:
        self.rbf.lengthscale = value

    @property
    def raw_lengthscale(self) -> torch.nn.Parameter:
        return self.rbf.raw_lengthscale

    @property
    def rbf_scale(self) -> torch.Tensor:
        return self.raw_rbf_scale.exp()

    def forward(self, x1, x2, diag: bool = False, last_dim_is_batch: bool = False, **params):
        if last_dim_is_batch:
            raise NotImplementedError("FeaturesPlusRBF: last_dim_is_batch is not supported")
        poly = self.features_kernel.forward(x1, x2, diag=diag)
        return poly + self.rbf_scale * self.rbf.forward(x1, x2, diag=diag)


def _exact_mll(K: torch.Tensor, Y: torch.Tensor, D: torch.Tensor) -> torch.Tensor:
    """Sum over outputs of log N(y_o; 0, K + diag(D_o)) for ``Y (N, m)``, noise variances ``D (N, m)``: one
    factorization per group of outputs with the same noise (:func:`~torchmisspec.gp._mll.factorize`)."""
    total = Y.new_zeros(())
    for cols in noise_groups(D):
        fac = _mll.factorize(K.unsqueeze(0), D[:, cols[0]].unsqueeze(0), Y[:, cols].unsqueeze(0), warn=False)
        total = total + _mll.exact_mll(fac, Y.shape[0])
    return total


def _least_valuable(Phi, w, K, Y, D) -> tuple[int, float]:
    """The kept term (``w > 0``) of least evidence gain at its best weight given all the others, and that gain
    (:func:`~torchmisspec.gp._relevance.term_gain`). From one factorization of ``C = K + D`` per distinct noise
    column: with ``s_j = phi_j^T C^-1 phi_j`` and ``q_oj = phi_j^T C^-1 y_o``, the factors with term j left out of C
    are ``S_j = s_j / (1 - w_j s_j)`` and ``Q_oj = q_oj / (1 - w_j s_j)`` (Sherman-Morrison), and
    ``theta_j = sum_o Q_oj^2 / (m S_j)``. When the outputs' noise differs, S_j does too and the gain is bounded by
    the sum of each output's own best gain (an upper bound: a term is never removed for a gain it could have). When
    ``C`` cannot be factorized without jitter (nearly noiseless samples, where every kept term's gain is large
    anyway), no term is offered: ``(-1, inf)``."""
    tiny = torch.finfo(Phi.dtype).tiny
    kept = w > 0
    gain = torch.zeros(int(kept.sum()), dtype=Phi.dtype, device=Phi.device)
    for cols in noise_groups(D):
        L, failed = cholesky_or_fail(K + torch.diag(D[:, cols[0]]))
        if bool(failed):
            return -1, math.inf
        A = torch.cholesky_solve(Phi[:, kept], L)  # C^-1 phi_j for the kept terms
        s = (Phi[:, kept] * A).sum(0)
        q = A.T @ Y[:, cols]  # (q, m)
        shrink = (1.0 - w[kept] * s).clamp_min(tiny)
        S, Q = s / shrink, q / shrink.unsqueeze(-1)
        gain += term_gain(Q.pow(2).sum(-1) / (len(cols) * S).clamp_min(tiny), len(cols))
    i = int(torch.argmin(gain))
    return int(kept.nonzero().flatten()[i]), float(gain[i])


def fit_sum(
    kernel: FeaturesPlusRBF,
    X: torch.Tensor,
    Y: torch.Tensor,
    known: torch.Tensor | None,
    *,
    floor: float | None,
    lengthscale: float | None,
    max_iter: int,
    outputscale: float = 1.0,
    min_gain: float = 0.0,
) -> tuple[float, float, int]:
    """Fit the weights, the RBF scale and lengthscale (unless ``lengthscale`` is given) and the noise floor (unless
    ``floor`` is given) by exact marginal likelihood of ``outputscale * k + noise``; write them into ``kernel``. Fixed
    values are used as given. With ``min_gain`` > 0, terms whose best evidence gain given the rest (RBF term
    included, :func:`_least_valuable`) is at most ``min_gain`` nats are then removed one at a time, and the rest
    re-fitted once. Returns ``(floor, lml, iterations)``.
    """

    second = float(Y.pow(2).mean())
    if not second > 0:
        raise FittingError("targets: expected some non-zero samples to learn the kernel from, got all zeros")
    Phi = kernel.features(X).detach() * math.sqrt(outputscale)  # the output scale folded into the features
    scale_phi = Phi.pow(2).mean(0).clamp_min(torch.finfo(Phi.dtype).tiny)
    known0 = torch.zeros_like(Y) if known is None else known
    w0, s0, _ = fit_relevance(Phi, Y, known, floor=floor, max_iter=10 * max_iter, min_gain=min_gain)
    kd = {"dtype": X.dtype, "device": X.device}
    # start: the feature fit's weights (removed ones small, not 0: the RBF term may change what is relevant),
    # the RBF term at a tenth of the targets' second moment, the lengthscale at the median distance
    lower = _LOG_FLOOR + torch.log(second / scale_phi)
    log_w = torch.maximum(torch.log(w0.clamp_min(1e-300)), lower + 2.0).clone().requires_grad_(True)
    log_a = torch.tensor(math.log(0.1 * second), **kd, requires_grad=True)
    dist = median_distance(X)
    log_l = torch.tensor(
        math.log(dist if lengthscale is None else lengthscale), **kd, requires_grad=lengthscale is None
    )
    log_s = torch.tensor(
        math.log(max(s0, 1e-12 * second) if floor is None else floor), **kd, requires_grad=floor is None
    )
    params = [log_w, log_a] + ([log_l] if lengthscale is None else []) + ([log_s] if floor is None else [])
    l_box = (math.log(1e-3 * dist), math.log(1e3 * dist))
    s_box = (math.log(1e-12 * second), math.log(10 * second))

    sq = torch.cdist(X, X).pow(2)  # once: every evaluation of the objective reuses it

    keep = torch.ones_like(w0, dtype=torch.bool)  # the terms still in the model (removed ones: weight exactly 0)

    def kernel_matrix(wts: torch.Tensor) -> torch.Tensor:
        wts = torch.where(keep, wts, torch.zeros_like(wts))
        return (Phi * wts) @ Phi.T + outputscale * log_a.exp() * torch.exp(-0.5 * sq / log_l.exp().pow(2))

    def clamp() -> None:
        with torch.no_grad():  # keep line-search trials in a sane box; fixed values are left as given
            log_w.clamp_(min=lower)
            if log_l.requires_grad:
                log_l.clamp_(*l_box)
            if log_s.requires_grad:
                log_s.clamp_(*s_box)
            log_a.clamp_(math.log(1e-12 * second), math.log(1e3 * second))

    def evaluate() -> tuple[torch.Tensor, torch.Tensor]:
        clamp()
        value = _exact_mll(kernel_matrix(log_w.exp()), Y, known0 + log_s.exp())
        return value, value  # autograd through the factorization: the value is its own surrogate

    def optimise() -> int:
        try:
            result = maximise(
                params,
                evaluate,
                max_iter=max_iter,
                normaliser=float(Y.numel()),
                tolerance_grad=1e-9,
                tolerance_change=1e-9,
                history_size=100,
                desc="fit features+rbf",
            )
        except (torch.linalg.LinAlgError, LinearAlgebraError) as exc:
            raise FittingError(
                f"the features+rbf fit failed: the covariance lost positive definiteness ({exc})"
            ) from exc
        clamp()  # L-BFGS's last step is taken after the last evaluation: back into the box it was evaluated in
        return result.iterations

    iterations = optimise()
    with torch.no_grad():
        keep &= log_w.exp() * scale_phi >= PRUNE_SUM * second
    if min_gain > 0:
        removed = False
        with torch.no_grad():
            while bool(keep.any()):
                j, gain = _least_valuable(Phi, log_w.exp() * keep, kernel_matrix(log_w.exp()), Y, known0 + log_s.exp())
                if gain > min_gain:
                    break
                keep[j] = False
                removed = True
        if removed:  # the RBF term and the noise take up what the removed terms explained
            iterations += optimise()
    with torch.no_grad():
        w = log_w.exp() * keep
        w[w * scale_phi < PRUNE_SUM * second] = 0.0
        try:
            lml = float(_exact_mll(kernel_matrix(w), Y, known0 + log_s.exp()))
        except (torch.linalg.LinAlgError, LinearAlgebraError) as exc:  # round-off with a floor near 0: say so
            raise FittingError(
                "the features+rbf fit failed: with the learned noise floor "
                f"{float(log_s.exp()):.3g} the covariance is not numerically positive definite ({exc}); the samples "
                "look noiseless: fix a small noise_variance, or use kernel='features'"
            ) from exc
        kernel.features_kernel.weights.copy_(w)
        kernel.raw_rbf_scale.copy_(log_a.reshape(1))
        if lengthscale is None:
            kernel.lengthscale = log_l.exp().reshape(1, 1)
    if not all(bool(torch.isfinite(p).all()) for p in params):
        raise FittingError("the features+rbf fit diverged: a hyperparameter became non-finite; rescale the data")
    return float(log_s.detach().exp()), lml, iterations
