"""Many samples: the RBF kernel in a feature space of quadrature (or random) Fourier features.

The exact GP factorizes the N x N training covariance, O(N^3) time and O(N^2) memory (a fit on 5,000 samples took
207 s and 1.35 GB). ``CorrectionGP(kernel="rbf-quadrature")`` keeps the RBF model and changes how it is computed:

1. **Hyperparameters** (lengthscale, output scale, noise) by the exact marginal likelihood of an evenly spaced
   subsample of ``subsample`` samples (the exact fit, warm start and all; the values given are kept fixed).
2. **Features.** ``k(x, x') ~ s^2 phi(x)^T phi(x')`` with the pruned tensor Gauss-Hermite rule of
   :mod:`torchmisspec.gp._quadrature` for that lengthscale, whose error is certified: ``|k_hat - k| <= error s^2``
   uniformly on the training inputs' box widened by its own width on each side (``feature_error``, default 1e-2).
   Where no such rule has at most as many frequency pairs as random features at the same bound would (high input
   dimension), random Fourier features at that root-mean-square bound are used instead (Rahimi and Recht 2007).
3. **Posterior** of all N samples in feature space (:class:`~torchmisspec.gp._features.FeatureFactorization`):
   ``O(N p^2 + p^3)`` time and ``O(N p)`` memory for p features; predictions cost p per input, not N.

The approximation is reported, not hidden: ``gp.approximation`` gives the kind of features, their number, the
certified (or root-mean-square) bound, its box and the subsample. ``CorrectionGP(kernel="rbf")`` (the default) uses
it above :data:`LARGE_N` samples; ``exact=True`` keeps the exact GP at any N, ``exact=False`` uses the features at
any N.
"""

from __future__ import annotations

import gpytorch
import torch

from .._errors import InputError
from ._kernels import RBF, Kernel, register
from ._quadrature import QUADRATURE_FEATURE_ERROR, _check_error

__all__ = ["RBFQuadrature", "QuadratureRBFModule", "SUBSAMPLE", "LARGE_N"]

#: Above this many samples ``CorrectionGP(kernel="rbf")`` is fitted in the feature space (``exact=None``): where the
#: exact fit becomes slower than the subsample's fit plus the features (BENCHMARKS.md, ``benchmark_large_fit.py``).
LARGE_N = 3000
#: Samples of the exact fit that sets the hyperparameters (evenly spaced over the training samples).
SUBSAMPLE = 2000


