"""Kernels as objects: everything the package asks of a covariance function, in one place per kernel.

A :class:`Kernel` knows its GPyTorch module (what the fit optimises and ``gp.model`` holds), its hyperparameters as
plain tensors and its matrix written out (what sampled paths, the design and the trajectory fit evaluate without
module calls), its prior features (:mod:`torchmisspec.gp._paths`: posterior draws as functions), which of its
parameters a fit learns, and how it is saved. :class:`~torchmisspec.CorrectionGP` takes one (``kernel=RBF()``) or its
name (``kernel="rbf"``, a shorthand for the registered class with its defaults); nothing outside this module
branches on a kernel's name: the rest of the package asks the object (``gp.kernel_spec``) its traits.

Adding a kernel is a subclass and a :func:`register` (see ``tests/test_kernel_objects.py``, a rational quadratic):
a stationary kernel writes its profile ``k(r^2)`` of the squared scaled distance, its GPyTorch module and the
spectral density its random Fourier features draw from (Rahimi and Recht 2007); :class:`Stationary` does the rest.

Compare GPyTorch's ``kernels/`` (a module per kernel, hyperparameters with constraints) and tinygp's ``kernels/``
(``Stationary`` kernels as a distance and a profile): the objects here wrap GPyTorch's modules rather than replace
them, and add what the package needs beyond a covariance (features for paths, traits for the model selection).
"""

from __future__ import annotations

from typing import ClassVar

import gpytorch
import torch

from .._errors import InputError
from ._exact import log_positive
from ._fit import fit_features, fit_sum_kernel

__all__ = ["Kernel", "Stationary", "RBF", "Matern52", "Polynomial", "Features", "FeaturesRBF", "register", "as_kernel"]

#: name -> class of every registered kernel (:func:`register`)
REGISTRY: dict[str, type[Kernel]] = {}


def register(cls: type[Kernel]) -> type[Kernel]:
    """Make a kernel class available by its ``name`` (to ``CorrectionGP(kernel=name)`` and to loading saved models).
    Usable as a class decorator."""
    if not (isinstance(cls, type) and issubclass(cls, Kernel)) or not isinstance(getattr(cls, "name", None), str):
        raise InputError(f"register: expected a Kernel subclass with a string name, got {cls!r}")
    if cls.name in ("auto",):
        raise InputError(f"register: the name {cls.name!r} is reserved")
    known = REGISTRY.get(cls.name)
    if known is not None and known is not cls and known.__module__ == __name__:
        raise InputError(
            f"register: the name {cls.name!r} is the package's {known.__name__}; give {cls.__name__} a name of its own"
        )
    REGISTRY[cls.name] = cls
    return cls


def as_kernel(kernel, config: dict | None = None) -> Kernel:
    """A :class:`Kernel` from an instance (returned as is) or a registered name (its class with ``config``)."""
    if isinstance(kernel, Kernel):
        return kernel
    if isinstance(kernel, str) and kernel in REGISTRY:
        return REGISTRY[kernel](**(config or {}))
    raise InputError(
        f"kernel: expected a Kernel object or one of {(*REGISTRY, 'auto')}, got {kernel!r:.80} (a kernel of your own "
        "is a torchmisspec.gp.Kernel subclass, registered with torchmisspec.gp.register before it is named or loaded)"
    )


