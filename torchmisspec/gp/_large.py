"""Many samples: the RBF kernel in a feature space (quadrature Fourier features, or Nystrom features), and the
Matern 5/2 kernel (Nystrom features, :class:`Matern52Features`).

The exact GP factorizes the N x N training covariance, O(N^3) time and O(N^2) memory (a fit on 5,000 samples took
207 s and 1.35 GB). ``CorrectionGP(kernel="rbf-features")`` keeps the RBF model and changes how it is computed:

1. **Hyperparameters** (lengthscale, output scale, noise) by the exact marginal likelihood of an evenly spaced
   subsample of ``subsample`` samples (the exact fit, warm start and all; the values given are kept fixed).
2. **Features** ``phi`` with ``k(x, x') ~ s^2 phi(x)^T phi(x')``, the fewer of two kinds at the same tolerance:

   * *quadrature*: the pruned tensor Gauss-Hermite rule of :mod:`torchmisspec.gp._quadrature` for that lengthscale,
     ``|k_hat - k| <= error s^2`` certified uniformly on the training inputs' box widened by its own width on each
     side. Few features in one or two dimensions; the tensor grid grows as m^d.
   * *Nystrom*: ``phi(x) = L_Z^-1 k(Z, x) / s`` on pivots Z chosen by pivoted Cholesky of the subsample until its
     residual variance is at most ``error s^2``. The residual ``r(x) = k(x, x) - s^2 |phi(x)|^2 >= 0`` is computed
     at every training input, and ``|k_hat(x, x') - k(x, x')| <= sqrt(r(x) r(x'))`` (Cauchy-Schwarz for the PSD
     residual) certifies the largest one over the data. Grows with the data's effective dimension, not as m^d.

   ``error`` defaults to a tenth of the noise-to-signal ratio ``sigma^2 / s^2`` (within [1e-8, 1e-2]): the kernel
   error then stays below what the noise lets the data resolve. Measured on a 4-input F with 4,000 samples
   (BENCHMARKS.md): Nystrom pivots at 1e-6 (447) gave 1.05x the exact GP's error, at 1e-7 (601) 1.004x; the
   quadrature rule at 1e-2 needed 3,558 features and gave 1.14x.
3. **Posterior** of all N samples in feature space (:class:`~torchmisspec.gp._features.FeatureFactorization`):
   ``O(N p^2 + p^3)`` time and ``O(N p)`` memory for p features; predictions cost p per input, not N.

The approximation is reported, not hidden: ``gp.approximation`` gives the kind of features, their number, the bound
and where it holds. ``CorrectionGP(kernel="rbf")`` (the default) and ``kernel="matern52"`` use it above
:data:`LARGE_N` samples; ``exact=True`` keeps the exact GP at any N, ``exact=False`` uses the features at any N.
"""

from __future__ import annotations

import gpytorch
import torch

from .._errors import InputError
from .._linalg import cholesky, pivots
from .._validation import check_positive_int
from ._kernels import Kernel, register
from ._quadrature import _check_error

__all__ = ["RBFFeatures", "Matern52Features", "RBFFeatureModule", "SUBSAMPLE", "LARGE_N", "MAX_FEATURES"]

#: Above this many samples ``CorrectionGP(kernel="rbf")`` is fitted in the feature space (``exact=None``): where the
#: exact fit becomes slower than the subsample's fit plus the features (BENCHMARKS.md, ``benchmark_large_fit.py``).
LARGE_N = 3000
#: Samples of the exact fit that sets the hyperparameters (evenly spaced over the training samples).
SUBSAMPLE = 2000
#: Most features (memory 8 N p bytes for N samples: 1.6 GB at N = 10^5).
MAX_FEATURES = 2048
_KINDS = ("quadrature", "random", "nystrom")
#: rows of inputs whose Nystrom features are computed at once (the kernel block and its temporaries)
_ROWS = 8192
#: the kernels the Nystrom features compute (the quadrature rule is the RBF's)
_PROFILES = ("rbf", "matern52")


