"""Posterior function samples of the correction, consistent along whole paths (pathwise conditioning).

Matheron's rule (Wilson et al. 2020, "Efficiently sampling functions from Gaussian process posteriors"): if
``f ~ GP(0, k)`` and ``e ~ N(0, diag(s))``, then

    f_post(x) = f(x) + k(x, X) C^-1 (Y - f(X) - e),    C = K(X, X) + diag(s),

is a draw from the posterior of f given ``Y``. The prior draw ``f`` is a finite feature expansion
``f(x) = phi(x)^T w``, ``w ~ N(0, I)``, which can be evaluated anywhere at any time, so one draw is one *function*:
an ODE solver can call it at every step and every state of a path and always sees the same function (independent
draws per solver step would not be a sample of anything). The update uses the canonical basis ``k(x, X)`` and the
cached factorization of C, so the posterior mean of the samples is the exact posterior mean and their covariance
is exact up to the prior's feature error (near the data the update removes most of it: the "decoupled" sampler).

Features (:func:`feature_map`):

* ``rbf``, by default: deterministic **quadrature Fourier features** (kind ``"quadrature"``; Dao et al. 2017,
  "Gaussian quadrature for kernel features"; Mutny and Krause 2018, "Efficient high dimensional Bayesian
  optimization with additivity and quadrature Fourier features"), frequency pairs
  ``sqrt(s^2 c_j) [cos(w_j^T x), sin(w_j^T x)]`` on a pruned tensor-product Gauss-Hermite grid ``w_j = z_j / l``,
  with a certified *uniform* bound on the prior-covariance error over the data's box (below); they fall back to
  random features when those need fewer frequencies (high input dimension);
* ``rbf`` with ``num_features`` given, or the fallback: random Fourier features (kind ``"fourier"``), frequency
  pairs ``[cos(w^T x), sin(w^T x)] / sqrt(D)`` with ``w ~ N(0, I / l^2)``;
* ``matern52``: random Fourier features with ``w`` from the Matern spectral density, a multivariate Student t with
  2 nu = 5 degrees of freedom and scale ``1 / l`` (its heavy tails have no Gauss-Hermite rule);
* ``polynomial``: the exact finite features of ``(c + <x, x'>)^m`` (c = 1), the monomials ``x^a`` (``|a| <= m``)
  weighted by the square roots of the multinomial coefficients times ``c^(m - |a|)``: no approximation error.

**Random features.** With ``D`` frequency pairs the prior covariance estimate at a pair of points,
``k_hat(x, x') = s^2 / D sum_j cos(w_j^T (x - x'))``, is unbiased with variance
``s^4 ((1 + k0(2 r)) / 2 - k0(r)^2) / D <= s^4 / D`` (``k0`` the unit-scale kernel, ``r = x - x'``), and exact at
``x = x'``. :func:`frequencies_for` therefore takes ``D = ceil(1 / eps^2)`` for a root-mean-square error of at
most ``eps`` times the prior variance at every pair of points, in particular over the data's box (the default
``eps = 0.05``: D = 400, 800 features). A *uniform* bound over a box (Rahimi and Recht 2007, Claim 1) needs
``D >= 8 (d + 2) / eps^2 log(...)``, tens of thousands of frequencies for ``eps = 0.1``; it is far from tight, and
the pointwise bound is the one random features carry (``FeatureMap.error_bound = 1 / sqrt(D)``).

**Quadrature features and their bound** (:func:`quadrature_rule`). ``k(r) / s^2 = prod_i c(r_i / l)`` with
``c(rho) = exp(-rho^2 / 2) = E cos(rho z)``, ``z ~ N(0, 1)``. The m-node Gauss-Hermite rule (nodes ``z_j``
symmetric about 0, weights ``a_j`` summing to 1) gives ``Q_m(rho) = sum_j a_j cos(rho z_j)`` (the sine part
cancels between ``+z_j`` and ``-z_j``), with the 1-D error ``e_m(rho) = max_{|t| <= rho} |Q_m(t) - c(t)|`` bounded
by the smaller of

1. the Gauss-Hermite remainder: ``int e^{-x^2} f = sum + m! sqrt(pi) / (2^m (2m)!) f^(2m)(xi)``; with
   ``x = z / sqrt(2)`` the standard-normal form is ``E g - sum_j a_j g(z_j) = m! / (2m)! g^(2m)(xi)`` and
   ``|d^2m/dz^2m cos(t z)| <= t^2m``, so ``e_m(rho) <= m! rho^2m / (2m)!`` (the first term of the error's series,
   tight for small rho, loose by orders of magnitude where it matters, near rho^2 ~ m);
2. a certified grid maximum: ``|Q_m''| <= sum_j a_j z_j^2`` (= 1 for m >= 2) and ``|c''| <= 1``, so between
   points of a grid ``h`` apart ``|Q_m - c|`` exceeds its largest value at the grid points by at most
   ``(1 + sum_j a_j z_j^2) h^2 / 8`` (linear interpolation); ``h <= 2^-7`` keeps this below 1.6e-5 (finer grids
   for tighter targets; plus ``64 m`` ulps for rounding).

The tensor rule with ``m_i`` nodes in dimension i gives ``prod_i Q_{m_i}(r_i / l)``; every factor of both
products lies in [-1, 1], and ``|prod a_i - prod b_i| <= sum_i |a_i - b_i|`` for such factors, so
``|k_hat(x, x') - k(x, x')| <= s^2 sum_i e_{m_i}(R_i / l)`` whenever ``|x_i - x'_i| <= R_i``. Nodes come in pairs
``+-w`` (one frequency pair each, weight ``c_j = 2 A_j``, ``A_j`` the product weight; the origin, if it is a node,
has its own weight): only half of the grid is built. Most product weights are tiny, so pairs of total weight
``delta`` are dropped (the smallest first) and the rest renormalized to sum 1 (exact prior variance at ``x = x'``),
which adds at most ``2 delta`` to the bound (``|Q'/(1 - delta) - Q'| <= delta`` since ``|Q'| <= 1 - delta``).
The box: ``R_i = (1 + 2 QUADRATURE_MARGIN) W_i`` with ``W_i`` the width of the GP's training inputs in dimension i,
i.e. ``x`` and ``x'`` anywhere in that box widened by ``QUADRATURE_MARGIN = 1`` times its own width on each side
(paths leave the data a bit), and at least one lengthscale. Per-output kernels share the nodes, designed for the
shortest lengthscale (the bound grows with ``R_i / l``), each scaled by its own ``l``. Outside the box the error is
not bounded (a quadrature is nearly periodic far away); the posterior there is the prior anyway.

``feature_map`` chooses the ``m_i`` and ``delta`` with the fewest pairs whose bound is at most the target
(:data:`QUADRATURE_FEATURE_ERROR` = 1e-2 by default: a *uniform* error 5 times below the random features'
*root-mean-square* 0.05, for far fewer features in low dimension, e.g. 45 pairs instead of 400 on paper_linear;
1e-3 costs 70 pairs there, and a posterior 22x the mean-only prediction instead of 17x: BENCHMARKS.md) and
uses them when they need no more pairs than random features at :data:`DEFAULT_FEATURE_ERROR` (else, by default,
the quadrature at 0.05, else random features at 0.05). With ``feature_error`` given, the quadrature at that bound
is used when it needs no more pairs than random features at it (``1 / eps^2``). ``FeatureMap.error_bound`` holds
the bound reached (relative to the prior variance of every output) and ``FeatureMap.box`` its box.
"""