class Kernel:
    """What the package asks of a kernel (subclass it; the defaults describe a kernel with a lengthscale).

    Class attributes (traits the rest of the package asks instead of the name):
        name: the registry key and what ``gp.kernel`` reports.
        has_lengthscale: a lengthscale hyperparameter (``gp.lengthscale``; learned unless fixed).
        stationary: k(x, x') depends on x - x' only: the prior falls back to F = 0 away from the data (the
            model selection's safe default), the variance is the output scale everywhere, sampled updates may be
            compressed, and cross-validation may search its lengthscale.
        terms: the kernel has a weight per feature term (``gp.weights``, ``gp.terms()``; the output scale is fixed
            at 1, the weights carry it).
        shared_only: one kernel for every output (``per_output=True`` refused).
        feature_space: the posterior is factorized in feature space, O(N p^2) (the N x N matrix never formed).
    """

    name: ClassVar[str] = ""
    has_lengthscale: ClassVar[bool] = True
    stationary: ClassVar[bool] = False
    terms: ClassVar[bool] = False
    shared_only: ClassVar[bool] = False
    feature_space: ClassVar[bool] = False

    def config(self) -> dict:
        """The constructor's arguments (saved with a model, so that loading rebuilds the same kernel)."""
        return {}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.config().items())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other.config() == self.config()

    def __hash__(self) -> int:
        return hash((type(self), tuple(sorted(self.config().items()))))

    # -------------------------------------------------------------------------------------------- GPyTorch side
    def module(self, gp, batch_shape: torch.Size) -> gpytorch.kernels.Kernel:
        """The GPyTorch base kernel (without the output scale) for ``gp`` (its ``degree``, ``library`` and input
        dimension where the kernel needs them)."""
        raise NotImplementedError

    def free_parameters(self, base, fixed: dict) -> list[tuple[str, torch.nn.Parameter]]:
        """``(name, raw parameter)`` of the base kernel that a fit learns (``fixed``: the values the user fixed)."""
        if self.has_lengthscale and fixed.get("lengthscale") is None:
            return [("lengthscale", base.raw_lengthscale)]
        return []

    def fit(self, gp, X, Y, noise, *, max_iter: int) -> tuple[int, int] | None:
        """A fit of its own (``(iterations, evaluations)``), or ``None``: the generic marginal-likelihood fit."""
        return None

    def scaled_inputs(self, x: torch.Tensor) -> torch.Tensor:
        """The inputs as the kernel sees them (the same, unless a stationary kernel has an ``input_scale``)."""
        return x

    def prepare(self, gp, X) -> tuple[int, int] | None:
        """What the kernel needs from the training inputs when nothing is learned (every hyperparameter given):
        ``(0, 0)`` when it did something, ``None`` when it needs nothing (the default)."""
        return None

    # ---------------------------------------------------------------------------------------- the written-out side
    def hyperparameters(self, base, B: int) -> dict:
        """The base kernel's hyperparameters as ``(B, 1, 1)`` tensors (or what :meth:`matrix` needs), keeping the
        autograd graph to the GPyTorch parameters."""
        return {"lengthscale": base.lengthscale.reshape(-1, 1, 1)}

    def matrix(self, x: torch.Tensor, X: torch.Tensor, params: dict, degree: int) -> torch.Tensor:
        """``k(x, X)`` as ``(B, M, N)`` for inputs ``x (M, d)``, ``X (N, d)``, output scale included (tested against
        the GPyTorch module)."""
        raise NotImplementedError

    def path_features(self, gp, base, outputscale, num_features, feature_error, generator):
        """The prior :class:`~torchmisspec.gp._paths.FeatureMap` of posterior draws (``outputscale (B, 1)``)."""
        raise InputError(f"kernel: the {self.name} kernel has no feature representation for posterior draws")