class QuadratureRBFModule(gpytorch.kernels.Kernel):
    """``phi(x)^T phi(x')`` with ``phi(x) = sqrt(c_j) [cos(w_j^T x), sin(w_j^T x)]`` (the output scale is the
    :class:`~gpytorch.kernels.ScaleKernel`'s): the features are set by :meth:`set_features` (the fit or a load)."""

    has_lengthscale = False  # the lengthscale is a buffer set with the features, not a GPyTorch parameter

    def __init__(self, batch_shape: torch.Size | None = None) -> None:
        super().__init__(batch_shape=torch.Size() if batch_shape is None else batch_shape)
        self.register_buffer("omega", torch.zeros(0, 0))  # (d_in, D): frequencies w_j = z_j / lengthscale
        self.register_buffer("mass", torch.zeros(0))  # (D,): sqrt(c_j)
        self.register_buffer("length", torch.ones(1))  # the RBF lengthscale the features are for
        self.register_buffer("bound", torch.zeros(1))  # the error bound reached (relative to the prior variance)
        self.register_buffer("box", torch.zeros(2, 0))  # (2, d_in): the box of a certified bound; empty: random
        self.spread = None  # no term is uncertain (the posterior's interface for the feature kernels)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        for name in ("omega", "mass", "box"):  # the number of features is the saved model's
            key = prefix + name
            if key in state_dict:
                setattr(self, name, torch.empty_like(state_dict[key]).to(getattr(self, name)))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def set_features(self, omega: torch.Tensor, mass: torch.Tensor, lengthscale: float, bound: float, box) -> None:
        self.omega, self.mass = omega.detach().clone(), mass.detach().clone()
        self.length = torch.full((1,), float(lengthscale), dtype=omega.dtype, device=omega.device)
        self.bound = torch.full((1,), float(bound), dtype=omega.dtype, device=omega.device)
        self.box = torch.zeros(2, 0, dtype=omega.dtype, device=omega.device) if box is None else box.detach().clone()

    def describe(self) -> dict:
        """The features in plain values (``gp.approximation``)."""
        certified = self.box.shape[-1] > 0
        return {
            "kind": "quadrature" if certified else "random",
            "num_features": 2 * self.mass.shape[0],
            "error_bound": float(self.bound),
            "box": self.box.tolist() if certified else None,
        }

    @property
    def lengthscale(self) -> torch.Tensor:
        return self.length.reshape(1, 1)

    @lengthscale.setter
    def lengthscale(self, value) -> None:  # a fixed lengthscale (the features are set for it by the fit)
        self.length = torch.as_tensor(value, dtype=self.length.dtype, device=self.length.device).reshape(1).clone()

    @property
    def weights(self) -> torch.Tensor:
        """One weight per feature (the output scale multiplies them in the posterior)."""
        return torch.ones(1, 2 * self.mass.shape[0], dtype=self.mass.dtype, device=self.mass.device)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., M, 2 D)`` features of ``x (..., M, d_in)``."""
        if self.omega.shape[0] != x.shape[-1]:
            raise InputError(
                f"x: expected inputs with {self.omega.shape[0]} columns (the features' dimension), got {x.shape[-1]}"
            )
        proj = x @ self.omega
        return torch.cat([proj.cos() * self.mass, proj.sin() * self.mass], dim=-1)

    def forward(self, x1, x2, diag: bool = False, last_dim_is_batch: bool = False, **params):
        f1 = self.features(x1)
        if diag:
            if x2 is x1 or torch.equal(x1, x2):
                return f1.pow(2).sum(-1)
            return (f1 * self.features(x2)).sum(-1)
        return f1 @ self.features(x2).transpose(-1, -2)


@register
class RBFQuadrature(Kernel):
    """The RBF kernel computed in a feature space for many samples (module docstring): hyperparameters from an exact
    fit on ``subsample`` samples, features with the certified bound ``feature_error``, the posterior of all."""

    name = "rbf-quadrature"
    has_lengthscale = True
    stationary = True
    shared_only = True
    feature_space = True

    def __init__(self, feature_error: float = QUADRATURE_FEATURE_ERROR, subsample: int = SUBSAMPLE) -> None:
        from .._validation import check_positive_int

        self.feature_error = _check_error(feature_error)
        self.subsample = check_positive_int(subsample, "subsample", minimum=10)

    def config(self) -> dict:
        return {"feature_error": self.feature_error, "subsample": self.subsample}

    def module(self, gp, batch_shape):
        return QuadratureRBFModule(batch_shape)

    def free_parameters(self, base, fixed):
        return []  # the lengthscale comes from the subsample's exact fit (fit), not from an optimiser here

    def fit(self, gp, X, Y, noise, *, max_iter):
        """The exact RBF fit on an evenly spaced subsample, then the features for its lengthscale."""
        n = X.shape[0]
        sub = torch.linspace(0, n - 1, min(n, self.subsample), device=X.device).round().long()
        exact = type(gp)(kernel="rbf", max_iter=max_iter, dtype=gp.dtype, device=gp.device, **gp.fixed)
        exact.fit(X[sub], Y[sub], noise=None if noise is None else noise[sub])
        with torch.no_grad():
            gp.covar_module.outputscale = torch.as_tensor(exact.outputscale, dtype=gp.dtype, device=gp.device)
            gp._floor(gp.likelihood).noise = torch.as_tensor(
                exact.noise_variance, dtype=gp.dtype, device=gp.device
            ).reshape(1)
        self.prepare(gp, X, lengthscale=float(exact.lengthscale))
        return exact.n_iterations_, exact.n_evaluations_

    def prepare(self, gp, X, *, lengthscale: float | None = None):
        """The features for ``lengthscale`` (default: the fixed one) on the training inputs ``X``."""
        from ._paths import stationary_features

        if lengthscale is None:
            if gp.fixed["lengthscale"] is None:
                raise InputError("lengthscale: expected a fixed lengthscale to compute the features without a fit")
            lengthscale = float(gp.fixed["lengthscale"])
        kd = dict(dtype=gp.dtype, device=gp.device)
        ls = torch.full((1, X.shape[1]), lengthscale, **kd)
        one = torch.ones(1, 1, **kd)  # the output scale is the ScaleKernel's
        fmap = stationary_features(gp, RBF(), ls, one, None, self.feature_error, None)
        omega, scale = fmap._t["omega"][0], fmap._t["scale"][0]  # (d_in, D), (D,) or (1,)
        mass = scale.expand(omega.shape[1]).contiguous()
        gp.covar_module.base_kernel.set_features(omega, mass, lengthscale, fmap.error_bound, fmap.box)
        return 0, 0

    def hyperparameters(self, base, B):
        return {"weights": base.weights.reshape(B, 1, -1), "features": base.features}

    def matrix(self, x, X, params, degree):
        phi = params["features"]
        return params["outputscale"] * (phi(x) * params["weights"]) @ phi(X).transpose(-1, -2)

    def path_features(self, gp, base, outputscale, num_features, feature_error, generator):
        from ._paths import FeatureMap

        if num_features is not None or feature_error is not None:
            raise InputError(
                "num_features / feature_error: expected neither (this kernel's features are those of the fit), got "
                f"{num_features!r} / {feature_error!r}"
            )
        ones = base.weights.reshape(outputscale.shape[0], -1).to(outputscale)
        return FeatureMap("library", ones.shape[-1], fn=base.features, coef=(outputscale * ones).sqrt())