from __future__ import annotations

import itertools
import math

import torch

from .._errors import InputError, ShapeError
from .._validation import check_generator, check_positive_int
from ._quadrature import (
    MAX_FREQUENCIES,
    QUADRATURE_FEATURE_ERROR,
    _check_error,
    frequencies_for,
    gauss_hermite_error,
    hermite_remainder,
    quadrature_rule,
)

__all__ = [
    "DEFAULT_FEATURE_ERROR",
    "QUADRATURE_FEATURE_ERROR",
    "QUADRATURE_MARGIN",
    "FeatureMap",
    "FunctionSamples",
    "feature_map",
    "frequencies_for",
    "gauss_hermite_error",
    "hermite_remainder",
    "kernel_hyperparameters",
    "kernel_matrix",
    "quadrature_rule",
]

#: Default bound on the root-mean-square error of the prior covariance, relative to the prior variance.
DEFAULT_FEATURE_ERROR = 0.05
#: The quadrature's bound holds on the training inputs' box widened by this many times its own width on each side.
QUADRATURE_MARGIN = 1.0
#: Entries of k(x, X) evaluated at once (memory: 8 bytes each in float64): 2 ** 22 ~ 32 MB.
_CHUNK = 2**22
#: Entries per buffer of the sampled paths' hot loop (FunctionSamples._evaluate_fast): 2 ** 20 ~ 8 MB, small enough
#: to stay in cache between the operations on it, large enough to amortize their dispatch.
_HOT_CHUNK = 2**20


