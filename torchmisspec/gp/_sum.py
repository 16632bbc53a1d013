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


class _SumFit:
    """:func:`fit_sum`'s optimisation: the log hyperparameters (the weights, the RBF term's scale and lengthscale,
    the noise floor; a fixed lengthscale or floor is held), the boxes that keep line-search trials sane, and the terms
    still in the model (``keep``: removed ones have weight exactly 0), with the exact log marginal likelihood as the
    objective. Starts from the feature fit ``(w0, s0)`` (removed weights small, not 0: the RBF term may change what
    is relevant), the RBF term at a tenth of the targets' second moment and the lengthscale at the median distance."""

    def __init__(self, Phi, X, Y, known0, w0, s0, *, floor, lengthscale, outputscale: float, max_iter: int):
        second = float(Y.pow(2).mean())
        self.Phi, self.Y, self.known0, self.outputscale, self.max_iter = Phi, Y, known0, outputscale, max_iter
        self.second = second
        self.scale_phi = Phi.pow(2).mean(0).clamp_min(torch.finfo(Phi.dtype).tiny)
        kd = {"dtype": X.dtype, "device": X.device}
        self.lower = _LOG_FLOOR + torch.log(second / self.scale_phi)
        self.log_w = torch.maximum(torch.log(w0.clamp_min(1e-300)), self.lower + 2.0).clone().requires_grad_(True)
        self.log_a = torch.tensor(math.log(0.1 * second), **kd, requires_grad=True)
        dist = median_distance(X)
        self.log_l = torch.tensor(
            math.log(dist if lengthscale is None else lengthscale), **kd, requires_grad=lengthscale is None
        )
        self.log_s = torch.tensor(
            math.log(max(s0, 1e-12 * second) if floor is None else floor), **kd, requires_grad=floor is None
        )
        self.params = [self.log_w, self.log_a] + ([self.log_l] if lengthscale is None else [])
        self.params += [self.log_s] if floor is None else []
        self.l_box = (math.log(1e-3 * dist), math.log(1e3 * dist))
        self.s_box = (math.log(1e-12 * second), math.log(10 * second))
        self.sq = torch.cdist(X, X).pow(2)  # once: every evaluation of the objective reuses it
        self.keep = torch.ones_like(w0, dtype=torch.bool)

    def kernel_matrix(self, wts: torch.Tensor) -> torch.Tensor:
        """``K`` with the weights ``wts`` (removed terms at 0) and the current RBF term."""
        wts = torch.where(self.keep, wts, torch.zeros_like(wts))
        rbf = torch.exp(-0.5 * self.sq / self.log_l.exp().pow(2))
        return (self.Phi * wts) @ self.Phi.T + self.outputscale * self.log_a.exp() * rbf

    def noise(self) -> torch.Tensor:
        """``(N, m)``: the samples' noise variances, known noise plus the current floor."""
        return self.known0 + self.log_s.exp()

    def clamp(self) -> None:
        """Back into the box (fixed values are left as given)."""
        second = self.second
        with torch.no_grad():  # keep line-search trials in a sane box; fixed values are left as given
            self.log_w.clamp_(min=self.lower)
            if self.log_l.requires_grad:
                self.log_l.clamp_(*self.l_box)
            if self.log_s.requires_grad:
                self.log_s.clamp_(*self.s_box)
            self.log_a.clamp_(math.log(1e-12 * second), math.log(1e3 * second))

    def evaluate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The objective at the current (clamped) hyperparameters, and its surrogate for autograd."""
        self.clamp()
        value = _exact_mll(self.kernel_matrix(self.log_w.exp()), self.Y, self.noise())
        return value, value  # autograd through the factorization: the value is its own surrogate

    def optimise(self) -> int:
        """L-BFGS over the free hyperparameters; its iterations."""
        try:
            result = maximise(
                self.params,
                self.evaluate,
                max_iter=self.max_iter,
                normaliser=float(self.Y.numel()),
                tolerance_grad=1e-9,
                tolerance_change=1e-9,
                history_size=100,
                desc="fit features+rbf",
            )
        except (torch.linalg.LinAlgError, LinearAlgebraError) as exc:
            raise FittingError(
                f"the features+rbf fit failed: the covariance lost positive definiteness ({exc})"
            ) from exc
        self.clamp()  # L-BFGS's last step is taken after the last evaluation: back into the box it was evaluated in
        return result.iterations

    def prune(self) -> None:
        """Remove the terms whose share of the prior variance fell below :data:`PRUNE_SUM`."""
        with torch.no_grad():
            self.keep &= self.log_w.exp() * self.scale_phi >= PRUNE_SUM * self.second

    def remove_cheap(self, min_gain: float) -> bool:
        """Remove, one at a time, the kept terms whose best evidence gain given the rest (:func:`_least_valuable`)
        is at most ``min_gain`` nats; whether any was removed."""
        removed = False
        with torch.no_grad():
            while bool(self.keep.any()):
                w = self.log_w.exp()
                j, gain = _least_valuable(self.Phi, w * self.keep, self.kernel_matrix(w), self.Y, self.noise())
                if gain > min_gain:
                    break
                self.keep[j] = False
                removed = True
        return removed

    def final(self) -> tuple[torch.Tensor, float]:
        """``(weights, log marginal likelihood)`` where the fit ended, the weights below :data:`PRUNE_SUM` at 0."""
        with torch.no_grad():
            w = self.log_w.exp() * self.keep
            w[w * self.scale_phi < PRUNE_SUM * self.second] = 0.0
            try:
                return w, float(_exact_mll(self.kernel_matrix(w), self.Y, self.noise()))
            except (torch.linalg.LinAlgError, LinearAlgebraError) as exc:  # round-off with a floor near 0: say so
                raise FittingError(
                    "the features+rbf fit failed: with the learned noise floor "
                    f"{float(self.log_s.exp()):.3g} the covariance is not numerically positive definite ({exc}); the "
                    "samples look noiseless: fix a small noise_variance, or use kernel='features'"
                ) from exc


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
    known0 = torch.zeros_like(Y) if known is None else known
    w0, s0, _ = fit_relevance(Phi, Y, known, floor=floor, max_iter=10 * max_iter, min_gain=min_gain)
    fit = _SumFit(
        Phi, X, Y, known0, w0, s0, floor=floor, lengthscale=lengthscale, outputscale=outputscale, max_iter=max_iter
    )
    iterations = fit.optimise()
    fit.prune()
    if min_gain > 0 and fit.remove_cheap(min_gain):  # the RBF term and the noise take up what they explained
        iterations += fit.optimise()
    w, lml = fit.final()
    with torch.no_grad():
        kernel.features_kernel.weights.copy_(w)
        kernel.raw_rbf_scale.copy_(fit.log_a.reshape(1))
        if lengthscale is None:
            kernel.lengthscale = fit.log_l.exp().reshape(1, 1)
    if not all(bool(torch.isfinite(p).all()) for p in fit.params):
        raise FittingError("the features+rbf fit diverged: a hyperparameter became non-finite; rescale the data")
    return float(fit.log_s.detach().exp()), lml, iterations