class Stationary(Kernel):
    """k(x, x') = s^2 profile(|x - x'|^2 / l^2): write :meth:`profile`, :meth:`module` and :meth:`spectral`.

    ``input_scale`` (optional, one positive number per input): the kernel sees the inputs divided by it,
    ``|x / c - x' / c|^2 / l^2``, and ``l`` is in those units. The fits in the data's units write a kernel fitted on
    standardized inputs so in the user's units (:mod:`torchmisspec.gp._rescale`): an isotropic kernel on inputs of
    different scales.
    """

    stationary = True
    #: the inputs' scales (``None``: none), a tuple of floats
    input_scale: tuple[float, ...] | None = None

    def __init__(self, input_scale=None) -> None:
        self.input_scale = None if input_scale is None else _check_scale(input_scale)

    def config(self) -> dict:
        return {} if self.input_scale is None else {"input_scale": self.input_scale}

    def scaled_inputs(self, x: torch.Tensor) -> torch.Tensor:
        """The inputs as the kernel sees them (divided by :attr:`input_scale`, when it has one)."""
        if self.input_scale is None:
            return x
        cache = self.__dict__.setdefault("_scales", {})  # per dtype and device: an ODE's field calls this each step
        key = (x.dtype, x.device)
        if key not in cache:
            cache[key] = torch.tensor(self.input_scale, dtype=x.dtype, device=x.device)
        return x / cache[key]

    def _module(self, cls, **options) -> gpytorch.kernels.Kernel:
        """The GPyTorch kernel ``cls(**options)``, on inputs divided by :attr:`input_scale` when it has one."""
        if self.input_scale is None:
            return cls(**options)
        module = _SCALED[cls](**options)
        module.scaled_inputs = self.scaled_inputs
        return module

    def profile(self, sq: torch.Tensor) -> torch.Tensor:
        """k / s^2 as a function of the squared scaled distance ``sq`` (>= 0)."""
        raise NotImplementedError

    def spectral(self, shape: tuple[int, ...], generator, dtype, device) -> torch.Tensor:
        """Frequencies ``shape = (B, d_in, D)`` drawn from the kernel's spectral density at unit lengthscale."""
        raise NotImplementedError

    def matrix(self, x, X, params, degree):
        s2, ell = params["outputscale"], params["lengthscale"]
        x, X = self.scaled_inputs(x), self.scaled_inputs(X)
        sq = (x.pow(2).sum(-1, keepdim=True) + X.pow(2).sum(-1) - 2.0 * (x @ X.T)).clamp_min(0.0) / ell.pow(2)
        return s2 * self.profile(sq)

    def path_features(self, gp, base, outputscale, num_features, feature_error, generator):
        from ._paths import stationary_features

        kd = dict(dtype=gp.dtype, device=gp.device)
        B = outputscale.shape[0]
        lengthscale = base.lengthscale.detach().to(**kd).reshape(B, -1).expand(B, gp.input_dim)
        if self.input_scale is not None:  # l in the inputs' own units, per input
            lengthscale = lengthscale * torch.tensor(self.input_scale, **kd)
        return stationary_features(gp, self, lengthscale, outputscale, num_features, feature_error, generator)


@register
class RBF(Stationary):
    """exp(-|x - x'|^2 / (2 l^2)): the paper's kernel and the package's default. Its draws use quadrature features
    with a certified bound where they pay (:mod:`torchmisspec.gp._paths`)."""

    name = "rbf"
    #: the squared-exponential kernel: deterministic quadrature features and the fused hot path of sampled paths
    squared_exponential: ClassVar[bool] = True

    def module(self, gp, batch_shape):
        return self._module(gpytorch.kernels.RBFKernel, batch_shape=batch_shape, lengthscale_constraint=log_positive())

    def profile(self, sq):
        return torch.exp(-0.5 * sq)

    def spectral(self, shape, generator, dtype, device):
        return torch.randn(shape, generator=generator, dtype=dtype, device=device)

    def matrix(self, x, X, params, degree):
        s2, ell = params["outputscale"], params["lengthscale"]
        if (
            ell.numel() == 1
            and self.input_scale is None
            and not (x.requires_grad or ell.requires_grad or s2.requires_grad)
        ):
            # the hot path of sampled trajectories: one fused pass per operation, in place (no temporaries)
            a, b = x / ell.reshape(()), X / ell.reshape(())
            sq = torch.addmm(a.pow(2).sum(-1, keepdim=True) + b.pow(2).sum(-1), a, b.T, alpha=-2.0)
            return sq.clamp_min_(0.0).mul_(-0.5).exp_().mul_(s2.reshape(())).unsqueeze(0)
        return super().matrix(x, X, params, degree)