class FeatureMap:
    """``phi(x)``: ``(B, ..., F)`` features of inputs ``(..., d_in)`` with ``phi(x)^T phi(x') ~ k(x, x')`` per batch
    ``b`` (B = 1 for a shared kernel, d_out for per-output kernels); output scale included.

    Attributes:
        kind: ``"quadrature"`` (deterministic, certified uniform bound over :attr:`box`), ``"fourier"`` (random),
            ``"polynomial"`` (exact) or ``"sum"`` (the features of a sum of kernels side by side, ``parts``).
        num_features: F (for Fourier kinds, twice the number of frequency pairs).
        error_bound: the bound reached on ``|k_hat - k|`` relative to the prior variance: uniform over ``box`` for
            ``"quadrature"``, the root-mean-square bound ``1 / sqrt(D)`` at every pair of points for ``"fourier"``,
            0 for ``"polynomial"``.
        box: ``(2, d_in)`` lower and upper corners of the box of ``error_bound`` (``"quadrature"``), else ``None``.
    """

    def __init__(
        self,
        kind: str,
        num_features: int,
        *,
        error_bound: float = 0.0,
        box: torch.Tensor | None = None,
        **tensors: torch.Tensor,
    ) -> None:
        self.kind = kind
        self.num_features = num_features
        self.error_bound = error_bound
        self.box = box
        self._t = tensors

    def __repr__(self) -> str:
        return f"FeatureMap(kind={self.kind!r}, num_features={self.num_features}, error_bound={self.error_bound:.3g})"

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        t = self._t
        if self.kind in ("fourier", "quadrature"):
            omega, scale = t["omega"], t["scale"]  # (B, d_in, D), (B, 1) or (B, D): per-frequency sqrt(s^2 c_j)
            proj = torch.einsum("...i,bid->b...d", x, omega)
            scale = scale.reshape((omega.shape[0],) + (1,) * (proj.dim() - 2) + (scale.shape[-1],))
            return torch.cat([proj.cos() * scale, proj.sin() * scale], dim=-1)
        if self.kind == "sum":
            return torch.cat([part(x) for part in t["parts"]], dim=-1)
        coef = t["coef"]  # (B, P) sqrt(s^2 c_a)
        if self.kind == "library":  # a feature kernel's own features (monomials or a user library)
            mono = t["fn"](x)
        else:
            mono = (x.unsqueeze(-2) ** t["powers"]).prod(-1)  # (..., P)
        shape = (coef.shape[0],) + (1,) * (mono.dim() - 1) + (coef.shape[-1],)
        return mono.unsqueeze(0) * coef.reshape(shape)


def feature_map(gp, *, num_features: int | None = None, feature_error: float | None = None, generator=None):
    """The prior features of a fitted :class:`~torchmisspec.CorrectionGP`'s kernel (see the module docstring).

    Args:
        gp: a fitted CorrectionGP (RBF, Matern 5/2 or polynomial kernel; shared or per-output).
        num_features: number of *random* Fourier features F (even: F / 2 frequency pairs), for the RBF kernel too
            (no quadrature); for the polynomial kernel the exact number is used and this must be ``None``.
        feature_error: the bound that chooses the features when ``num_features`` is ``None``, relative to the prior
            variance: for the RBF kernel the certified uniform bound of quadrature features over the data's widened
            box when they need no more pairs than random features at this bound, else the root-mean-square bound
            of :func:`frequencies_for` (default: quadrature at :data:`QUADRATURE_FEATURE_ERROR` = 1e-2, else at
            :data:`DEFAULT_FEATURE_ERROR`, else random features at the latter; module docstring).
        generator: ``torch.Generator`` on the GP's device, for reproducible frequencies (quadrature features are
            deterministic).

    Returns:
        :class:`FeatureMap`, with the bound reached in ``error_bound`` (and its box in ``box`` for quadrature).
    """
    gp._require_fitted()
    generator = check_generator(generator, gp.device)
    covar = gp.covar_module
    outputscale = covar.outputscale.detach().reshape(-1, 1).to(dtype=gp.dtype, device=gp.device)  # (B, 1)
    return gp.kernel_spec.path_features(gp, covar.base_kernel, outputscale, num_features, feature_error, generator)


def polynomial_features(gp, base, outputscale: torch.Tensor) -> FeatureMap:
    """The exact features of (c + <x, x'>)^m: every monomial x^a with |a| <= m, weighted by the multinomial
    coefficient times c^(m - |a|) and the output scale ``(B, 1)``."""
    kd = dict(dtype=gp.dtype, device=gp.device)
    d_in = gp.input_dim
    m = gp.degree
    offset = base.offset.detach().reshape(-1, 1).to(**kd)  # (B, 1)
    powers, coef, rest = [], [], []
    for a in itertools.product(range(m + 1), repeat=d_in):
        if sum(a) <= m:  # (c + <x, x'>)^m = sum_a m! / ((m - |a|)! prod a_i!) c^(m - |a|) x^a x'^a
            powers.append(a)
            coef.append(math.factorial(m) / (math.factorial(m - sum(a)) * math.prod(math.factorial(i) for i in a)))
            rest.append(m - sum(a))
    P = torch.tensor(powers, **kd)
    c = torch.tensor(coef, **kd) * offset ** torch.tensor(rest, **kd)  # (B, P)
    return FeatureMap("polynomial", len(coef), powers=P, coef=(outputscale * c).sqrt())


