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

* ``rbf``: random Fourier features, frequency pairs ``[cos(w^T x), sin(w^T x)] / sqrt(D)`` with ``w ~ N(0, I / l^2)``;
* ``matern52``: the same with ``w`` from the Matern spectral density, a multivariate Student t with 2 nu = 5
  degrees of freedom and scale ``1 / l``;
* ``polynomial``: the exact finite features of ``(c + <x, x'>)^m`` (c = 1), the monomials ``x^a`` (``|a| <= m``)
  weighted by the square roots of the multinomial coefficients times ``c^(m - |a|)``: no approximation error.

**Number of features.** With ``D`` frequency pairs the prior covariance estimate at a pair of points,
``k_hat(x, x') = s^2 / D sum_j cos(w_j^T (x - x'))``, is unbiased with variance
``s^4 ((1 + k0(2 r)) / 2 - k0(r)^2) / D <= s^4 / D`` (``k0`` the unit-scale kernel, ``r = x - x'``), and exact at
``x = x'``. :func:`frequencies_for` therefore takes ``D = ceil(1 / eps^2)`` for a root-mean-square error of at
most ``eps`` times the prior variance at every pair of points, in particular over the data's box (the default
``eps = 0.05``: D = 400, 800 features). A *uniform* bound over a box (Rahimi and Recht 2007, Claim 1) needs
``D >= 8 (d + 2) / eps^2 log(...)``, tens of thousands of frequencies for ``eps = 0.1``; it is far from tight, and
the pointwise bound is the one the package uses (the tests compare sample covariances with the exact posterior).
"""

from __future__ import annotations

import itertools
import math

import torch

from .._errors import InputError, ShapeError
from .._validation import check_positive_int, check_real
from ._features import monomials

__all__ = [
    "DEFAULT_FEATURE_ERROR",
    "FeatureMap",
    "FunctionSamples",
    "feature_map",
    "frequencies_for",
    "kernel_hyperparameters",
    "kernel_matrix",
]

#: Default bound on the root-mean-square error of the prior covariance, relative to the prior variance.
DEFAULT_FEATURE_ERROR = 0.05
#: Largest number of frequency pairs chosen automatically (a bound asking for more is refused).
MAX_FREQUENCIES = 65_536
#: Entries of k(x, X) evaluated at once (memory: 8 bytes each in float64): 2 ** 22 ~ 32 MB.
_CHUNK = 2**22


def frequencies_for(error: float) -> int:
    """Frequency pairs D for a root-mean-square prior-covariance error of at most ``error`` x the prior variance."""
    error = check_real(error, "feature_error", positive=True)
    if error >= 1.0:
        raise InputError(f"feature_error: expected a relative error in (0, 1), got {error!r}")
    D = math.ceil(1.0 / error**2)
    if D > MAX_FREQUENCIES:
        raise InputError(
            f"feature_error: {error!r} needs {D} frequency pairs, more than {MAX_FREQUENCIES}; ask for a larger error "
            "or pass num_features"
        )
    return D


class FeatureMap:
    """``phi(x)``: ``(B, ..., F)`` features of inputs ``(..., d_in)`` with ``phi(x)^T phi(x') ~ k(x, x')`` per batch
    ``b`` (B = 1 for a shared kernel, d_out for per-output kernels); output scale included.

    Attributes:
        kind: ``"fourier"`` (random, approximate) or ``"polynomial"`` (exact).
        num_features: F.
    """

    def __init__(self, kind: str, num_features: int, **tensors: torch.Tensor) -> None:
        self.kind = kind
        self.num_features = num_features
        self._t = tensors

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        t = self._t
        if self.kind == "fourier":
            omega, scale = t["omega"], t["scale"]  # (B, d_in, D), (B, 1)
            proj = torch.einsum("...i,bid->b...d", x, omega)
            shape = (omega.shape[0],) + (1,) * (proj.dim() - 1)
            return torch.cat([proj.cos(), proj.sin()], dim=-1) * scale.reshape(shape)
        powers, coef = t["powers"], t["coef"]  # (P, d_in) integer exponents, (B, P) sqrt(s^2 c_a)
        mono = (x.unsqueeze(-2) ** powers).prod(-1)  # (..., P)
        shape = (coef.shape[0],) + (1,) * (mono.dim() - 1) + (coef.shape[-1],)
        return mono.unsqueeze(0) * coef.reshape(shape)


def _check_generator(generator, device: torch.device) -> torch.Generator | None:
    if generator is None:
        return None
    if not isinstance(generator, torch.Generator):
        raise InputError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    if generator.device.type != device.type:
        raise InputError(
            f"generator: expected a generator on the GP's device ({device}), got one on {generator.device}"
        )
    return generator


def feature_map(gp, *, num_features: int | None = None, feature_error: float | None = None, generator=None):
    """The prior features of a fitted :class:`~torchmisspec.CorrectionGP`'s kernel (see the module docstring).

    Args:
        gp: a fitted CorrectionGP (RBF, Matern 5/2 or polynomial kernel; shared or per-output).
        num_features: number of Fourier features F (even: F / 2 frequency pairs); for the polynomial kernel the
            exact number is used and this must be ``None``.
        feature_error: the bound of :func:`frequencies_for` that chooses F when ``num_features`` is ``None``
            (default :data:`DEFAULT_FEATURE_ERROR`).
        generator: ``torch.Generator`` on the GP's device, for reproducible frequencies.
    """
    gp._require_fitted()
    generator = _check_generator(generator, gp.device)
    covar = gp.covar_module
    kd = dict(dtype=gp.dtype, device=gp.device)
    outputscale = covar.outputscale.detach().reshape(-1, 1).to(**kd)  # (B, 1)
    B = outputscale.shape[0]
    d_in = gp.input_dim
    if gp.kernel == "polynomial":
        if num_features is not None or feature_error is not None:
            raise InputError(
                "num_features / feature_error: the polynomial kernel has exact finite features; pass neither"
            )
        m = gp.degree
        offset = covar.base_kernel.offset.detach().reshape(-1, 1).to(**kd)  # (B, 1)
        powers, coef, rest = [], [], []
        for a in itertools.product(range(m + 1), repeat=d_in):
            if sum(a) <= m:  # (c + <x, x'>)^m = sum_a m! / ((m - |a|)! prod a_i!) c^(m - |a|) x^a x'^a
                powers.append(a)
                coef.append(math.factorial(m) / (math.factorial(m - sum(a)) * math.prod(math.factorial(i) for i in a)))
                rest.append(m - sum(a))
        P = torch.tensor(powers, **kd)
        c = torch.tensor(coef, **kd) * offset ** torch.tensor(rest, **kd)  # (B, P)
        return FeatureMap("polynomial", len(coef), powers=P, coef=(outputscale * c).sqrt())
    if gp.kernel == "features":  # exact: the monomials weighted by sqrt(outputscale w_j)
        if num_features is not None or feature_error is not None:
            raise InputError("num_features / feature_error: the feature kernel has exact finite features; pass neither")
        base = covar.base_kernel
        w = base.weights.detach().reshape(B, -1).to(**kd)
        return FeatureMap("polynomial", w.shape[-1], powers=base.powers.to(**kd), coef=(outputscale * w).sqrt())
    if gp.kernel not in ("rbf", "matern52"):
        raise InputError(
            "kernel: expected a kernel with a feature representation (rbf, matern52, polynomial, features), got "
            f"{gp.kernel!r}"
        )
    if num_features is None:
        D = frequencies_for(DEFAULT_FEATURE_ERROR if feature_error is None else feature_error)
    else:
        if feature_error is not None:
            raise InputError("num_features and feature_error: pass one of them, not both")
        F = check_positive_int(num_features, "num_features")
        if F % 2:
            raise InputError(f"num_features: expected an even number (cos and sin per frequency), got {F}")
        D = F // 2
    lengthscale = covar.base_kernel.lengthscale.detach().reshape(-1, 1, 1).to(**kd)  # (B, 1, 1)
    z = torch.randn((B, d_in, D), generator=generator, **kd)
    if gp.kernel == "matern52":  # Student t with 2 nu = 5 degrees of freedom: z sqrt(5 / chi2_5)
        chi2 = torch.randn((B, 5, D), generator=generator, **kd).pow(2).sum(1, keepdim=True)
        z = z * (5.0 / chi2).sqrt()
    omega = z / lengthscale
    return FeatureMap("fourier", 2 * D, omega=omega, scale=(outputscale / D).sqrt())


def kernel_hyperparameters(gp) -> dict[str, torch.Tensor]:
    """The GP's kernel hyperparameters as ``(B, 1, 1)`` tensors (``outputscale``; ``lengthscale``, or ``offset``
    for the polynomial kernel, or ``weights (B, 1, p)`` for the feature kernel), keeping the autograd graph to the
    GPyTorch parameters."""
    covar = gp.covar_module
    out = {"outputscale": covar.outputscale.reshape(-1, 1, 1)}
    if gp.kernel == "polynomial":  # GPyTorch's offset c of (c + <x, x'>)^m: 1 up to its constraint's rounding
        out["offset"] = covar.base_kernel.offset.reshape(-1, 1, 1)
    elif gp.kernel == "features":
        out["weights"] = covar.base_kernel.weights.reshape(out["outputscale"].shape[0], 1, -1)
        out["powers"] = covar.base_kernel.powers  # the exponents, not rebuilt at every call of kernel_matrix
    else:
        out["lengthscale"] = covar.base_kernel.lengthscale.reshape(-1, 1, 1)
    return out


def kernel_matrix(kind: str, x: torch.Tensor, X: torch.Tensor, params: dict, degree: int = 2) -> torch.Tensor:
    """``k(x, X)`` as ``(B, M, N)`` for inputs ``x (M, d)``, ``X (N, d)`` and hyperparameters ``(B, 1, 1)``: the
    same kernels as the GP's GPyTorch modules (tested against them), written out so that the hot loop of sampled
    paths needs no module calls and the hyperparameters can be constants or carry gradients."""
    s2 = params["outputscale"]
    if kind == "polynomial":
        return s2 * (params["offset"] + x @ X.T).pow(degree)
    if kind == "features":
        powers = params["powers"]
        return s2 * (monomials(x, powers) * params["weights"]) @ monomials(X, powers).T
    ell = params["lengthscale"]
    if kind == "rbf" and ell.numel() == 1 and not (x.requires_grad or ell.requires_grad or s2.requires_grad):
        # the hot path of sampled trajectories: one fused pass per operation, in place (no temporaries)
        a, b = x / ell.reshape(()), X / ell.reshape(())
        sq = torch.addmm(a.pow(2).sum(-1, keepdim=True) + b.pow(2).sum(-1), a, b.T, alpha=-2.0)
        return sq.clamp_min_(0.0).mul_(-0.5).exp_().mul_(s2.reshape(())).unsqueeze(0)
    sq = (x.pow(2).sum(-1, keepdim=True) + X.pow(2).sum(-1) - 2.0 * (x @ X.T)).clamp_min(0.0) / ell.pow(2)
    if kind == "rbf":
        return s2 * torch.exp(-0.5 * sq)
    r = (5.0 * sq).clamp_min(1e-300).sqrt() * (sq > 0)  # sqrt(5) ||x - x'|| / l, with a finite gradient at 0
    return s2 * (1.0 + r + r.pow(2) / 3.0) * torch.exp(-r)


class FunctionSamples:
    """``S`` posterior draws of F as functions: ``samples(x)`` with ``x (S, M, d_in)`` (draw s at its own points)
    or ``(M, d_in)`` (every draw at the same points) returns ``(S, M, d_out)``.

    Built by :meth:`CorrectionGP.sample_functions <torchmisspec.CorrectionGP.sample_functions>`; the GP's cached
    factorization is reused (one triangular solve pair for all draws). The draws are frozen: later changes to the
    GP do not affect them.

    With ``update_error`` (a fraction of the prior standard deviation), the update ``k(x, X) v_s`` is replaced by its
    projection on the fewest training inputs that keep a *certified* bound ``update_error * s`` on the change at any
    point (see :meth:`_compress`); ``samples.update_error`` holds the bound reached (0: exact basis).

    Attributes:
        num_samples: S.
        features: the :class:`FeatureMap` of the prior draws.
        update_error: the certified bound on the compression's error in F (0 when not compressed).
    """

    def __init__(
        self, gp, num_samples: int, features: FeatureMap, generator=None, update_error: float | None = None
    ) -> None:
        cache = gp._posterior_cache()
        X, Y, noise = gp.train_inputs_, gp.train_targets_, gp.train_noise_
        S = num_samples
        N, d_out = Y.shape
        kd = dict(dtype=gp.dtype, device=gp.device)
        with torch.no_grad():
            _, diag = gp._kernel_parts(X, noise)  # (1, 1), (1, N), (d_out, 1) or (d_out, N)
            B = features(X[:1]).shape[0]
            weights = torch.randn((S, B, features.num_features, d_out if B == 1 else 1), generator=generator, **kd)
            eps = torch.randn((S, N, d_out), generator=generator, **kd) * diag.T.sqrt()  # (S, N, d_out)
            residual = Y - self._prior(features, weights, X.expand(S, N, -1)) - eps  # (S, N, d_out)
            chol = cache.fac.chol  # (1 or d_out, N, N)
            if chol.shape[0] == 1:
                rhs = residual.permute(1, 0, 2).reshape(N, S * d_out)
                v = torch.cholesky_solve(rhs, chol[0]).reshape(N, S, d_out).permute(1, 0, 2)
            else:
                v = torch.cholesky_solve(residual.permute(2, 1, 0), chol).permute(2, 1, 0)  # (S, N, d_out)
        self.num_samples = S
        self.features = features
        self._kind, self._degree = gp.kernel, gp.degree
        with torch.no_grad():
            self._params = {k: v.detach().clone() for k, v in kernel_hyperparameters(gp).items()}
        self._X = X.detach()
        self._weights = weights
        self._v = v.contiguous()
        self._per_output = gp.per_output
        self._d_out = d_out
        #: certified bound on |update - exact update| at any point (0: the exact canonical basis is used)
        self.update_error = 0.0
        if update_error is not None and chol.shape[0] == 1 and gp.kernel in ("rbf", "matern52"):
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
        if features.kind == "fourier" and features._t["omega"].shape[0] == 1:
            # the hot path of sampled trajectories: no concatenated feature matrix, the scale folded into w
            omega, scale = features._t["omega"][0], features._t["scale"].reshape(())
            D = omega.shape[-1]
            proj = x @ omega  # (S, M, D)
            w = weights[:, 0] * scale  # (S, 2D, d_out)
            out = torch.bmm(proj.cos(), w[:, :D])
            sin = proj.sin() if proj.requires_grad else proj.sin_()  # in place unless autograd needs proj
            return torch.baddbmm(out, sin, w[:, D:])
        phi = features(x)  # (B, S, M, F)
        if phi.shape[0] == 1:
            return phi[0] @ weights[:, 0]  # (S, M, F) @ (S, F, d_out)
        return torch.einsum("bsmf,sbf->smb", phi, weights[..., 0])

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        S = self.num_samples
        if x.dim() == 2:
            x = x.expand(S, -1, -1)
        if x.dim() != 3 or x.shape[0] != S or x.shape[-1] != self._X.shape[-1]:
            raise ShapeError(
                f"x: expected (M, {self._X.shape[-1]}) or ({S}, M, {self._X.shape[-1]}) inputs, got {tuple(x.shape)}"
            )
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
        return parts[0] if len(parts) == 1 else torch.cat(parts)