@register
class Matern52(Stationary):
    """(1 + r + r^2 / 3) exp(-r) with r = sqrt(5) |x - x'| / l: rougher draws than the RBF's."""

    name = "matern52"

    def module(self, gp, batch_shape):
        options = dict(nu=2.5, batch_shape=batch_shape, lengthscale_constraint=log_positive())
        return self._module(gpytorch.kernels.MaternKernel, **options)

    def profile(self, sq):
        r = (5.0 * sq).clamp_min(1e-300).sqrt() * (sq > 0)  # sqrt(5) ||x - x'|| / l, with a finite gradient at 0
        return (1.0 + r + r.pow(2) / 3.0) * torch.exp(-r)

    def spectral(self, shape, generator, dtype, device):
        # Student t with 2 nu = 5 degrees of freedom: z sqrt(5 / chi2_5)
        B, _, D = shape
        z = torch.randn(shape, generator=generator, dtype=dtype, device=device)
        chi2 = torch.randn((B, 5, D), generator=generator, dtype=dtype, device=device).pow(2).sum(1, keepdim=True)
        return z * (5.0 / chi2).sqrt()


@register
class Polynomial(Kernel):
    """(1 + <x, x'>)^m, the paper's polynomial kernel (m = ``gp.degree``); exact finite features."""

    name = "polynomial"
    has_lengthscale = False

    def module(self, gp, batch_shape):
        base = gpytorch.kernels.PolynomialKernel(power=gp.degree, batch_shape=batch_shape)
        base.offset = 1.0
        base.raw_offset.requires_grad_(False)
        return base

    def hyperparameters(self, base, B):
        # GPyTorch's offset c of (c + <x, x'>)^m: 1 up to its constraint's rounding
        return {"offset": base.offset.reshape(-1, 1, 1)}

    def matrix(self, x, X, params, degree):
        return params["outputscale"] * (params["offset"] + x @ X.T).pow(degree)

    def path_features(self, gp, base, outputscale, num_features, feature_error, generator):
        from ._paths import polynomial_features

        if num_features is not None or feature_error is not None:
            raise InputError(
                "num_features / feature_error: expected neither (the polynomial kernel has exact finite features), "
                f"got {num_features!r} / {feature_error!r}"
            )
        return polynomial_features(gp, base, outputscale)


@register
class Features(Kernel):
    """sum_j w_j phi_j(x) phi_j(x') over the monomials up to ``gp.degree`` (or a user library): one learned weight
    per term and output, fitted in feature space with a price per term (:mod:`torchmisspec.gp._features`)."""

    name = "features"
    has_lengthscale = False
    terms = True
    feature_space = True

    def module(self, gp, batch_shape):
        from ._features import FeatureKernel

        lib = {"library": gp.library, "library_names": gp.library_names}
        return FeatureKernel(gp._d_in, gp.degree, batch_shape=batch_shape, **lib)

    def free_parameters(self, base, fixed):
        return [("weights", base.weights)]

    def fit(self, gp, X, Y, noise, *, max_iter):
        iterations = fit_features(gp, X, Y, noise, max_iter=max_iter)
        return iterations, iterations

    def hyperparameters(self, base, B):
        # phi(x): the monomials or a user library (not a tensor)
        return {"weights": base.weights.reshape(B, 1, -1), "features": base.features}

    def matrix(self, x, X, params, degree):
        phi = params["features"]
        return params["outputscale"] * (phi(x) * params["weights"]) @ phi(X).T

    def path_features(self, gp, base, outputscale, num_features, feature_error, generator):
        from ._paths import FeatureMap

        if num_features is not None or feature_error is not None:
            raise InputError(
                "num_features / feature_error: expected neither (the feature kernel has exact finite features), got "
                f"{num_features!r} / {feature_error!r}"
            )
        w = base.weights.detach().reshape(outputscale.shape[0], -1).to(outputscale)
        return FeatureMap("library", w.shape[-1], fn=base.features, coef=(outputscale * w).sqrt())