def stationary_features(gp, kernel, lengthscale, outputscale, num_features, feature_error, generator):
    """Features of the stationary ``kernel`` (the squared exponential: quadrature when they pay, else random; the
    others: random, from ``kernel.spectral``) with ``lengthscale (B, d_in)`` and ``outputscale (B, 1)``."""
    kd = dict(dtype=gp.dtype, device=gp.device)
    B, d_in = lengthscale.shape
    if num_features is None and getattr(kernel, "squared_exponential", False):
        quadrature = _quadrature_features(gp.train_inputs_.detach().to(**kd), lengthscale, outputscale, feature_error)
        if quadrature is not None:
            return quadrature
    if num_features is None:
        D = frequencies_for(DEFAULT_FEATURE_ERROR if feature_error is None else feature_error)
    else:
        if feature_error is not None:
            raise InputError(
                "num_features and feature_error: expected one of them, got both "
                f"({num_features!r} and {feature_error!r})"
            )
        F = check_positive_int(num_features, "num_features")
        if F % 2:
            raise InputError(f"num_features: expected an even number (cos and sin per frequency), got {F}")
        D = F // 2
    z = kernel.spectral((B, d_in, D), generator, kd["dtype"], kd["device"])
    omega = z / lengthscale.unsqueeze(-1)
    return FeatureMap("fourier", 2 * D, omega=omega, scale=(outputscale / D).sqrt(), error_bound=1.0 / math.sqrt(D))


def _quadrature_features(X: torch.Tensor, lengthscale: torch.Tensor, outputscale: torch.Tensor, feature_error):
    """Quadrature features of the RBF kernel (module docstring) when they need no more frequency pairs than random
    features at the same bound would; ``None`` otherwise.

    By default the target is :data:`QUADRATURE_FEATURE_ERROR`, against random features at
    :data:`DEFAULT_FEATURE_ERROR` (a uniform 1e-2 for no more pairs than a root-mean-square 0.05), then 0.05 for
    both; a given ``feature_error`` is the target of both.
    """
    lo, hi = X.amin(0), X.amax(0)
    # |x_i - x'_i| <= R_i on the training inputs' box widened by QUADRATURE_MARGIN times its width on each side, and
    # at least one (the shortest) lengthscale wide: rho_i = R_i / l_i, with l_i the shortest over the outputs (the
    # bound grows with rho, so one rule designed for it holds for every output's kernel)
    shortest = lengthscale.amin(0)  # (d_in,)
    R = torch.maximum((1 + 2 * QUADRATURE_MARGIN) * (hi - lo), shortest)
    rho = (R / shortest).tolist()
    centre = (lo + hi) / 2
    box = torch.stack([centre - R / 2, centre + R / 2])
    if feature_error is None:
        targets = [(QUADRATURE_FEATURE_ERROR, DEFAULT_FEATURE_ERROR), (DEFAULT_FEATURE_ERROR, DEFAULT_FEATURE_ERROR)]
    else:
        targets = [(_check_error(feature_error),) * 2]
    for target, random_target in targets:
        rule = quadrature_rule(rho, target)
        if rule is None or len(rule[1]) > min(math.ceil(1.0 / random_target**2), MAX_FREQUENCIES):
            continue
        Z, c, bound = rule
        Z, c = torch.as_tensor(Z, dtype=X.dtype, device=X.device), torch.as_tensor(c, dtype=X.dtype, device=X.device)
        omega = Z.T.unsqueeze(0) / lengthscale.unsqueeze(-1)  # (B, d_in, D): w_j = z_j / l per output
        scale = (outputscale * c).sqrt()  # (B, D): sqrt(s^2 c_j)
        return FeatureMap("quadrature", 2 * len(c), omega=omega, scale=scale, error_bound=bound, box=box)
    return None


def detached(params: dict, *, clone: bool = False) -> dict:
    """:func:`kernel_hyperparameters` without the autograd graph (the feature function is kept as it is)."""
    return {k: (v.detach().clone() if clone else v.detach()) if torch.is_tensor(v) else v for k, v in params.items()}


def kernel_hyperparameters(gp) -> dict[str, torch.Tensor]:
    """The GP's kernel hyperparameters as ``(B, 1, 1)`` tensors (``outputscale`` and what its kernel object's
    :meth:`~torchmisspec.gp._kernels.Kernel.hyperparameters` gives), keeping the autograd graph to the GPyTorch
    parameters."""
    covar = gp.covar_module
    out = {"outputscale": covar.outputscale.reshape(-1, 1, 1)}
    out.update(gp.kernel_spec.hyperparameters(covar.base_kernel, out["outputscale"].shape[0]))
    return out