class RBFFeatureModule(gpytorch.kernels.Kernel):
    """``phi(x)^T phi(x')`` for the features set by :meth:`set_fourier` or :meth:`set_nystrom` (the fit, or a load);
    the output scale is the :class:`~gpytorch.kernels.ScaleKernel`'s."""

    has_lengthscale = False  # the lengthscale is a buffer set with the features, not a GPyTorch parameter

    def __init__(self, batch_shape: torch.Size | None = None) -> None:
        super().__init__(batch_shape=torch.Size() if batch_shape is None else batch_shape)
        self.register_buffer("kind", torch.zeros(1, dtype=torch.long))  # index into _KINDS
        self.register_buffer("omega", torch.zeros(0, 0))  # Fourier: (d_in, D) frequencies w_j = z_j / lengthscale
        self.register_buffer("mass", torch.zeros(0))  # Fourier: (D,) sqrt(c_j)
        self.register_buffer("pivots", torch.zeros(0, 0))  # Nystrom: (M, d_in) the points Z
        self.register_buffer("factor", torch.zeros(0, 0))  # Nystrom: (M, M) L_Z, L_Z L_Z^T = k(Z, Z) / s^2
        self.register_buffer("length", torch.ones(1))  # the lengthscale the features are for
        self.register_buffer("profile", torch.zeros(1, dtype=torch.long))  # Nystrom: the kernel, into _PROFILES
        self.register_buffer("bound", torch.zeros(1))  # the error bound reached (relative to the prior variance)
        self.register_buffer("box", torch.zeros(2, 0))  # (2, d_in): where a quadrature bound holds; else empty
        self.spread = None  # no term is uncertain (the posterior's interface for the feature kernels)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        state_dict.setdefault(prefix + "profile", torch.zeros(1, dtype=torch.long))  # files from before Matern: RBF
        for name in ("omega", "mass", "pivots", "factor", "box"):  # the number of features is the saved model's
            key = prefix + name
            if key in state_dict:
                setattr(self, name, torch.empty_like(state_dict[key]).to(getattr(self, name)))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _set(self, kind: str, lengthscale: float, bound: float, **tensors) -> None:
        like = next(iter(tensors.values()))
        self.kind = torch.tensor([_KINDS.index(kind)], device=like.device)
        self.length = torch.full((1,), float(lengthscale), dtype=like.dtype, device=like.device)
        self.bound = torch.full((1,), float(bound), dtype=like.dtype, device=like.device)
        empty = like.new_zeros(0, 0)
        self.omega, self.mass, self.pivots, self.factor = empty, like.new_zeros(0), empty, empty
        self.box = like.new_zeros(2, 0)
        for name, value in tensors.items():
            setattr(self, name, value.detach().clone())

    def set_fourier(self, omega, mass, lengthscale: float, bound: float, box) -> None:
        kind = "quadrature" if box is not None else "random"
        extra = {} if box is None else {"box": box}
        self._set(kind, lengthscale, bound, omega=omega, mass=mass, **extra)

    def set_nystrom(self, pivots, factor, lengthscale: float, bound: float, profile: str = "rbf") -> None:
        self._set("nystrom", lengthscale, bound, pivots=pivots, factor=factor)
        self.profile = torch.tensor([_PROFILES.index(profile)], device=pivots.device)

    @property
    def kind_name(self) -> str:
        return _KINDS[int(self.kind)]

    @property
    def num_features(self) -> int:
        return self.pivots.shape[0] if self.kind_name == "nystrom" else 2 * self.mass.shape[0]

    def describe(self) -> dict:
        """The features in plain values (``gp.approximation``): where the bound holds is ``box`` for quadrature
        (certified uniformly there), the training inputs for Nystrom (certified at them), every pair of points in
        root mean square for random features."""
        name = self.kind_name
        where = {"quadrature": "box", "nystrom": "training inputs", "random": "root mean square"}[name]
        return {
            "kind": name,
            "num_features": self.num_features,
            "error_bound": float(self.bound),
            "bound_holds_on": where,
            "box": self.box.tolist() if name == "quadrature" else None,
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
        return torch.ones(1, self.num_features, dtype=self.length.dtype, device=self.length.device)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., M, p)`` features of ``x (..., M, d_in)``."""
        d = self.pivots.shape[-1] if self.kind_name == "nystrom" else self.omega.shape[0]
        if d != x.shape[-1]:
            raise InputError(f"x: expected inputs with {d} columns (the features' dimension), got {x.shape[-1]}")
        if self.kind_name == "nystrom":
            if x.dim() == 2 and x.shape[0] > _ROWS:  # in blocks of rows: the kernel's temporaries stay small
                return torch.cat([self.features(x[s : s + _ROWS]) for s in range(0, x.shape[0], _ROWS)])
            K = unit_kernel(_PROFILES[int(self.profile)], self.pivots, x, float(self.length))  # (..., M, N)
            return torch.linalg.solve_triangular(self.factor, K, upper=False).transpose(-1, -2)
        proj = x @ self.omega
        return torch.cat([proj.cos() * self.mass, proj.sin() * self.mass], dim=-1)

    def forward(self, x1, x2, diag: bool = False, last_dim_is_batch: bool = False, **params):
        f1 = self.features(x1)
        if diag:
            if x2 is x1 or torch.equal(x1, x2):
                return f1.pow(2).sum(-1)
            return (f1 * self.features(x2)).sum(-1)
        return f1 @ self.features(x2).transpose(-1, -2)


def rbf_unit(a: torch.Tensor, b: torch.Tensor, lengthscale: float) -> torch.Tensor:
    """``exp(-|a_i - b_j|^2 / (2 l^2))`` ``(..., M, N)`` (output scale 1), from squared norms (no cdist graph)."""
    sq = (a * a).sum(-1).unsqueeze(-1) + (b * b).sum(-1).unsqueeze(-2) - 2.0 * a @ b.transpose(-1, -2)
    return torch.exp(-sq.clamp_min(0.0) / (2.0 * lengthscale * lengthscale))


def unit_kernel(profile: str, a: torch.Tensor, b: torch.Tensor, lengthscale: float) -> torch.Tensor:
    """The unit-scale ``profile`` kernel (``"rbf"`` or ``"matern52"``, see :mod:`._kernels`) ``(..., M, N)``."""
    if profile == "rbf":
        return rbf_unit(a, b, lengthscale)
    sq = (a * a).sum(-1).unsqueeze(-1) + (b * b).sum(-1).unsqueeze(-2) - 2.0 * a @ b.transpose(-1, -2)
    r = (5.0 * sq.clamp_min(0.0)).sqrt() / lengthscale
    return (1.0 + r + r * r / 3.0) * torch.exp(-r)


class _Unit:
    """A unit-scale kernel as :func:`~torchmisspec._linalg.pivots` asks for it."""

    def __init__(self, profile: str, lengthscale: float) -> None:
        self.profile, self.lengthscale = profile, lengthscale

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return unit_kernel(self.profile, a, b, self.lengthscale)

    def diag(self, a: torch.Tensor) -> torch.Tensor:
        return torch.ones(a.shape[0], dtype=a.dtype, device=a.device)


def nystrom(X: torch.Tensor, sub: torch.Tensor, lengthscale: float, error: float, most: int, profile: str = "rbf"):
    """Pivots Z of the subsample ``sub`` (greedy pivoted Cholesky of the unit-scale kernel until the residual
    variance is at most ``error`` or ``most`` pivots) and the factor L_Z; the bound: the largest residual over ``X``
    (the residual is PSD for any kernel, so the bound holds for the Matern kernel as for the RBF)."""
    piv, _ = pivots(_Unit(profile, lengthscale), sub, most, error)
    Z = sub[piv]
    LZ = cholesky(unit_kernel(profile, Z, Z, lengthscale), what="k(Z, Z) (Nystrom pivots)")
    worst = 0.0
    for s in range(0, X.shape[0], 16384):  # the residual at every training input: the certified bound on the data
        phi = torch.linalg.solve_triangular(LZ, unit_kernel(profile, Z, X[s : s + 16384], lengthscale), upper=False)
        worst = max(worst, float((1.0 - phi.pow(2).sum(0)).max()))
    return Z, LZ, max(worst, 0.0) + 64 * Z.shape[0] * torch.finfo(X.dtype).eps


@register
class RBFFeatures(Kernel):
    """The RBF kernel computed in a feature space for many samples (module docstring): hyperparameters from an exact
    fit on ``subsample`` samples, then quadrature or Nystrom features (the fewer) at ``feature_error`` (default:
    a tenth of the noise-to-signal ratio, within [1e-8, 1e-2]), the posterior of all samples."""

    name = "rbf-features"
    exact_kernel = "rbf"  # the kernel computed, and fitted exactly on the subsample
    has_lengthscale = True
    stationary = True
    shared_only = True
    feature_space = True

    def __init__(self, feature_error: float | None = None, subsample: int = SUBSAMPLE) -> None:
        self.feature_error = None if feature_error is None else _check_error(feature_error)
        self.subsample = check_positive_int(subsample, "subsample", minimum=10)

    def config(self) -> dict:
        return {"feature_error": self.feature_error, "subsample": self.subsample}

    def module(self, gp, batch_shape):
        return RBFFeatureModule(batch_shape)

    def free_parameters(self, base, fixed):
        return []  # the lengthscale comes from the subsample's exact fit (fit), not from an optimiser here

    def _subsample(self, X: torch.Tensor) -> torch.Tensor:
        n = X.shape[0]
        return torch.linspace(0, n - 1, min(n, self.subsample), device=X.device).round().long()

    def fit(self, gp, X, Y, noise, *, max_iter):
        """The exact RBF fit on an evenly spaced subsample, then the features for its lengthscale."""
        sub = self._subsample(X)
        exact = type(gp)(
            kernel=self.exact_kernel, max_iter=max_iter, dtype=gp.dtype, device=gp.device, exact=True, **gp.fixed
        )
        exact.fit(X[sub], Y[sub], noise=None if noise is None else noise[sub])
        with torch.no_grad():
            gp.covar_module.outputscale = torch.as_tensor(exact.outputscale, dtype=gp.dtype, device=gp.device)
            gp._floor(gp.likelihood).noise = torch.as_tensor(
                exact.noise_variance, dtype=gp.dtype, device=gp.device
            ).reshape(1)
        self._features(gp, X, float(exact.lengthscale))
        return exact.n_iterations_, exact.n_evaluations_

    def prepare(self, gp, X):
        """Every hyperparameter given (or kept, by ``gp.condition``): the features for them on these inputs, so that
        the certified bound holds where the new inputs are."""
        ell = gp.fixed.get("lengthscale")
        self._features(gp, X, float(gp.covar_module.base_kernel.lengthscale if ell is None else ell))
        return 0, 0

    #: the default tolerance's floor (a tenth of the noise-to-signal ratio, within [floor, 1e-2])
    error_floor = 1e-8

    def _error(self, gp) -> float:
        """The tolerance: ``feature_error``, or a tenth of the noise-to-signal ratio within [error_floor, 1e-2]."""
        if self.feature_error is not None:
            return self.feature_error
        s2 = float(gp.covar_module.outputscale.detach().reshape(-1)[0])
        s2n = float(gp._floor(gp.likelihood).noise.detach().reshape(-1)[0])
        return min(max(0.1 * s2n / s2, self.error_floor), 1e-2)

    def _features(self, gp, X: torch.Tensor, lengthscale: float) -> None:
        """Quadrature or Nystrom features (the fewer) at the tolerance, on ``gp``'s base kernel."""
        from ._paths import _quadrature_features

        error = self._error(gp)
        kd = dict(dtype=gp.dtype, device=gp.device)
        ls = torch.full((1, X.shape[1]), lengthscale, **kd)
        quad = _quadrature_features(X, ls, torch.ones(1, 1, **kd), error)
        base = gp.covar_module.base_kernel
        if quad is not None and quad.num_features <= min(64, MAX_FEATURES):  # few: no need to look further
            base.set_fourier(quad._t["omega"][0], quad._t["scale"][0], lengthscale, quad.error_bound, quad.box)
            return
        Z, LZ, bound = nystrom(X, X[self._subsample(X)], lengthscale, error, MAX_FEATURES)
        if quad is not None and quad.num_features <= Z.shape[0]:
            base.set_fourier(quad._t["omega"][0], quad._t["scale"][0], lengthscale, quad.error_bound, quad.box)
        else:
            base.set_nystrom(Z, LZ, lengthscale, bound)

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


@register
class Matern52Features(RBFFeatures):
    """The Matern 5/2 kernel computed in a feature space for many samples: as :class:`RBFFeatures`, with Nystrom
    features only (the quadrature rule is the RBF's; the Nystrom bound holds for any kernel)."""

    name = "matern52-features"
    exact_kernel = "matern52"
    # the Matern 5/2 fit of a smooth F takes long lengthscales and large output scales, so its noise-to-signal
    # ratio is tiny (2e-12 on paper 5.1's F): at the RBF's floor of 1e-8 its 6 pivots gave 16x the exact GP's error,
    # at 1e-12 32 pivots 0.8x (pivoted Cholesky in float64 reaches that, the quadrature rule would not)
    error_floor = 1e-12

    def _features(self, gp, X: torch.Tensor, lengthscale: float) -> None:
        base = gp.covar_module.base_kernel
        Z, LZ, bound = nystrom(X, X[self._subsample(X)], lengthscale, self._error(gp), MAX_FEATURES, "matern52")
        base.set_nystrom(Z, LZ, lengthscale, bound, "matern52")