@register
class FeaturesRBF(Features):
    """The feature library plus an RBF term for what it misses (:mod:`torchmisspec.gp._sum`); shared by the
    outputs. ``kernel="auto"`` uses it to test whether the library suffices."""

    name = "features+rbf"
    has_lengthscale = True
    shared_only = True
    feature_space = False

    def module(self, gp, batch_shape):
        from ._sum import FeaturesPlusRBF

        return FeaturesPlusRBF(gp._d_in, gp.degree, library=gp.library, library_names=gp.library_names)

    def free_parameters(self, base, fixed):
        out = [("weights", base.weights), ("rbf_scale", base.raw_rbf_scale)]
        if fixed.get("lengthscale") is None:
            out.append(("lengthscale", base.raw_lengthscale))
        return out

    def fit(self, gp, X, Y, noise, *, max_iter):
        return fit_sum_kernel(gp, X, Y, noise, max_iter=max_iter)

    def hyperparameters(self, base, B):
        out = super().hyperparameters(base, B)
        out["lengthscale"] = base.lengthscale.reshape(-1, 1, 1)
        out["rbf_scale"] = base.rbf_scale.reshape(-1, 1, 1)
        return out

    def matrix(self, x, X, params, degree):
        poly = super().matrix(x, X, params, degree)
        rbf = {"outputscale": params["outputscale"] * params["rbf_scale"], "lengthscale": params["lengthscale"]}
        return poly + RBF().matrix(x, X, rbf, degree)

    def path_features(self, gp, base, outputscale, num_features, feature_error, generator):
        from ._paths import FeatureMap, stationary_features

        kd = dict(dtype=gp.dtype, device=gp.device)
        B = outputscale.shape[0]
        w = base.weights.detach().reshape(B, -1).to(**kd)
        poly = FeatureMap("library", w.shape[-1], fn=base.features, coef=(outputscale * w).sqrt())
        rbf = stationary_features(
            gp,
            RBF(),
            base.lengthscale.detach().to(**kd).reshape(B, -1).expand(B, gp.input_dim),
            outputscale * base.rbf_scale.detach().to(**kd).reshape(B, 1),
            num_features,
            feature_error,
            generator,
        )
        return FeatureMap(
            "sum", poly.num_features + rbf.num_features, error_bound=rbf.error_bound, box=rbf.box, parts=(poly, rbf)
        )


def _check_scale(value) -> tuple[float, ...]:
    """``input_scale`` as a tuple of positive finite floats (a saved kernel's plain values)."""
    try:
        scale = tuple(float(v) for v in torch.as_tensor(value, dtype=torch.float64).reshape(-1).tolist())
    except (TypeError, ValueError, RuntimeError):
        scale = ()
    if not scale or not all(v > 0 and v < float("inf") for v in scale):
        raise InputError(f"input_scale: expected one positive finite number per input, got {value!r:.80}")
    return scale


class _InputScaled:
    """A GPyTorch stationary kernel on inputs divided by its kernel object's ``input_scale`` (``scaled_inputs``, set
    when it is built: not a parameter or buffer, so its state is the plain kernel's)."""

    def forward(self, x1, x2, **params):
        return super().forward(self.scaled_inputs(x1), self.scaled_inputs(x2), **params)


class _ScaledRBF(_InputScaled, gpytorch.kernels.RBFKernel):
    pass


class _ScaledMatern(_InputScaled, gpytorch.kernels.MaternKernel):
    pass


_SCALED = {gpytorch.kernels.RBFKernel: _ScaledRBF, gpytorch.kernels.MaternKernel: _ScaledMatern}