def kernel_matrix(kernel, x: torch.Tensor, X: torch.Tensor, params: dict, degree: int = 2) -> torch.Tensor:
    """``k(x, X)`` as ``(B, M, N)`` for inputs ``x (M, d)``, ``X (N, d)`` and hyperparameters ``(B, 1, 1)`` of the
    kernel object ``kernel`` (:meth:`~torchmisspec.gp._kernels.Kernel.matrix`): the same kernels as the GP's
    GPyTorch modules (tested against them), written out so that the hot loop of sampled paths needs no module calls
    and the hyperparameters can be constants or carry gradients."""
    return kernel.matrix(x, X, params, degree)


class FunctionSamples:
    """``S`` posterior draws of F as functions: ``samples(x)`` with ``x (S, M, d_in)`` (draw s at its own points)
    or ``(M, d_in)`` (every draw at the same points) returns ``(S, M, d_out)``.

    Built by :meth:`CorrectionGP.sample_functions <torchmisspec.CorrectionGP.sample_functions>`; the GP's cached
    factorization is reused (one triangular solve pair for all draws). The draws are frozen: later changes to the
    GP do not affect them.

    With ``update_error`` (a fraction of the prior standard deviation), the update ``k(x, X) v_s`` is replaced by its
    projection on the fewest training inputs that keep a *certified* bound ``update_error * s`` on the change at any
    point (see :meth:`_compress`); ``samples.update_error`` holds the bound reached (0: exact basis).

    With ``scale`` c, the draws are ``mu + c (F_s - mu)`` (``mu = k(x, X) alpha`` the posterior mean): since
    ``F_s = phi(x)^T w_s + k(x, X) v_s``, that is ``phi(x)^T (c w_s) + k(x, X) (c v_s + (1 - c) alpha)``, the same
    kind of function at no extra cost (the compression, if any, applies to the scaled update).

    Attributes:
        num_samples: S.
        features: the :class:`FeatureMap` of the prior draws.
        update_error: the certified bound on the compression's error in F (0 when not compressed).
        scale: c.
    """

    def __init__(
        self,
        gp,
        num_samples: int,
        features: FeatureMap,
        generator=None,
        update_error: float | None = None,
        *,
        scale: float = 1.0,
    ) -> None:
        cache = gp.posterior()
        X, Y, noise = gp.train_inputs_, gp.train_targets_, gp.train_noise_
        S = num_samples
        N, d_out = Y.shape
        kd = dict(dtype=gp.dtype, device=gp.device)
        with torch.no_grad():
            diag = gp._noise_diag(noise)  # (1, 1), (1, N), (d_out, 1) or (d_out, N): no N x N kernel
            B = features(X[:1]).shape[0]
            fac = cache.factor
            batches = fac.alpha.shape[0]  # 1: one covariance for every output, else one per output
            if gp.kernel_spec.feature_space and B == 1 and batches == 1 and features.kind == "library":
                # finitely many features (output scale in phi): each draw is phi(x)^T z_s with the coefficients
                # drawn from their posterior, z_s = (mean + sqrt(W) L_M^-T e_s) / coef: p per point, not N, and
                # no solve with C (whose Woodbury form cancels badly when the noise is tiny)
                beta = fac.sample_coefficients(S, float(scale), generator)  # (S, p, d_out)
                coef = features._t["coef"].reshape(-1, 1)  # (p, 1): sqrt(s^2 w); 0 for a removed term
                weights = torch.where(coef > 0, beta / coef.clamp_min(torch.finfo(coef.dtype).tiny), 0.0).unsqueeze(1)
                X, v = X[:0], weights.new_zeros(S, 0, d_out)
            else:
                weights = torch.randn((S, B, features.num_features, d_out if B == 1 else 1), generator=generator, **kd)
                eps = torch.randn((S, N, d_out), generator=generator, **kd) * diag.T.sqrt()  # (S, N, d_out)
                # the prior draws at the training inputs: one feature matrix phi(X) for all draws
                phi = features(X)  # (B, N, F)
                prior = phi[0] @ weights[:, 0] if B == 1 else torch.einsum("bnf,sbf->snb", phi, weights[..., 0])
                residual = Y - prior - eps  # (S, N, d_out)
                solve = fac.solve if hasattr(fac, "solve") else (lambda V: torch.cholesky_solve(V, fac.chol))
                if batches == 1:
                    rhs = residual.permute(1, 0, 2).reshape(1, N, S * d_out)
                    v = solve(rhs)[0].reshape(N, S, d_out).permute(1, 0, 2)
                else:
                    v = solve(residual.permute(2, 1, 0)).permute(2, 1, 0)  # (S, N, d_out)
            # the removed feature terms' chance of being present: independent coefficients e_s ~ N(0, spread), not
            # conditioned on the data (it is posterior spread already: gp._features), drawn after the others
            extra = None
            base = gp.covar_module.base_kernel
            if getattr(base, "spread", None) is not None and bool((base.spread > 0).any()):
                spread = base.spread.detach().reshape(-1, base.spread.shape[-1]).to(**kd)  # (B, p)
                e = torch.randn((S, spread.shape[-1], d_out), generator=generator, **kd)
                extra = (base.features, e * spread.T.sqrt())  # (S, p, d_out): one column per output
            scale = float(scale)
            if scale != 1.0 and X.shape[0] == 0:  # the coefficient draws carry the scale already
                extra = None if extra is None else (extra[0], extra[1] * scale)
            elif scale != 1.0:  # mu + c (F_s - mu): c w_s and c v_s + (1 - c) alpha (and c e_s)
                alpha = cache.weights  # (N, d_out)
                weights = weights * scale
                extra = None if extra is None else (extra[0], extra[1] * scale)
                v = scale * v + (1.0 - scale) * alpha
        self.num_samples = S
        self.scale = scale
        self.features = features
        self._kind, self._degree = gp.kernel_spec, gp.degree
        with torch.no_grad():
            self._params = detached(kernel_hyperparameters(gp), clone=True)
        self._X = X.detach()
        self._weights = weights
        self._v = v.contiguous()
        self._per_output = gp.per_output
        self._d_out = d_out
        self._extra = extra  # (features, coefficients (S, p, d_out)) of the removed terms' spread, or None
        self._fast: dict | bool | None = None  # the hot path's precomputed pieces (built at the first call)
        self._buffers: dict = {}
        #: certified bound on |update - exact update| at any point (0: the exact canonical basis is used)
        self.update_error = 0.0
        if update_error is not None and batches == 1 and gp.kernel_spec.stationary and X.shape[0] > 0:
            with torch.no_grad():
                self._compress(float(update_error) * math.sqrt(float(self._params["outputscale"].reshape(-1)[0])))

    def _compress(self, target: float) -> None:
        """Replace the update ``k(x, X) v_s`` by its RKHS projection ``k(x, Z) u_s`` on a subset Z of X.

        Z grows by greedy pivoted Cholesky of K(X, X) (the point with the largest residual variance next) until the
        bound holds for every draw and output: ``|k(x, X) v - k(x, Z) u| <= k(x, x)^(1/2) ||r||_H`` (Cauchy-Schwarz
        in the RKHS), with ``||r||_H^2 = v^T (K - K_XZ K_ZZ^-1 K_ZX) v`` computed from the explicit residual (no
        cancellation). ``u = K_ZZ^-1 K_ZX v`` is the orthogonal projection. For stationary kernels
        ``k(x, x)^(1/2)`` is the prior standard deviation, so ``target`` is an absolute bound on F.
        """
        X, v = self._X, self._v  # (N, d_in), (S, N, d_out)
        N = X.shape[0]
        K = kernel_matrix(self._kind, X, X, self._params, self._degree)[0]
        scale = math.sqrt(float(self._params["outputscale"].reshape(-1)[0]))
        V = v.permute(1, 0, 2).reshape(N, -1)  # (N, S d_out)
        resid = K.diagonal().clone()
        L = torch.zeros((N, 0), dtype=K.dtype, device=K.device)
        pivots: list[int] = []
        bound = math.inf
        step = 8
        while len(pivots) < N:
            new_cols = []
            for _ in range(min(step, N - len(pivots))):
                i = int(resid.argmax())
                if float(resid[i]) <= 0.0:
                    break
                col = K[:, i] - L @ L[i] if L.shape[1] else K[:, i].clone()
                if new_cols:
                    prev = torch.stack(new_cols, -1)
                    col = col - prev @ prev[i]
                col = col / math.sqrt(float(resid[i]))
                new_cols.append(col)
                resid = (resid - col.pow(2)).clamp_min(0.0)
                resid[i] = 0.0
                pivots.append(i)
            if not new_cols:
                break
            L = torch.cat([L, torch.stack(new_cols, -1)], -1)
            R = K - L @ L.T  # the Nystrom residual, small entries: no cancellation in v^T R v
            # plus the rounding of R itself (|delta R_ij| <= N eps max K), so that a tiny residual is not over-trusted
            rounding = N * torch.finfo(K.dtype).eps * float(K.abs().max()) * V.pow(2).sum(0)
            bound = scale * float(((V * (R @ V)).sum(0).clamp_min(0.0) + rounding).max().sqrt())
            if bound <= target:
                break
            step = min(2 * step, 64)
        if len(pivots) >= N or not math.isfinite(bound) or bound > target:
            return  # no compression pays off: keep the exact canonical basis
        # u = K_ZZ^-1 K_ZX v with K_ZZ = L_Z L_Z^T and K_ZX = L_Z L^T (the pivoted factor reproduces both), so
        # u = L_Z^-T L^T v: one triangular solve with L_Z (condition number the square root of K_ZZ's)
        LZ = L[pivots].tril()
        u = torch.linalg.solve_triangular(LZ.T, L.T @ V, upper=True)  # (M, S d_out)
        # a posteriori check at the training inputs: rounding in u must not break the bound
        seen = float((K[:, pivots] @ u - K @ V).abs().max())
        if not seen <= bound:
            return
        u = u.reshape(len(pivots), v.shape[0], v.shape[2]).permute(1, 0, 2)
        self._X, self._v, self.update_error = X[pivots], u.contiguous(), bound

    @staticmethod
    def _prior(features: FeatureMap, weights: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Prior draws ``phi(x)^T w`` at ``x (S, M, d_in)``: ``(S, M, d_out)``."""
        if features.kind in ("fourier", "quadrature") and features._t["omega"].shape[0] == 1:
            # no concatenated feature matrix, the (per-frequency) scales folded into w (the sampled paths' hot path
            # without autograd is _evaluate_fast)
            omega, scale = features._t["omega"][0], features._t["scale"].reshape(-1, 1)  # (d_in, D), (1 or D, 1)
            D = omega.shape[-1]
            proj = x @ omega  # (S, M, D)
            w = weights[:, 0] * (scale if scale.shape[0] == 1 else torch.cat([scale, scale]))  # (S, 2D, d_out)
            out = torch.bmm(proj.cos(), w[:, :D])
            sin = proj.sin() if proj.requires_grad else proj.sin_()  # in place unless autograd needs proj
            return torch.baddbmm(out, sin, w[:, D:])
        phi = features(x)  # (B, S, M, F)
        if phi.shape[0] == 1:
            return phi[0] @ weights[:, 0]  # (S, M, F) @ (S, F, d_out)
        return torch.einsum("bsmf,sbf->smb", phi, weights[..., 0])

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        S = self.num_samples
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise InputError(f"x: expected a floating-point tensor of inputs, got {type(x).__name__} {x!r:.60}")
        x = x.to(self._X)  # the model's dtype and device (float32 states with a float64 GP, or the reverse)
        if x.dim() == 2:
            x = x.expand(S, -1, -1)
        if x.dim() != 3 or x.shape[0] != S or x.shape[-1] != self._X.shape[-1]:
            raise ShapeError(
                f"x: expected (M, {self._X.shape[-1]}) or ({S}, M, {self._X.shape[-1]}) inputs, got {tuple(x.shape)}"
            )
        if not (torch.is_grad_enabled() and x.requires_grad):
            fast = self._fast_parts()
            if fast is not None:
                return self._evaluate_fast(x, fast)
        M, N = x.shape[1], self._X.shape[0]
        width = max(N, self.features.num_features)
        step = max(1, _CHUNK // max(1, M * width))  # draws per chunk: bounded memory for k(x, X) and phi(x)
        parts = []
        for s0 in range(0, S, step):
            xs = x[s0 : s0 + step]
            prior = self._prior(self.features, self._weights[s0 : s0 + step], xs)
            K = kernel_matrix(self._kind, xs.reshape(-1, xs.shape[-1]), self._X, self._params, self._degree)
            if K.shape[0] == 1:  # (1, s*M, N): shared kernel
                parts.append(torch.baddbmm(prior, K.reshape(xs.shape[0], M, N), self._v[s0 : s0 + step]))
            else:  # (d_out, s*M, N): per-output kernels
                K = K.reshape(self._d_out, xs.shape[0], M, N)
                parts.append(prior + torch.einsum("bsmn,snb->smb", K, self._v[s0 : s0 + step]))
            if self._extra is not None:
                fn, e = self._extra
                parts[-1] = parts[-1] + fn(xs) @ e[s0 : s0 + step]  # (s, M, p) @ (s, p, d_out)
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def _fast_parts(self) -> dict | None:
        """The hot path's constants for a shared RBF kernel with Fourier features (the sampled paths' case), else
        ``None``: the frequencies ``omega^T (D, d_in)``; the basis augmented as ``[Z / l^2, -|Z|^2 / (2 l^2), 1]``
        ``(N, d_in + 2)``, so that one product with ``[x; 1; -|x|^2 / (2 l^2)]`` is the exponent of
        ``k(Z, x) / s^2``; and the weights of ``[cos; sin]``, ``(S, d_out, 2 D)``, the prior weights times the
        (per-frequency) feature scales, and of ``k(Z, x) / s^2``, ``s^2 v^T (S, d_out, N)`` (the outputscale folded
        in)."""
        if self._fast is None:
            f, params = self.features, self._params
            self._fast = False
            if (
                f.kind in ("fourier", "quadrature")
                and f._t["omega"].shape[0] == 1
                and getattr(self._kind, "squared_exponential", False)
                and getattr(self._kind, "input_scale", None) is None
                and params["lengthscale"].numel() == 1
            ):
                omega, scale = f._t["omega"][0], f._t["scale"].reshape(-1, 1)  # (d_in, D), (1 or D, 1)
                w = self._weights[:, 0] * (scale if scale.shape[0] == 1 else torch.cat([scale, scale]))  # (S, 2D, o)
                l2 = params["lengthscale"].reshape(()).pow(2)
                Z = self._X
                half_sq = -0.5 * Z.pow(2).sum(-1, keepdim=True) / l2
                update = self._v * params["outputscale"].reshape(())  # (S, N, d_out)
                self._fast = {
                    "omega": omega.T.contiguous(),
                    "basis": torch.cat([Z / l2, half_sq, torch.ones_like(half_sq)], -1),
                    "half_inv_l2": -0.5 / l2,
                    "w_trig": w.transpose(1, 2).contiguous(),  # (S, d_out, 2D)
                    "w_kernel": update.transpose(1, 2).contiguous(),  # (S, d_out, N)
                }
        return self._fast or None

    def _evaluate_fast(self, x: torch.Tensor, c: dict) -> torch.Tensor:
        """``samples(x)`` for ``x (S, M, d_in)`` without autograd, in the layout ``(draws, features, points)``: per
        chunk of draws (and points), the frequencies ``omega^T x`` ``(s, D, m)``, ``[cos; sin]`` ``(s, 2 D, m)`` and
        ``k(Z, x) / s^2`` ``(s, N, m)`` are written in place into buffers, then multiplied by the weights from the
        left (``(d_out, 2 D) @ (2 D, m)``, a well-shaped product; ``(m, 2 D) @ (2 D, d_out)`` is not). The buffers
        are contiguous (a product into a strided slice would go through a copy), reused across chunks and calls (no
        fresh memory in the solver's loop) and small enough to stay in cache.

        The kernel block is ``exp(Z^T x / l^2 - |Z|^2 / (2 l^2) - |x|^2 / (2 l^2))`` in one product: the value of
        :func:`kernel_matrix`'s ``exp(-|x - Z|^2 / (2 l^2))`` up to the rounding of the exponent (which a positive
        rounding error at x = Z leaves at exp(1e-16): no clamping needed)."""
        S, M, d_in = x.shape
        D, N = c["omega"].shape[0], c["basis"].shape[0]
        F = 3 * D + N  # buffer entries per point
        step = max(1, _HOT_CHUNK // (M * F))  # draws per chunk
        points = M if step > 1 else min(M, max(1, _HOT_CHUNK // F))  # and points, when one draw is too many
        # [x; 1; -|x|^2 / (2 l^2)] as (S, d_in + 2, M) (|x|^2 by a product: a reduction over a short last dimension
        # is slow)
        sq = torch.matmul(x.square(), torch.full((d_in, 1), c["half_inv_l2"], dtype=x.dtype, device=x.device))
        xa = torch.cat([x, torch.ones_like(sq), sq], -1).transpose(1, 2)
        out = torch.empty((S, self._d_out, M), dtype=x.dtype, device=x.device)
        for s0 in range(0, S, step):
            for m0 in range(0, M, points):
                xs = xa[s0 : s0 + step, :, m0 : m0 + points]
                s, m = xs.shape[0], xs.shape[2]
                key = (s, m, x.dtype, x.device)
                if key not in self._buffers:
                    if len(self._buffers) >= 4:  # a few shapes (a solve has one or two): bounded memory
                        self._buffers.clear()
                    self._buffers[key] = tuple(
                        torch.empty((s, n, m), dtype=x.dtype, device=x.device) for n in (D, 2 * D, N)
                    )
                proj, trig, K = self._buffers[key]  # each contiguous: a product into a strided slice would copy
                torch.matmul(c["omega"], xs[:, :d_in], out=proj)  # (s, D, m)
                torch.cos(proj, out=trig[:, :D])
                torch.sin(proj, out=trig[:, D:])
                torch.matmul(c["basis"], xs, out=K).exp_()  # k(Z, x) / s^2
                o = out[s0 : s0 + s, :, m0 : m0 + m]
                if m == M:  # a contiguous slice of out
                    torch.bmm(c["w_trig"][s0 : s0 + s], trig, out=o)
                else:
                    o[...] = torch.bmm(c["w_trig"][s0 : s0 + s], trig)
                o.baddbmm_(c["w_kernel"][s0 : s0 + s], K)
        return out.transpose(1, 2).contiguous()
