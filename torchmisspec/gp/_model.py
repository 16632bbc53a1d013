"""The correction model: a Gaussian process for F with independent outputs sharing one kernel (paper §3.1).

F ~ GP(0, k(y, y') I_{d_out}). Because the kernel is shared, the d_out outputs have the same covariance
K + sigma^2 I, so **one** Cholesky factorization serves all of them, in the marginal likelihood as in the
posterior. The hyperparameters and the training data live in a GPyTorch ``ExactGP`` (``gp.model``: a batch of
d_out independent outputs, GPyTorch kernels, likelihood and constraints). Two choices depart from GPyTorch's
defaults, on purpose:

* Training maximises the exact log marginal likelihood with one Cholesky of the shared N x N covariance and an
  analytic gradient (:mod:`torchmisspec.gp._mll`). GPyTorch's ``ExactMarginalLogLikelihood`` would factorize the
  same matrix once per output and, above 800 points, switch to conjugate gradients and stochastic Lanczos.
* The posterior solve alpha = (K + sigma^2 I)^-1 Y and the Cholesky factor are cached; ``predict_mean`` then costs
  one kernel block k(x, X) @ alpha, which is what an ODE right-hand side needs. The cache is keyed by the values of
  every parameter and buffer of ``gp.model`` and by the identity and version of its training tensors: a change of
  hyperparameters or data through any public path (the properties, ``gp.model``, its GPyTorch modules,
  ``set_train_data``) is detected at the next prediction, which refactorizes once.

Positive hyperparameters are optimised in log space (as scikit-learn does), which keeps small output scales and
noise variances (1e-5 .. 1e-4 in the paper) well conditioned for L-BFGS.

**Known per-sample noise** (``fit(..., noise=...)``, heteroscedastic): the covariance of output j is
K + diag(known_j + floor), the known variances plus the ``noise_variance`` hyperparameter (a learned or fixed floor).
Noise the same for every output (``(N,)``) keeps one factorization for all outputs; noise that differs between
outputs (``(N, d_out)``) needs one per output (the per-output batch layout ``(d_out, N, N)``, with the shared kernel
expanded). ``gp.model`` then holds a GPyTorch ``FixedNoiseGaussianLikelihood`` (known noise plus a learned floor), so
the ExactGP view and the cached posterior still agree.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path

import gpytorch
import torch

from .._errors import FittingError, InputError, LinearAlgebraError, NotFittedError, NumericalWarning, ShapeError, warn
from .._threads import adaptive_threads
from .._validation import DEFAULT_DTYPE, as_tensor, check_finite, check_ndim, check_positive_int, check_real
from . import _mll
from ._exact import IndependentOutputsGP, median_distance
from ._features import (
    FeatureFactorization,
    Term,
    check_library,
    coefficient_posterior,
    fit_relevance,
    term_inclusion,
    unit_information_weights,
)
from ._kernels import Kernel, as_kernel, log_positive
from ._optim import maximise
from ._persistence import load as _load
from ._persistence import save as _save
from ._selection import EVIDENCE_MARGIN, fit_auto
from ._sum import fit_sum

__all__ = ["CorrectionGP", "GPPosterior", "KERNELS"]

KERNELS = ("rbf", "matern52", "polynomial", "features", "features+rbf", "auto")
#: Standard deviation of the weak prior on each log hyperparameter of :meth:`CorrectionGP.laplace_covariance`
#: (centred at the fitted value: a factor of about 7 either way).
LOG_PRIOR_SD = 2.0
#: smallest noise-to-output-scale ratio the profiled fit considers (relative, so the fit is scale-equivariant)
_MIN_RATIO = 1e-12


@dataclass(frozen=True)
class GPPosterior:
    """Posterior of F at test inputs (no observation noise).

    Attributes:
        mean: ``(M, d_out)``.
        variance: ``(M, d_out)``.
    """

    mean: torch.Tensor
    variance: torch.Tensor

    @property
    def stddev(self) -> torch.Tensor:
        return self.variance.clamp_min(0).sqrt()


def _show(module, name: str) -> str:
    """A hyperparameter's current value(s) for an error message."""
    value = getattr(module, name, None)
    if not isinstance(value, torch.Tensor):
        return "n/a"
    flat = value.detach().reshape(-1).tolist()
    return f"{flat[0]:.4g}" if len(flat) == 1 else "[" + ", ".join(f"{v:.4g}" for v in flat) + "]"


def _check_prediction(value: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Refuse a non-finite prediction at finite inputs (the kernel overflowed: inputs far too large)."""
    if not bool(torch.isfinite(value).all()):
        raise InputError(
            f"x: the prediction is not finite at inputs of size up to {float(x.abs().max()):.3g} (the kernel "
            "overflows there); rescale the inputs so that they are of the size of the training inputs"
        )
    return value


MEAN_BLOCK = 2**19  # kernel entries per row block of the posterior mean (4 MiB in float64)


def _identical_columns(noise: torch.Tensor) -> bool:
    """Known noise ``(N, d_out)`` the same for every output (then one factorization serves all outputs)."""
    return bool((noise == noise[:, :1]).all())


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.device == b.device and torch.equal(a, b)


#: Certified bound on the error of the posterior / prior variance ratio in the extrapolation check
#: (:meth:`CorrectionGP._sd_ratio`): 1e-3, far below the threshold's scale (a ratio of 1/2).
SUPPORT_TOLERANCE = 1e-3


class _Cache:
    """The factorization of the training covariance and the posterior solve, with the state they were built from."""

    def __init__(self, key: tuple, values: list[torch.Tensor], fac: _mll.Factorization, mll: float) -> None:
        self.key, self.values, self.fac, self.mll = key, values, fac, mll
        #: the extrapolation check's truncated eigenbasis (``CorrectionGP._sd_ratio``), built on first use
        #: (a 1-tuple, since the basis itself may be None: the exact solve)
        self.support_basis: tuple[torch.Tensor | None] | None = None


class CorrectionGP:
    """Gaussian-process model of the correction F, trained by exact marginal likelihood.

    Args:
        kernel: ``"rbf"`` (exp(-||y - y'||^2 / (2 l^2))), ``"matern52"``, ``"polynomial"``
            ((1 + <y, y'>)^degree, the paper's polynomial kernel), or ``"features"`` (sum_j w_j y^a_j y'^a_j over
            the monomials up to ``degree``, one learned weight per term: automatic relevance, see
            :mod:`torchmisspec.gp._features`), ``"features+rbf"`` (that library plus an RBF term for what it misses,
            :mod:`torchmisspec.gp._sum`), or ``"auto"``: every fit fits rbf, matern52, features and features+rbf
            by marginal likelihood and scores them by :attr:`evidence_score` (the log marginal likelihood less
            BIC's price of its learned hyperparameters). When features+rbf outscores the feature kernel it nests,
            the library misses part of F and only rbf and matern52 are eligible (:func:`library_check`:
            features+rbf is the library's test, never chosen). Leaving the RBF then takes strong evidence: the
            Matern or the feature kernel is kept only if it outscores the eligible stationary kernels by more than
            ``evidence_margin`` (:func:`auto_choice`). ``model_selection_`` lists them all; the cost of about five
            fits. Each is scaled by ``outputscale`` (fixed at 1 for the feature kernels, whose weights carry the
            scale).
        lengthscale: the RBF/Matern l (the paper's sigma_k^2 = l^2); not for the polynomial kernel. A value passed
            here (or for the next two) is held fixed; ``None`` means learned by marginal likelihood.
        outputscale: the kernel's variance factor.
        noise_variance: the variance of the observation noise on the samples of F.
        per_output: one set of hyperparameters per output (costs one factorization per output) instead of the
            paper's shared kernel.
        degree: the polynomial kernel's order m; the highest total degree of the feature kernel's monomials.
        min_gain: the feature kernels' price of a term: a term stays only while the log evidence it adds at its best
            weight exceeds this many nats (a spike-and-slab prior including each term with probability pi costs
            ``log((1 - pi) / pi)``). ``None`` (default): half the log of the number of samples, BIC's price of one
            learned value, the same as :attr:`evidence_score` charges, so spurious terms vanish as data accumulate;
            0: plain automatic relevance (every term whose evidence-optimal weight is positive). For the feature
            kernels and ``"auto"`` only.
        evidence_margin: ``"auto"`` only: by how many nats a candidate's score must exceed the RBF's (the feature
            kernel's: every eligible stationary kernel's) to be chosen instead (``None``: :data:`EVIDENCE_MARGIN`,
            3, "strong" evidence; 0: the highest score, ties going to the RBF).
        max_iter: most L-BFGS iterations when fitting.
        dtype: of the model's tensors (float64 by default: recommended for GP maths).
        device: of the model's tensors (the CPU by default).

    After :meth:`fit`: ``lengthscale``, ``outputscale`` and ``noise_variance`` hold the values in use (floats, or
    tensors ``(d_out,)`` when ``per_output``; with known per-sample noise, ``noise_variance`` is the floor added to
    it); ``train_noise_`` the known noise ``(N, d_out)`` or ``None``; ``log_marginal_likelihood_`` the exact log
    marginal likelihood (nats, summed over outputs) at those values; ``n_iterations_`` and ``n_evaluations_`` the
    L-BFGS iterations and likelihood evaluations of the final optimisation pass; ``model`` the GPyTorch ``ExactGP``
    holding the hyperparameters and the training data. With ``kernel="auto"``, ``kernel`` is the kernel chosen and
    ``model_selection_`` a list of dictionaries (``kernel``, ``log_marginal_likelihood``, ``hyperparameters``
    (the number learned), ``score`` (:attr:`evidence_score`), ``seconds``, ``error`` of a candidate that failed,
    ``eligible`` (allowed by :func:`library_check`), ``chosen``; features+rbf's also ``library_score``, the score of
    the feature kernel it nests) and ``library_suffices_`` the outcome of that check (``None``: not made; neither is
    saved with the model).
    """

    #: the :class:`~torchmisspec.calibration.BandCalibration` of this fit's bands (``CorrectedODE.calibrate``), saved
    #: with the model; ``None`` until calibrated, and again after a refit
    calibration_ = None
    #: the system it corrects (name, state_dim, correction_inputs, correction_outputs), when the command line fitted
    #: it; saved with the model and checked by the command line
    system_ = None
    #: the settings of :func:`~torchmisspec.fit_trajectories` when this model was refined through the ODE (``None``
    #: otherwise); saved with the model, so that ``CorrectedODE.calibrate`` refines each fold the same way
    refinement_ = None

    def __init__(
        self,
        *,
        kernel: str = "rbf",
        lengthscale: float | None = None,
        outputscale: float | None = None,
        noise_variance: float | None = None,
        per_output: bool = False,
        degree: int = 2,
        max_iter: int = 200,
        dtype: torch.dtype = DEFAULT_DTYPE,
        device: torch.device | str | None = None,
        library=None,
        library_names=None,
        min_gain: float | None = None,
        evidence_margin: float | None = None,
    ) -> None:
        auto = isinstance(kernel, str) and kernel == "auto"
        spec = as_kernel("rbf" if auto else kernel)  # the unfitted auto model holds an RBF until its first fit
        if not spec.has_lengthscale and lengthscale is not None:
            raise InputError(f"lengthscale: the {spec.name} kernel {spec!r} has no lengthscale; pass None")
        if spec.terms and outputscale is None:
            outputscale = 1.0  # the weights carry the scale
        if spec.shared_only and per_output:
            raise InputError(f"per_output: the {spec.name} kernel is shared by the outputs; pass per_output=False")
        if auto and (lengthscale is not None or outputscale is not None):
            raise InputError(
                "kernel='auto': the candidates' hyperparameters are learned (only noise_variance may be fixed); got "
                f"lengthscale={lengthscale!r}, outputscale={outputscale!r}"
            )
        degree = check_positive_int(degree, "degree")
        if min_gain is not None:
            if not (auto or spec.terms):
                raise InputError(
                    f"min_gain: the price of a feature term is for the feature kernels or 'auto', got {spec.name!r}"
                )
            min_gain = check_real(min_gain, "min_gain", minimum=0.0)
        #: the feature kernel's price of a term in nats per learned weight (None: half the log of the sample count)
        self.min_gain = None if min_gain is None else float(min_gain)
        if evidence_margin is not None and not auto:
            raise InputError(
                f"evidence_margin: expected kernel='auto' (the margin over the RBF), got kernel={spec.name!r} with "
                f"evidence_margin={evidence_margin!r}"
            )
        #: kernel="auto": the nats by which a candidate must outscore the RBF to be chosen instead (None otherwise)
        self.evidence_margin = (
            (
                EVIDENCE_MARGIN
                if evidence_margin is None
                else float(check_real(evidence_margin, "evidence_margin", minimum=0.0))
            )
            if auto
            else None
        )
        if library is not None and not (spec.terms or auto):
            raise InputError(
                f"library: a feature library is for kernel 'features' or 'features+rbf', got {spec.name!r}"
            )
        if library is None and library_names is not None:
            raise InputError("library_names: names a library of features; pass library=[...] too")
        #: user features replacing the monomials (callables x (..., d_in) -> (...,)), and their names
        self.library, self.library_names = (None, None) if library is None else check_library(library, library_names)
        lengthscale, outputscale, noise_variance = (
            None if value is None else check_real(value, name, positive=True)
            for name, value in (
                ("lengthscale", lengthscale),
                ("outputscale", outputscale),
                ("noise_variance", noise_variance),
            )
        )
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise InputError(f"dtype: expected a floating torch.dtype such as torch.float64, got {dtype!r}")
        #: kernel="auto": every fit chooses among AUTO_KERNELS by evidence (self.kernel is then the one chosen)
        self.auto = auto
        #: kernel="auto": whether the last fit's library check found the library sufficient (None: not checked)
        self.library_suffices_: bool | None = None
        #: the kernel object (:mod:`torchmisspec.gp._kernels`); ``kernel`` is its name
        self.kernel_spec: Kernel = spec
        self._d_in = 1  # the feature kernel's input dimension (set by fit)
        self.fixed = {
            "lengthscale": None if lengthscale is None else float(lengthscale),
            "outputscale": None if outputscale is None else float(outputscale),
            "noise_variance": None if noise_variance is None else float(noise_variance),
        }
        self.per_output = bool(per_output)
        self._auto_per_output = self.per_output  # what kernel="auto" was asked for (the chosen model may differ)
        self.degree = degree
        self.max_iter = check_positive_int(max_iter, "max_iter")
        self.dtype = dtype
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.log_marginal_likelihood_: float | None = None
        self.n_iterations_: int = 0
        self.n_evaluations_: int = 0
        self._cache: _Cache | None = None
        covar, lik = self._modules(batch=1)
        self.model: IndependentOutputsGP = IndependentOutputsGP(None, None, lik, covar, 1).eval()
        self._freeze()

    @classmethod
    def prior(
        cls,
        system,
        *,
        noise_variance: float,
        relative_size: float = 0.1,
        lengthscale_fraction: float = 0.5,
        kernel: str = "rbf",
        states=None,
        grid_size: int = 33,
        **kwargs,
    ) -> CorrectionGP:
        """A GP with hyperparameters set before any data, from the known model and the domain of interest D.

        The rule (documented, so that a design can start from it): the correction is expected to be a fraction
        ``relative_size`` of what the known model G already explains, and to vary on the scale of D:

        * ``outputscale = (relative_size * g)^2`` with ``g`` the median over D of ``||G_out(y)|| / sqrt(d_out)``,
          the known model's size on the correction's outputs (the median, not the mean: G may be singular in D,
          as a point mass is at its own position);
        * ``lengthscale = lengthscale_fraction *`` the mean side length of D (``system.domain``);
        * ``noise_variance``: the variance of the samples' noise, which only the experimenter knows (required).

        On the paper's §5.1 system (G(y) = A y on D = [-1, 1]^2) the defaults give lengthscale 1 and an output
        scale within a factor 2 of the paper's 4e-5. Hyperparameters are fixed: refit by marginal likelihood once
        data are in (``CorrectionGP(kernel=...).fit``).

        Args:
            system: a :class:`~torchmisspec.MisspecifiedSystem` with a ``domain``.
            noise_variance: the samples' noise variance.
            relative_size: the expected size of F relative to G's, > 0.
            lengthscale_fraction: the lengthscale as a fraction of D's mean side length, > 0.
            kernel: a stationary kernel with a lengthscale: ``"rbf"``, ``"matern52"`` or such an object.
            states: ``(M, d)`` full states at which G is evaluated; default: a ``grid_size`` per axis grid over D
                in the correction inputs, the other state components at 0.
            grid_size: points per axis of the default grid (at least 2).
            **kwargs: other constructor arguments (``dtype``, ``device``, ``max_iter``).
        """
        from ..systems import MisspecifiedSystem

        if not isinstance(system, MisspecifiedSystem):
            raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
        spec = as_kernel(kernel)
        if not (spec.stationary and spec.has_lengthscale):
            raise InputError(
                "kernel: expected a stationary kernel with a lengthscale such as 'rbf' or 'matern52', got "
                f"{spec.name!r}"
            )
        if system.domain is None:
            raise InputError(
                f"system: '{system.name}' has no domain D; build it with MisspecifiedSystem(..., domain=((lo, hi), "
                "...)) (one box side per correction input)"
            )
        relative_size = check_real(relative_size, "relative_size", positive=True)
        fraction = check_real(lengthscale_fraction, "lengthscale_fraction", positive=True)
        noise_variance = check_real(noise_variance, "noise_variance", positive=True)
        dtype = kwargs.get("dtype", DEFAULT_DTYPE)
        kd = dict(dtype=dtype, device=kwargs.get("device"))
        box = torch.as_tensor(system.domain, **kd)  # (d_in, 2)
        if states is None:
            from ..design.candidates import grid  # the package's one grid over a box (checks grid_size >= 2)

            inputs = grid(system.domain, grid_size, **kd)
            states = torch.zeros((inputs.shape[0], system.state_dim), **kd)
            states[:, list(system.correction_inputs)] = inputs
        else:
            states = as_tensor(states, "states", **kd)
            if states.dim() != 2 or states.shape[1] != system.state_dim:
                raise ShapeError(f"states: expected (M, {system.state_dim}) full states, got {tuple(states.shape)}")
        with torch.no_grad():
            g = system.select_outputs(system.known_rhs(states))
        size = g.norm(dim=-1) / math.sqrt(g.shape[-1])
        size = size[torch.isfinite(size)]
        if size.numel() == 0 or not float(size.median()) > 0:
            raise InputError(
                "system: the known model G is zero or not finite on D's correction outputs, so it gives no scale "
                "for F; pass CorrectionGP(outputscale=...) yourself"
            )
        outputscale = (relative_size * float(size.median())) ** 2
        lengthscale = fraction * float((box[:, 1] - box[:, 0]).mean())
        return cls(
            kernel=spec,
            lengthscale=lengthscale,
            outputscale=outputscale,
            noise_variance=noise_variance,
            **kwargs,
        )

    @property
    def kernel(self) -> str:
        """The kernel's name (``"rbf"``, ``"features"``, ...; for ``kernel="auto"`` the one chosen); the object itself
        is :attr:`kernel_spec`."""
        return self.kernel_spec.name

    @kernel.setter
    def kernel(self, value) -> None:
        self.kernel_spec = as_kernel(value)

    def _freeze(self) -> None:
        """Outside fitting no hyperparameter requires grad, so predictions build no autograd graph through them.

        To get sensitivities to a hyperparameter, set ``requires_grad_(True)`` on its raw GPyTorch parameter (e.g.
        ``gp.covar_module.base_kernel.raw_lengthscale``): :class:`~torchmisspec.CorrectedODE` then keeps the graph.
        The fit enables the parameters it optimises only while it runs. (To train ``gp.model`` with your own
        GPyTorch loop, call ``gp.model.requires_grad_(True)`` first.)
        """
        self.model.requires_grad_(False)

    def _hyperparameters_require_grad(self) -> bool:
        return any(p.requires_grad for p in self.model.parameters())

    def _differentiable_cache(self):
        """The posterior solve recomputed with the autograd graph to the hyperparameters (one factorization, not
        cached): for predictions whose gradient in the hyperparameters is wanted."""
        from types import SimpleNamespace

        self._posterior_cache()  # validates the training data and noise as for any prediction
        X, Y, noise = self.train_inputs_, self.train_targets_, self.train_noise_
        K, diag = self._kernel_parts(X, noise)
        return SimpleNamespace(fac=_mll.factorize(K, diag, self._targets_batched(Y, noise)))

    # ------------------------------------------------------------------------------------------------ building
    def _modules(self, batch: int, noise: torch.Tensor | None = None):
        """A fresh kernel and likelihood holding the fixed values (batch of ``batch`` when ``per_output``).

        ``noise``: known per-sample noise ``(d_out, N)`` (model dtype and device), or ``None``. With it the likelihood
        is a ``FixedNoiseGaussianLikelihood`` whose learned additional noise is the floor ``noise_variance``.
        """
        shape = torch.Size([batch]) if self.per_output else torch.Size([])
        base = self.kernel_spec.module(self, shape)
        covar = gpytorch.kernels.ScaleKernel(base, batch_shape=shape, outputscale_constraint=log_positive())
        if noise is None:
            lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=shape, noise_constraint=log_positive())
        else:
            # min_fixed_noise 0: GPyTorch would otherwise round known variances below 1e-6 up (and warn), and the
            # ExactGP view would no longer be the model that is fitted
            with gpytorch.settings.min_fixed_noise(float_value=0.0, double_value=0.0, half_value=0.0):
                lik = gpytorch.likelihoods.FixedNoiseGaussianLikelihood(
                    noise=noise, learn_additional_noise=True, batch_shape=shape, noise_constraint=log_positive()
                )
        covar, lik = covar.to(self.device, self.dtype), lik.to(self.device, self.dtype)

        # GPyTorch's setters would round a Python float through float32: pass tensors of the model's dtype
        def value(name):
            return torch.tensor(self.fixed[name], dtype=self.dtype, device=self.device)

        if self.fixed["lengthscale"] is not None:
            base.lengthscale = value("lengthscale")
        if self.fixed["outputscale"] is not None:
            covar.outputscale = value("outputscale")
        if self.fixed["noise_variance"] is not None:
            self._floor(lik).noise = value("noise_variance")
        return covar, lik

    @staticmethod
    def _floor(lik) -> gpytorch.likelihoods.noise_models.HomoskedasticNoise:
        """The module of the learned (or fixed) noise variance: the whole noise, or the floor over known noise."""
        if isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
            return lik.second_noise_covar
        return lik.noise_covar

    @property
    def covar_module(self) -> gpytorch.kernels.ScaleKernel:
        """The GPyTorch kernel in use (``gp.model.covar_module``), output scale included."""
        return self.model.covar_module

    @property
    def likelihood(self) -> gpytorch.likelihoods.GaussianLikelihood | gpytorch.likelihoods.FixedNoiseGaussianLikelihood:
        """The GPyTorch likelihood in use (``gp.model.likelihood``): a ``GaussianLikelihood`` holding the noise
        variance, or, when fitted with known noise, a ``FixedNoiseGaussianLikelihood`` holding the known noise
        ``(d_out, N)`` and the floor (its ``second_noise``)."""
        return self.model.likelihood

    @property
    def train_noise_(self) -> torch.Tensor | None:
        """``(N, d_out)`` known per-sample noise variances of the training targets (a view of the likelihood's
        ``(d_out, N)`` tensor, like ``train_targets_``), ``None`` when fitted without (or not fitted)."""
        lik = self.model.likelihood
        if not isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood) or not self.is_fitted:
            return None
        return lik.noise_covar.noise.T

    @property
    def train_inputs_(self) -> torch.Tensor | None:
        """``(N, d_in)`` training inputs (``gp.model.train_inputs[0]``), ``None`` before fitting."""
        inputs = self.model.train_inputs
        return None if inputs is None else inputs[0]

    @property
    def train_targets_(self) -> torch.Tensor | None:
        """``(N, d_out)`` training targets (``gp.model.train_targets`` is their transpose), ``None`` before fitting."""
        targets = self.model.train_targets
        return None if targets is None else targets.T

    def _free_parameters(self) -> list[tuple[str, torch.nn.Parameter]]:
        params = self.kernel_spec.free_parameters(self.covar_module.base_kernel, self.fixed)
        if self.fixed["outputscale"] is None:
            params.append(("outputscale", self.covar_module.raw_outputscale))
        if self.fixed["noise_variance"] is None:
            params.append(("noise_variance", self._floor(self.likelihood).raw_noise))
        return params

    def starting_values(self, inputs, targets) -> dict[str, torch.Tensor]:
        """The data-driven values the fit starts the learned hyperparameters from (a public hook, so that peers in
        benchmarks can start from the same point).

        * ``lengthscale``: the median distance between distinct inputs of an evenly spaced subsample of 500;
        * ``outputscale``: the targets' second moment (mean over outputs; per output with ``per_output``); the prior
          mean is zero, and it stays positive for constant targets;
        * ``noise_variance``: 1 % of it.

        Every value scales with the data, so the fit is equivariant to the units of inputs and targets. Returns
        tensors (``()``, or ``(d_out,)`` with ``per_output``) for the hyperparameters this kernel has.
        """
        X = as_tensor(inputs, "inputs", dtype=self.dtype, device=self.device)
        Y = as_tensor(targets, "targets", dtype=self.dtype, device=self.device)
        Y = Y.unsqueeze(-1) if Y.dim() == 1 else Y
        var = Y.pow(2).mean(dim=0)  # (d_out,)
        var = torch.where(var > 0, var, var.max()) if self.per_output else var.mean()
        out = {"outputscale": var, "noise_variance": 1e-2 * var}
        if self.kernel_spec.has_lengthscale:
            out["lengthscale"] = torch.tensor(median_distance(X), dtype=X.dtype, device=X.device)
        return out

    def _initialise(self, X: torch.Tensor, Y: torch.Tensor) -> None:
        """Set the learned hyperparameters to :meth:`starting_values` (the fixed ones are already set)."""
        start = self.starting_values(X, Y)
        with torch.no_grad():
            if self.kernel_spec.has_lengthscale and self.fixed["lengthscale"] is None:
                base = self.covar_module.base_kernel
                base.lengthscale = start["lengthscale"].expand(base.lengthscale.shape)
            if self.fixed["outputscale"] is None:
                self.covar_module.outputscale = start["outputscale"].expand(self.covar_module.outputscale.shape)
            if self.fixed["noise_variance"] is None:
                noise = start["noise_variance"]
                self._floor(self.likelihood).noise = noise.reshape(-1, 1) if self.per_output else noise.reshape(1)

    # ----------------------------------------------------------------------------------------------- the maths
    def _batched(self, noise: torch.Tensor | None) -> bool:
        """One covariance per output: per-output kernels, or known noise that differs between outputs."""
        return self.per_output or (noise is not None and not _identical_columns(noise))

    def _kernel_parts(self, X: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """C = K + diag as kernel part ``(B, N, N)`` and diagonal; B = 1 shared, d_out per output.

        Without known noise the diagonal is the noise variance ``(B, 1)``; with known noise ``(N, d_out)`` it is
        known + floor, ``(1, N)`` when the noise is the same for every output (shared kernel), else ``(d_out, N)``
        (the shared kernel expanded to ``(d_out, N, N)``).
        """
        K = self.covar_module.forward(X, X)
        K = K.unsqueeze(0) if K.dim() == 2 else K
        diag = self._noise_diag(noise)
        return (K.expand(diag.shape[0], -1, -1) if diag.shape[0] > K.shape[0] else K), diag

    def _noise_diag(self, noise: torch.Tensor | None = None) -> torch.Tensor:
        """The diagonal of C = K + diag: the noise variance ``(B, 1)``, or known + floor ``(1, N)`` / ``(d_out, N)``
        (see :meth:`_kernel_parts`)."""
        floor = self._floor(self.likelihood).noise.reshape(-1, 1)  # (1, 1) or (d_out, 1)
        if noise is None:
            return floor
        if not self._batched(noise):
            return noise[:, 0].unsqueeze(0) + floor
        return noise.T + floor

    def _targets_batched(self, Y: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """Targets arranged to match ``(B, N, N)``: one covariance -> ``(1, N, d_out)``; one per output (per-output
        kernels, or known noise differing between outputs) -> ``(d_out, N, 1)``."""
        return Y.T.unsqueeze(-1) if self._batched(noise) else Y.unsqueeze(0)

    # ------------------------------------------------------------------------------------------------- fitting
    def _check_inputs(self, x, name: str) -> torch.Tensor:
        x = as_tensor(x, name, dtype=self.dtype, device=self.device)
        d_in = self.input_dim
        if x.dim() == 1 and d_in == 1:
            x = x.unsqueeze(-1)
        check_ndim(x, 2, name, "(M, d_in)")
        check_finite(x, name)
        if d_in is not None and x.shape[1] != d_in:
            raise ShapeError(f"{name}: expected {d_in} input columns (as in training), got shape {tuple(x.shape)}")
        return x

    @staticmethod
    def _unpack(inputs, targets, noise):
        """``fit(samples)`` or ``fit(inputs, targets, noise=...)``: the three arrays."""
        from ..observations import CorrectionSamples

        if isinstance(inputs, CorrectionSamples):
            if targets is not None or noise is not None:
                given = [name for name, v in (("targets", targets), ("noise", noise)) if v is not None]
                raise InputError(
                    f"fit: expected either a CorrectionSamples object alone or inputs and targets (and noise), got a "
                    f"CorrectionSamples object and {' and '.join(given)} (the samples already carry their targets "
                    "and noise)"
                )
            return inputs.inputs, inputs.targets, inputs.noise
        if targets is None:
            raise InputError(
                f"targets: expected (N, d_out) samples of F (or a CorrectionSamples object as the only argument), "
                f"got None with inputs of type {type(inputs).__name__}"
            )
        return inputs, targets, noise

    def _check_noise(self, noise, N: int, d_out: int) -> torch.Tensor | None:
        """Known noise variances ``(N,)`` or ``(N, d_out)`` -> ``(N, d_out)`` (finite, >= 0), or ``None``."""
        if noise is None:
            return None
        noise = as_tensor(noise, "noise", dtype=self.dtype, device=self.device)
        if noise.dim() == 1 and noise.shape[0] == N:
            noise = noise.unsqueeze(-1).expand(N, d_out)
        if noise.shape != (N, d_out):
            raise ShapeError(
                f"noise: expected known noise variances ({N},) (the same for every output) or ({N}, {d_out}) (per "
                f"sample and output), got shape {tuple(noise.shape)}"
            )
        check_finite(noise, "noise")
        if bool((noise < 0).any()):
            raise InputError(
                f"noise: expected non-negative variances, got {int((noise < 0).sum())} negative values (smallest "
                f"{float(noise.min()):.3g})"
            )
        return noise.contiguous()

    @adaptive_threads()
    def fit(
        self,
        inputs,
        targets=None,
        *,
        noise=None,
        progress: bool = False,
        max_iter: int | None = None,
        warm_start: int = 500,
    ) -> CorrectionGP:
        """Fit to samples of F: ``inputs (N, d_in)``, ``targets (N, d_out)``. Returns ``self``.

        ``gp.fit(samples)`` takes a :class:`~torchmisspec.CorrectionSamples` object instead (its ``inputs``,
        ``targets`` and ``noise``); then no other data argument is accepted.

        ``noise``: known per-sample noise variances of the targets, ``(N,)`` (the same for every output) or
        ``(N, d_out)`` (heteroscedastic, e.g. an estimator's variance), added to the ``noise_variance``
        hyperparameter, which becomes a floor (learned, or fixed when given). The posterior (``predict``,
        ``predict_mean``) is that of F itself, without observation noise, as without known noise.

        The learned hyperparameters maximise the exact log marginal likelihood (L-BFGS with strong Wolfe line
        search, in log space, from data-driven starting values; analytic gradients, see :mod:`torchmisspec.gp._mll`).
        With a shared kernel, both the output scale and the noise learned, and no known noise, the output scale is
        maximised out in closed form; with known noise (which does not scale with the output scale) the output scale
        and the floor are optimised directly. When N > 2 * ``warm_start``, a first pass on an evenly spaced
        subsample of ``warm_start`` points provides the starting values (0 disables it). ``progress=True`` shows a
        progress bar.
        """
        if self.auto:
            return fit_auto(self, inputs, targets, noise, progress=progress, max_iter=max_iter, warm_start=warm_start)
        inputs, targets, noise = self._unpack(inputs, targets, noise)
        X = as_tensor(inputs, "inputs", dtype=self.dtype, device=self.device)
        Y = as_tensor(targets, "targets", dtype=self.dtype, device=self.device)
        if Y.dim() == 1:
            Y = Y.unsqueeze(-1)
        check_ndim(X, 2, "inputs", "(N, d_in)")
        check_ndim(Y, 2, "targets", "(N, d_out)")
        if X.shape[0] != Y.shape[0]:
            raise ShapeError(
                f"targets: expected {X.shape[0]} rows to match inputs {tuple(X.shape)}, got {tuple(Y.shape)}"
            )
        if X.shape[0] < 1:
            raise FittingError("inputs: expected at least one sample, got 0")
        check_finite(X, "inputs")
        check_finite(Y, "targets")
        noise = self._check_noise(noise, Y.shape[0], Y.shape[1])
        max_iter = self.max_iter if max_iter is None else check_positive_int(max_iter, "max_iter")
        warm_start = check_positive_int(warm_start, "warm_start", minimum=0)
        free = [name for name, _ in self._free_parameters()]
        if any(name in ("outputscale", "noise_variance") for name in free) and not bool((Y != 0).any()):
            raise FittingError(
                "targets: expected some non-zero samples to learn the output scale and noise from, got all zeros "
                "(the likelihood grows without bound as both shrink to 0); fix them: CorrectionGP(outputscale=..., "
                "noise_variance=...)"
            )
        # a failed fit leaves the model as it was (not half-fitted on the new data)
        before = (self.model, self._cache, self.n_iterations_, self.n_evaluations_, self.log_marginal_likelihood_)
        saved = [{k: v.clone() for k, v in m.state_dict().items()} for m in (self.covar_module, self.likelihood)]
        try:
            self._fit(X, Y, noise, bool(free), progress=progress, max_iter=max_iter, warm_start=warm_start)
        except BaseException:
            self.model, self._cache, self.n_iterations_, self.n_evaluations_, self.log_marginal_likelihood_ = before
            self.covar_module.load_state_dict(saved[0])
            self.likelihood.load_state_dict(saved[1])
            raise
        self.__dict__.pop("calibration_", None)  # a calibration of the bands belongs to the fit it was made for
        self.__dict__.pop("refinement_", None)  # and so does a refinement through the ODE
        return self

    def _fit(self, X, Y, noise, learn: bool, *, progress: bool, max_iter: int, warm_start: int) -> None:
        d_out = Y.shape[1]
        covar, lik = self.covar_module, self.likelihood
        if self.kernel_spec.terms and covar.base_kernel.powers.shape[1] != X.shape[1]:  # library: d_in too
            self._d_in = X.shape[1]  # the library of monomials of these inputs
            covar, lik = self._modules(batch=d_out)
        if self.per_output and covar.batch_shape != torch.Size([d_out]):
            covar, lik = self._modules(batch=d_out)
        if noise is not None or isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
            # the likelihood holds the known noise (or none): a fresh one for these data, fixed values included
            # (a copy: the model never shares storage with the caller's tensor)
            known = None if noise is None else noise.T.clone(memory_format=torch.contiguous_format)
            lik = self._modules(batch=d_out, noise=known)[1]
        self.model = IndependentOutputsGP(X, Y.T.contiguous(), lik, covar, d_out).eval()
        self._cache = None
        own = self.kernel_spec.fit(self, X, Y, noise, max_iter=max_iter) if learn else None
        if own is not None:  # the kernel's own fit (the feature kernels')
            self.n_iterations_, self.n_evaluations_ = own
        elif learn:
            self._initialise(X, Y)
            if warm_start and X.shape[0] > 2 * warm_start:
                # a cheap first pass on an evenly spaced subsample puts L-BFGS near the optimum; the second pass
                # on all the data then needs few O(N^3) evaluations (the result maximises the full likelihood)
                sub = torch.linspace(0, X.shape[0] - 1, warm_start, device=X.device).round().long()
                sub_noise = None if noise is None else noise[sub]
                self._optimise(X[sub], Y[sub], sub_noise, progress=False, max_iter=max_iter)
                if noise is not None and self.fixed["noise_variance"] is None:
                    # beside known noise a subsample often cannot identify the floor, which then collapses towards
                    # 0, where its log-space gradient vanishes: the full pass starts it afresh
                    start = self.starting_values(X, Y)["noise_variance"]
                    with torch.no_grad():
                        floor = self._floor(self.likelihood)
                        floor.noise = start.reshape(-1, 1) if self.per_output else start.reshape(1)
            result = self._optimise(X, Y, noise, progress=progress, max_iter=max_iter)
            self.n_iterations_, self.n_evaluations_ = result.iterations, result.evaluations
        else:
            self.n_iterations_, self.n_evaluations_ = 0, 0
        self._freeze()
        self._posterior_cache()

    @property
    def num_hyperparameters(self) -> int:
        """The number of hyperparameters learned by the fit: every free value (one per output with
        ``per_output``), and of the feature weights only those of the terms kept (a removed term is no parameter)."""
        self._require_fitted()
        return sum(
            int((p.detach() != 0).sum()) if name == "weights" else p.numel() for name, p in self._free_parameters()
        )

    @property
    def evidence_score(self) -> float:
        """The log marginal likelihood less ``num_hyperparameters * log(N) / 2`` (N samples): BIC's approximation
        of the hyperparameters' own Occam factor, which ML-II evidence leaves out (the log evidence with them
        integrated out, up to O(1)). ``kernel="auto"`` chooses by this score (:func:`auto_choice`). The price per
        learned value is the same as a feature term's (``min_gain``), so the choice between kernels and the choice
        of terms within a feature kernel follow one rule; without it, a kernel with more learned values wins
        whenever they fit the samples slightly better."""
        self._require_fitted()
        n = self.train_inputs_.shape[0]
        return float(self.log_marginal_likelihood_) - 0.5 * math.log(n) * self.num_hyperparameters

    def _fit_sum(self, X, Y, noise, *, max_iter: int) -> tuple[int, int]:
        """The features+rbf kernel's fit (:func:`~torchmisspec.gp._sum.fit_sum`): ``(iterations, evaluations)``."""
        floor, _, iterations = fit_sum(
            self.covar_module.base_kernel,
            X,
            Y,
            noise,
            floor=self.fixed["noise_variance"],
            lengthscale=self.fixed["lengthscale"],
            max_iter=max_iter,
            outputscale=float(self.fixed["outputscale"]),
            min_gain=0.5 * math.log(X.shape[0]) if self.min_gain is None else self.min_gain,
        )
        if self.fixed["noise_variance"] is None:
            with torch.no_grad():
                self._floor(self.likelihood).noise = torch.tensor([floor], dtype=self.dtype, device=self.device)
        return iterations, iterations

    def _fit_features(self, X: torch.Tensor, Y: torch.Tensor, noise: torch.Tensor | None, *, max_iter: int) -> int:
        """The feature kernel's weights (and the noise floor unless fixed) by sparse Bayesian learning in feature
        space (:func:`~torchmisspec.gp._features.fit_relevance`): one set of weights shared by the outputs, or one
        per output with ``per_output``. Returns the number of fixed-point iterations (the most over the outputs)."""
        covar, lik = self.covar_module, self.likelihood
        base = covar.base_kernel
        scale = float(self.fixed["outputscale"])
        Phi = base.features(X) * math.sqrt(scale)  # the output scale folded into the features
        floor = self.fixed["noise_variance"]
        groups = [[o] for o in range(Y.shape[1])] if self.per_output else [list(range(Y.shape[1]))]
        # the price of a term: per learned weight (shared by the outputs of a group or not), as evidence_score counts
        price = 0.5 * math.log(X.shape[0]) if self.min_gain is None else self.min_gain
        weights, floors, inclusion, spread, iterations = [], [], [], [], 0
        for cols in groups:
            known = None if noise is None else noise[:, cols]
            try:
                w, s, it = fit_relevance(Phi, Y[:, cols], known, floor=floor, max_iter=10 * max_iter, min_gain=price)
            except FittingError as exc:
                if not self.per_output:
                    raise
                raise FittingError(f"output {cols[0]}: {exc}") from exc
            if it >= 10 * max_iter:
                warn(
                    f"the feature weights{f' of output {cols[0]}' if self.per_output else ''} did not converge in "
                    f"{it} iterations (10 x max_iter): the terms kept may include some the price would remove; "
                    "raise max_iter",
                    NumericalWarning,
                )
            w = unit_information_weights(Phi, w, known, s)  # the kept terms' slab (_features)
            weights.append(w)
            p_in, extra = term_inclusion(Phi, Y[:, cols], known, w, s)  # each term's chance (_features)
            inclusion.append(p_in)
            spread.append(extra.mean(0) * scale)  # one per weight (shared outputs: their mean), unscaled features
            floors.append(s)
            iterations = max(iterations, it)
        with torch.no_grad():
            base.weights.copy_(torch.stack(weights).reshape(base.weights.shape))
            base.inclusion.copy_(torch.stack(inclusion).reshape(base.inclusion.shape))
            base.spread.copy_(torch.stack(spread).reshape(base.spread.shape))
            if floor is None:
                value = torch.tensor(floors, dtype=self.dtype, device=self.device)
                self._floor(lik).noise = value.reshape(-1, 1) if self.per_output else value.reshape(1)
        return iterations

    def _lengthscale_box(self, X: torch.Tensor):
        """``(raw lengthscale, lo, hi)``: the learned lengthscale is kept within [1e-4, 1e4] times the median distance
        between the inputs (log space), or ``None`` when it is not learned. Without the box a line-search trial can
        take log l to -1000, where every kernel entry is 0/0."""
        if not self.kernel_spec.has_lengthscale or self.fixed["lengthscale"] is not None:
            return None
        scale = median_distance(X)
        return self.covar_module.base_kernel.raw_lengthscale, math.log(1e-4 * scale), math.log(1e4 * scale)

    def _optimise(self, X: torch.Tensor, Y: torch.Tensor, noise: torch.Tensor | None, *, progress: bool, max_iter: int):
        """L-BFGS on the exact log marginal likelihood with the analytic gradient of :mod:`._mll`.

        When the output scale and the noise are both learned with a shared kernel and there is no known noise, the
        output scale s is profiled out: C = s (R + g I), leaving the lengthscale and the noise ratio g for L-BFGS
        (the same optimum of the same likelihood, in fewer iterations); s* and g s* are written back into the
        GPyTorch modules. Known noise does not scale with s, so then every free hyperparameter is optimised directly.
        """
        n, d_out = Y.shape
        free = [p for _, p in self._free_parameters()]
        profile = (
            not self.per_output
            and noise is None
            and self.fixed["outputscale"] is None
            and self.fixed["noise_variance"] is None
        )
        Yb = self._targets_batched(Y, noise)
        covar, lik = self.covar_module, self.likelihood
        if profile:
            ratio0 = (lik.noise.detach() / covar.outputscale.detach()).log().reshape(1)
            log_ratio = ratio0.clone().requires_grad_(True)
            params = [p for p in free if p is not covar.raw_outputscale and p is not lik.noise_covar.raw_noise]
            params.append(log_ratio)

            def matrices():
                return covar.base_kernel.forward(X, X).unsqueeze(0), (log_ratio.exp() + _MIN_RATIO).reshape(1, 1)
        else:
            params = free

            def matrices():
                return self._kernel_parts(X, noise)

        box = self._lengthscale_box(X)

        def evaluate():
            if box is not None:  # a line-search trial far out in log space (l -> 0 makes K all NaN): project back
                with torch.no_grad():
                    box[0].clamp_(box[1], box[2])
            K, diag = matrices()
            with torch.no_grad():
                fac = _mll.factorize(K.detach(), diag.detach(), Yb, warn=False)
                if profile:
                    value, scale = _mll.profiled_mll(fac)
                    Q = _mll.gradient_weights(fac, scale)
                else:
                    value = _mll.exact_mll(fac, n)
                    Q = _mll.gradient_weights(fac)
            return value, _mll.gradient_surrogate(Q, K, diag)

        try:
            result = maximise(
                params,
                evaluate,
                max_iter=max_iter,
                normaliser=float(n * d_out),
                progress=progress,
                desc=f"fit GP (N={n})",
            )
            if profile:  # write the profiled output scale and the noise back into the GPyTorch modules
                with torch.no_grad():
                    K, diag = matrices()
                    _, scale = _mll.profiled_mll(_mll.factorize(K, diag, Yb, warn=False))
                    covar.outputscale = scale
                    lik.noise = (scale * (log_ratio.exp() + _MIN_RATIO)).reshape(1)
        except LinearAlgebraError as exc:
            raise FittingError(
                f"fitting failed at lengthscale={_show(self.covar_module.base_kernel, 'lengthscale')}, "
                f"outputscale={_show(covar, 'outputscale')}, noise_variance={_show(self._floor(lik), 'noise')}: {exc}"
            ) from exc
        for p in params:
            if not bool(torch.isfinite(p).all()):
                raise FittingError(
                    "fitting diverged: a hyperparameter became non-finite; fix some of them "
                    "(lengthscale=..., outputscale=..., noise_variance=...) or rescale the data"
                )
        return result

    # ------------------------------------------------------------------------------------------- the cache
    def _state(self) -> tuple[tuple, list[torch.Tensor]]:
        """What the posterior depends on: identities/versions of modules and data, and every parameter's value."""
        m = self.model
        X, Yt = m.train_inputs[0], m.train_targets
        key = (id(m.covar_module), id(m.likelihood), id(X), X._version, id(Yt), Yt._version)
        values = [t.detach() for t in (*m.parameters(), *m.buffers())]
        if isinstance(m.likelihood, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
            known = m.likelihood.noise_covar.noise  # a plain attribute in GPyTorch (not a buffer): keyed here
            key += (id(known), known._version)
            values.append(known.detach())
        return key, values

    def _posterior_cache(self) -> _Cache:
        """The cached factorization; rebuilt (one factorization) when anything it depends on has changed."""
        self._require_fitted()
        key, values = self._state()
        c = self._cache
        if (
            c is not None
            and c.key == key
            and len(c.values) == len(values)
            and all(_same(a, b) for a, b in zip(c.values, values, strict=True))
        ):
            return c
        X, Y, noise = self.train_inputs_, self.train_targets_, self.train_noise_
        if noise is not None and noise.shape != Y.shape:
            raise ShapeError(
                f"known noise: expected {tuple(Y.shape)} (the training targets' shape) as gp.train_noise_, got "
                f"{tuple(noise.shape)}; refit with gp.fit(inputs, targets, noise=...)"
            )
        if self.per_output and self.covar_module.batch_shape != torch.Size([Y.shape[1]]):
            raise ShapeError(
                f"training targets: expected {self.covar_module.batch_shape[0]} outputs for the per-output kernels, "
                f"got {Y.shape[1]}; refit with gp.fit(inputs, targets)"
            )
        self.model.num_outputs = Y.shape[1]
        with torch.no_grad():
            Yb = self._targets_batched(Y, noise)
            if self.kernel_spec.feature_space:  # in feature space: O(N p^2), the N x N matrix is never formed
                base = self.covar_module.base_kernel
                Phi = base.features(X)
                W = base.weights.detach().reshape(-1, Phi.shape[1]) * self.covar_module.outputscale.reshape(-1, 1)
                diag = self._noise_diag(noise)
                fac = FeatureFactorization(Phi, W, diag, Yb)
                B = fac.alpha.shape[0]
                KA = Phi @ (W.expand(B, -1).unsqueeze(-1) * (Phi.T @ fac.alpha))  # K alpha, (B, N, m)
                resid = KA + diag.expand(B, -1).unsqueeze(-1) * fac.alpha - Yb
            else:
                K, diag = self._kernel_parts(X, noise)
                fac = _mll.factorize(K, diag, Yb)
                resid = K @ fac.alpha + diag.unsqueeze(-1) * fac.alpha - Yb
            # a Cholesky that "succeeds" on a nearly singular matrix can still solve badly (tiny noise with repeated
            # inputs). The residual r = (K + noise I) alpha - Y is, to first order, the error of the posterior mean
            # at the training inputs: warn when it exceeds a tenth of the noise standard deviation (then it is no
            # longer negligible beside the uncertainty the model reports; the smallest one with per-sample noise)
            err = float(resid.abs().max())
            tol = 0.1 * float(diag.min().sqrt())
        if err > tol:
            warn(
                f"CorrectionGP: the posterior solve is inaccurate: the posterior mean at the training inputs is off "
                f"by up to {err:.2e}, more than a tenth of the noise standard deviation ({10 * tol:.2e}). The noise "
                "variance is too small for these inputs (repeated or nearly repeated points?); raise noise_variance "
                "or remove duplicate inputs",
            )
        self._cache = _Cache(key, [v.clone() for v in values], fac, float(_mll.exact_mll(fac, X.shape[0])))
        self.log_marginal_likelihood_ = self._cache.mll
        return self._cache

    # ---------------------------------------------------------------------------------------------- prediction
    @property
    def is_fitted(self) -> bool:
        return self.model.train_inputs is not None

    def _require_fitted(self) -> None:
        if not self.is_fitted:
            raise NotFittedError("this CorrectionGP is not fitted yet; call .fit(inputs, targets) first")

    @property
    def input_dim(self) -> int | None:
        X = self.train_inputs_
        return None if X is None else X.shape[1]

    @property
    def output_dim(self) -> int | None:
        Y = self.train_targets_
        return None if Y is None else Y.shape[1]

    def covariance(self, x1, x2=None) -> torch.Tensor:
        """Prior covariance k(x1, x2) of F from the model's GPyTorch kernel (outputscale included).

        Returns a dense ``(M1, M2)`` tensor (``(d_out, M1, M2)`` when ``per_output``). Works before fitting for a
        shared kernel, with the hyperparameters given (or their defaults).
        """
        if (self.per_output or self.kernel_spec.terms) and not self.is_fitted:
            raise NotFittedError("per-output and feature kernels are built by fit(); call .fit(inputs, targets) first")
        x1 = self._check_inputs(x1, "x1")
        x2 = x1 if x2 is None else self._check_inputs(x2, "x2")
        with torch.no_grad():
            return self.covar_module.forward(x1, x2)

    def _cross(self, x: torch.Tensor) -> torch.Tensor:
        """k(X, x) as ``(B, N, M)``, training inputs first: GPyTorch's distances centre both inputs on the mean of
        the first, so with the queries first one far-away row would shift every other row's distances (a prediction
        would depend on what else is in the batch); centred on the fixed training inputs, each query is its own."""
        K = self.covar_module.forward(self.train_inputs_, x)
        return K.unsqueeze(0) if K.dim() == 2 else K

    @staticmethod
    def _cross_mean(Kt: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """k(x, X) alpha as ``(B, M, d)`` from ``Kt = k(X, x) (B, N, M)`` (:meth:`_cross`) and ``alpha (B, N, d)``:
        alpha^T k(X, x), transposed (a contiguous product)."""
        return (alpha.transpose(-1, -2) @ Kt).transpose(-1, -2)

    def predict_mean(self, x) -> torch.Tensor:
        """Posterior mean of F at ``x (M, d_in)``: ``(M, d_out)``. One kernel block times the cached solve.

        Differentiable with respect to ``x`` when ``x`` requires grad (autograd flows through the kernel; the cached
        solve is a constant, so no gradient reaches the hyperparameters). Never refactorizes unless the
        hyperparameters or the training data changed since the last prediction.
        """
        cache = self._posterior_cache()
        x = self._check_inputs(x, "x")
        # a graph only when the inputs ask for one: the cached solve is constant, so this is d mean / d x, and
        # results used as numbers carry no autograd history
        with torch.set_grad_enabled(x.requires_grad and torch.is_grad_enabled()):
            return _check_prediction(self._mean_from(cache, x), x)

    @staticmethod
    def _unbatch(mean: torch.Tensor) -> torch.Tensor:
        """``(1, M, d_out)`` (one covariance) or ``(d_out, M, 1)`` (one per output) -> ``(M, d_out)``."""
        return mean[0] if mean.shape[0] == 1 else mean.squeeze(-1).T

    def _mean_from(self, cache: _Cache, x: torch.Tensor) -> torch.Tensor:
        """The posterior mean at checked inputs ``x (M, d_in)`` from a cache (the ODE right-hand side's path).

        Row blocks of about ``MEAN_BLOCK`` kernel entries keep the kernel's elementwise passes in cache (a
        corrected-model solve is mostly this call; ``scripts/benchmark_campaign.py`` times it against one block)."""
        if isinstance(cache.fac, FeatureFactorization):  # phi(x)^T (posterior mean of the coefficients)
            return self._unbatch(self.covar_module.base_kernel.features(x) @ cache.fac.mean)
        alpha = cache.fac.alpha
        rows = max(64, MEAN_BLOCK // max(alpha.shape[-2], 1))
        if x.shape[0] <= rows:
            return self._unbatch(self._cross_mean(self._cross(x), alpha))  # (1, M, d_out) or (d_out, M, 1) before
        return torch.cat(
            [self._unbatch(self._cross_mean(self._cross(x[i : i + rows]), alpha)) for i in range(0, x.shape[0], rows)]
        )

    def predict(self, x) -> GPPosterior:
        """Posterior mean and variance of F itself (no observation noise) at ``x (M, d_in)``, each ``(M, d_out)``."""
        cache = self._posterior_cache()
        x = self._check_inputs(x, "x")
        with torch.no_grad():
            if isinstance(cache.fac, FeatureFactorization):  # phi(x)^T cov phi(x): no N x N factor
                phi = self.covar_module.base_kernel.features(x)  # (M, p)
                mean = self._unbatch(phi @ cache.fac.mean)
                var = ((phi @ cache.fac.cov) * phi).sum(-1).clamp_min(0.0)  # (B, M)
            else:
                Kt = self._cross(x)  # k(X, x): (1, N, M) shared kernel, (d_out, N, M) per output
                mean = self._unbatch(self._cross_mean(Kt, cache.fac.alpha))
                chol = cache.fac.chol  # (1 or d_out, N, N)
                Kt = Kt.expand(chol.shape[0], -1, -1)
                v = torch.linalg.solve_triangular(chol, Kt, upper=False)
                prior = self.covar_module.forward(x, x, diag=True)  # (M,) or (d_out, M)
                var = (prior - v.pow(2).sum(-2)).clamp_min(0.0)  # (1 or d_out, M)
            var = (var + self._term_spread(x)).T.expand(-1, mean.shape[-1])  # + the removed terms' chance
        _check_prediction(mean, x)
        _check_prediction(var, x)
        return GPPosterior(mean=mean, variance=var.contiguous())

    def _term_spread(self, x: torch.Tensor) -> torch.Tensor | float:
        """``(B, M)``: the variance the feature kernel's removed terms add at ``x (M, d_in)`` (their chance of being
        present, :attr:`~torchmisspec.gp._features.FeatureKernel.spread`), or 0 for other kernels."""
        base = self.covar_module.base_kernel
        if getattr(base, "spread", None) is None:
            return 0.0
        phi = base.features(x)  # (M, p)
        return (phi.pow(2) @ base.spread.reshape(-1, phi.shape[-1]).to(phi).T).T

    def _support_basis(self, X: torch.Tensor, params: dict) -> torch.Tensor | None:
        """``U_r / sqrt(lam_r + s2n)`` ``(B, N, r)`` for :meth:`_sd_ratio` (see there), or ``None`` for the exact
        solve (known per-sample noise, or no saving)."""
        from ._paths import kernel_matrix

        if self.train_noise_ is not None:
            return None
        K = kernel_matrix(self.kernel_spec, X, X, params, self.degree)  # (B, N, N)
        lam, U = torch.linalg.eigh(K)  # ascending
        lam = lam.clamp_min(0.0)
        s2n = self._floor(self.likelihood).noise.detach().reshape(-1, 1)  # (B, 1)
        # the tail sums of the shares lam / (lam + s2n) from the smallest: drop as many as the budget allows
        drop = int((((lam / (lam + s2n)).cumsum(-1)) <= SUPPORT_TOLERANCE).sum(-1).min())
        if X.shape[0] - drop > X.shape[0] // 2:  # not worth it: more than half the rank
            return None
        return U[..., drop:] / (lam[..., drop:] + s2n).sqrt().unsqueeze(-2)

    def _sd_ratio(self, x: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
        """``(M,)``: posterior over prior standard deviation of F at inputs ``x (M, d_in)``, the largest over the
        outputs (1: the prior alone, 0: F known). The extrapolation check of every predicted path calls this.

        With one noise variance per output (no known per-sample noise), the posterior variance is computed in the
        eigenbasis of K(X, X) = sum_i lam_i u_i u_i^T, keeping the r largest eigenpairs: k_x^T C^-1 k_x =
        sum_i (u_i^T k_x)^2 / (lam_i + s2n), and since k_x^T K^+ k_x <= k(x, x) every term i is at most
        lam_i / (lam_i + s2n) k(x, x), so the dropped terms change the variance ratio by at most
        sum_{i > r} lam_i / (lam_i + s2n) <= :data:`SUPPORT_TOLERANCE`, always upward (the ratio is never
        understated). The rank r is the smallest with that certificate; otherwise (known per-sample noise, or no
        saving) the exact triangular solve is used, in row chunks.
        """
        from ._paths import detached, kernel_hyperparameters, kernel_matrix

        cache = self._posterior_cache()
        X = self.train_inputs_
        with torch.no_grad():
            prior = self.covar_module.forward(x, x, diag=True).reshape(-1, x.shape[0])  # (1 or d_out, M)
            if isinstance(cache.fac, FeatureFactorization):  # exact, in feature space
                phi = self.covar_module.base_kernel.features(x)
                post = ((phi @ cache.fac.cov) * phi).sum(-1).clamp_min(0.0)
                ratio = (post / prior.clamp_min(torch.finfo(prior.dtype).tiny)).clamp(0.0, 1.0).sqrt()
                return ratio.amax(0)
            chol = cache.fac.chol  # (1 or d_out, N, N)
            params = detached(kernel_hyperparameters(self))
            if cache.support_basis is None:  # once per factorization, not at every extrapolation check
                cache.support_basis = (self._support_basis(X, params),)
            (basis,) = cache.support_basis
            explained = []
            for start in range(0, x.shape[0], chunk):
                K = kernel_matrix(self.kernel_spec, x[start : start + chunk], X, params, self.degree)  # (B, m, N)
                if basis is not None:
                    V = K @ basis  # (B, m, r): (u_i^T k_x) / sqrt(lam_i + s2n)
                else:
                    K = K.expand(chol.shape[0], -1, -1)
                    V = torch.linalg.solve_triangular(chol.transpose(-1, -2), K, upper=True, left=False)  # K L^-T
                explained.append(V.pow(2).sum(-1))
            post = (prior - torch.cat(explained, -1)).clamp_min(0.0)
            ratio = (post / prior.clamp_min(torch.finfo(prior.dtype).tiny)).clamp(0.0, 1.0).sqrt()
        return ratio.amax(0)

    def sample_functions(
        self,
        num_samples: int,
        *,
        num_features: int | None = None,
        feature_error: float | None = None,
        generator: torch.Generator | None = None,
        update_error: float | None = None,
        scale: float = 1.0,
    ):
        """``S`` posterior draws of F as whole functions (pathwise conditioning), consistent wherever evaluated.

        Each draw is a prior draw from features plus the exact posterior update through the cached factorization
        (see :mod:`torchmisspec.gp._paths`): evaluate it at any inputs, any number of times (an ODE solver calling
        it at every step sees one function). Their mean is the posterior mean; their covariance is the posterior
        covariance up to the prior features' error: for the RBF kernel in low input dimension, deterministic
        quadrature Fourier features with a certified uniform bound of ``feature_error`` (default 1e-2) times the
        prior variance over the training inputs' box widened by its width on each side; otherwise (Matern 5/2, high
        input dimension, or ``num_features`` given) random Fourier features with a root-mean-square bound (default
        0.05) at every pair of points; none for the polynomial and feature kernels (exact features). See
        :mod:`torchmisspec.gp._paths`.

        Args:
            num_samples: S >= 1.
            num_features: number of random Fourier features (even), instead of the bound ``feature_error``.
            feature_error: relative bound on the prior-covariance error that chooses the features.
            generator: ``torch.Generator`` on the GP's device, for reproducible draws.
            update_error: compress the update onto the fewest training inputs that keep a certified bound of
                ``update_error`` times the prior standard deviation on the change of every draw at any point
                (shared RBF / Matern kernels; ``None``: the exact canonical basis). Makes long paths cheaper.
            scale: a factor c > 0 on every draw's deviation from the posterior mean, ``mu + c (F_s - mu)``: draws
                from the posterior with its covariance times c^2 (a calibrated spread, see
                :mod:`torchmisspec.calibration`); 1 by default.

        Returns:
            :class:`~torchmisspec.gp._paths.FunctionSamples`: ``samples(x)`` maps ``(M, d_in)`` or ``(S, M, d_in)``
            inputs to ``(S, M, d_out)``.
        """
        from ._paths import FunctionSamples, _check_generator, feature_map

        self._require_fitted()
        num_samples = check_positive_int(num_samples, "num_samples")
        generator = _check_generator(generator, self.device)
        features = feature_map(self, num_features=num_features, feature_error=feature_error, generator=generator)
        if update_error is not None:
            update_error = check_real(update_error, "update_error", positive=True)
        scale = check_real(scale, "scale", positive=True)
        return FunctionSamples(self, num_samples, features, generator, update_error, scale=scale)

    # ------------------------------------------------------------------------------------------ hyperparameters
    def laplace_covariance(self) -> tuple[list[str], torch.Tensor, torch.Tensor]:
        """A Laplace approximation of the posterior of the learned hyperparameters, in log space.

        At the fitted (ML-II) values, ``-H`` with H the Hessian of the exact log marginal likelihood in the log
        hyperparameters (autograd through one Cholesky factorization) is the precision of a Gaussian around them;
        a weakly informative prior N(log value, :data:`LOG_PRIOR_SD`^2) on each log hyperparameter is added, which
        keeps the covariance finite where the likelihood is flat (the data barely constrain a hyperparameter, as at
        small K) and clips directions of negative curvature (an optimum on a boundary) to the prior alone.

        Returns:
            ``(names, mean, covariance)``: a name per entry (``"lengthscale"``, ``"outputscale"``,
            ``"noise_variance"``, with an output index for per-output values), the log values ``(P,)`` and the
            ``(P, P)`` covariance. Only the RBF, Matern and polynomial kernels (the feature kernel's weights have
            their own posterior: :meth:`terms`).
        """
        self._require_fitted()
        if self.kernel_spec.terms:
            raise InputError(
                "laplace_covariance: the feature kernel's weights are not log hyperparameters; its uncertainty is "
                "the coefficients' posterior (gp.terms())"
            )
        free = self._free_parameters()
        if not free:
            raise InputError("laplace_covariance: every hyperparameter is fixed; nothing is uncertain")
        params = [p for _, p in free]
        names = []
        for name, p in free:
            n = p.numel()
            names += [name] if n == 1 else [f"{name}[{i}]" for i in range(n)]
        X, Y, noise = self.train_inputs_, self.train_targets_, self.train_noise_
        Yb = self._targets_batched(Y, noise)
        for p in params:
            p.requires_grad_(True)
        try:
            with torch.enable_grad():
                # the kernel written out in torch (GPyTorch's RBF has a custom backward without a second derivative)
                from ._paths import kernel_hyperparameters, kernel_matrix

                K = kernel_matrix(self.kernel_spec, X, X, kernel_hyperparameters(self), self.degree)
                floor = self._floor(self.likelihood).noise.reshape(-1, 1)
                if noise is None:
                    diag = floor
                else:
                    diag = (noise.T if self._batched(noise) else noise[:, 0].unsqueeze(0)) + floor
                if diag.shape[0] != K.shape[0]:
                    K = K.expand(diag.shape[0], -1, -1)
                C = K + torch.diag_embed(diag.expand(K.shape[0], K.shape[-1]))
                L = torch.linalg.cholesky(C)
                alpha = torch.cholesky_solve(Yb, L)
                m = Yb.shape[-1]
                mll = -0.5 * (Yb * alpha).sum() - m * L.diagonal(dim1=-2, dim2=-1).log().sum()
                grads = torch.autograd.grad(mll, params, create_graph=True)
                g = torch.cat([t.reshape(-1) for t in grads])
                rows = [
                    torch.cat([t.reshape(-1) for t in torch.autograd.grad(g[i], params, retain_graph=True)])
                    for i in range(g.numel())
                ]
        except torch.linalg.LinAlgError as exc:
            raise LinearAlgebraError(
                f"laplace_covariance: the training covariance is not positive definite ({exc})"
            ) from exc
        finally:
            self._freeze()
        H = torch.stack(rows).detach()
        H = 0.5 * (H + H.T)
        evals, evecs = torch.linalg.eigh(-H)
        precision = (evecs * evals.clamp_min(0.0)) @ evecs.T + torch.eye(len(names), dtype=H.dtype, device=H.device) / (
            LOG_PRIOR_SD**2
        )
        mean = torch.cat([p.detach().reshape(-1) for p in params])
        return names, mean, torch.linalg.inv(precision)

    def hyperparameter_samples(self, num_samples: int, *, generator: torch.Generator | None = None) -> list:
        """``num_samples`` copies of this GP, each conditioned on the same data with hyperparameters drawn from the
        Laplace approximation of their posterior (:meth:`laplace_covariance`); for predictions that allow for the
        hyperparameters' own uncertainty (ML-II alone is overconfident when the data are few)."""
        num_samples = check_positive_int(num_samples, "num_samples")
        _, mean, cov = self.laplace_covariance()
        root = torch.linalg.cholesky(cov)
        z = torch.randn((num_samples, mean.numel()), generator=generator, dtype=mean.dtype, device=mean.device)
        draws = mean + z @ root.T
        out = []
        for theta in draws:
            copy_ = self.condition(self.train_inputs_, self.train_targets_, noise=self.train_noise_)
            start = 0
            with torch.no_grad():
                for _, p in copy_._free_parameters():
                    p.copy_(theta[start : start + p.numel()].reshape(p.shape))
                    start += p.numel()
            copy_._posterior_cache()
            out.append(copy_)
        return out

    def _value(self, name: str, t: torch.Tensor) -> float | torch.Tensor | None:
        """The value in use; before fitting only a fixed (given) value is in use, otherwise ``None``."""
        if not self.is_fitted:
            return self.fixed[name]
        t = t.detach().reshape(-1)
        return float(t[0]) if (not self.per_output or t.numel() == 1) else t.clone()

    @property
    def lengthscale(self) -> float | torch.Tensor | None:
        """The kernel lengthscale in use (``None`` for the polynomial and feature kernels, or when unfitted and not
        given)."""
        if not self.kernel_spec.has_lengthscale:
            return None
        return self._value("lengthscale", self.covar_module.base_kernel.lengthscale)

    @property
    def outputscale(self) -> float | torch.Tensor | None:
        """The kernel output scale in use (``None`` when unfitted and not given)."""
        return self._value("outputscale", self.covar_module.outputscale)

    @property
    def noise_variance(self) -> float | torch.Tensor | None:
        """The observation-noise variance in use (``None`` when unfitted and not given); with known per-sample
        noise, the floor added to it."""
        return self._value("noise_variance", self._floor(self.likelihood).noise)

    def clone(self, **overrides) -> CorrectionGP:
        """An unfitted model with this one's settings, ``overrides`` replacing any of the constructor's arguments:
        the one way to copy a template.

        The settings are the constructor's: the kernel (``"auto"`` for an auto model; pass ``kernel=gp.kernel_spec``
        for the kernel it chose), the fixed hyperparameters, ``per_output``, ``degree``, the feature library and
        price, ``max_iter``, dtype and device. Settings the new kernel has no use for (a lengthscale for the feature
        kernel, a price of terms for the RBF) are dropped when ``kernel`` is overridden.
        """
        auto = self.auto
        args = {
            "kernel": "auto" if auto else self.kernel_spec,
            "lengthscale": None if auto else self.fixed["lengthscale"],
            "outputscale": None if auto else self.fixed["outputscale"],
            "noise_variance": self.fixed["noise_variance"],
            "per_output": self._auto_per_output if auto else self.per_output,
            "degree": self.degree,
            "max_iter": self.max_iter,
            "dtype": self.dtype,
            "device": self.device,
            "library": self.library,
            "library_names": self.library_names,
            "min_gain": self.min_gain,
            "evidence_margin": self.evidence_margin,
        }
        unknown = sorted(set(overrides) - set(args))
        if unknown:
            raise InputError(f"clone: expected overrides among {sorted(args)}, got {unknown}")
        if "kernel" in overrides:
            kernel = overrides["kernel"]
            new_auto = isinstance(kernel, str) and kernel == "auto"
            spec = None if new_auto else as_kernel(kernel)
            dropped = {
                "lengthscale": new_auto or not spec.has_lengthscale,
                "outputscale": new_auto or (spec.terms != self.kernel_spec.terms),
                "library": not (new_auto or spec.terms),
                "library_names": not (new_auto or spec.terms),
                "min_gain": not (new_auto or spec.terms),
                "evidence_margin": not new_auto,
            }
            args.update({name: None for name, drop in dropped.items() if drop})
        args.update(overrides)
        return type(self)(**args)

    def fixed_copy(self) -> CorrectionGP:
        """A new, unfitted CorrectionGP with every hyperparameter fixed at this one's values in use.

        ``gp.fixed_copy().fit(inputs, targets)`` conditions on new samples without re-learning anything (the paper's
        studies fit every realization with the same prior). Known per-sample noise is data, not a hyperparameter:
        it is not copied (pass it again to ``fit``); the copy's ``noise_variance`` is this one's (floor). Needs every
        hyperparameter to be set (given or fitted).
        """
        values = {
            "lengthscale": self.lengthscale,
            "outputscale": self.outputscale,
            "noise_variance": self.noise_variance,
        }
        if self.kernel_spec.terms:
            raise InputError(
                "fixed_copy: the feature kernel's weights cannot be fixed by value; use gp.condition(inputs, targets) "
                "to condition these hyperparameters on other samples"
            )
        if not self.kernel_spec.has_lengthscale:
            values.pop("lengthscale")
        missing = [k for k, v in values.items() if v is None]
        if missing:
            raise NotFittedError(
                f"fixed_copy: expected every hyperparameter to be set, but {missing} are not; pass them to "
                "CorrectionGP(...) or fit first"
            )
        if self.per_output:
            raise InputError("fixed_copy: per-output hyperparameters cannot be fixed by value; use per_output=False")
        return CorrectionGP(
            kernel=self.kernel_spec,
            degree=self.degree,
            max_iter=self.max_iter,
            dtype=self.dtype,
            device=self.device,
            **{k: float(v) for k, v in values.items()},
        )

    def condition(self, inputs, targets=None, *, noise=None) -> CorrectionGP:
        """A new CorrectionGP with exactly this one's hyperparameters (every kind of kernel, per-output ones too)
        conditioned on other samples: nothing is re-learned. ``condition(samples)`` takes a
        :class:`~torchmisspec.CorrectionSamples` object; ``noise`` is known per-sample noise as in :meth:`fit` (the
        floor ``noise_variance`` is this one's)."""
        self._require_fitted()
        inputs, targets, noise = self._unpack(inputs, targets, noise)
        X = self._check_inputs(inputs, "inputs")
        Y = as_tensor(targets, "targets", dtype=self.dtype, device=self.device)
        Y = Y.unsqueeze(-1) if Y.dim() == 1 else Y
        check_ndim(Y, 2, "targets", "(N, d_out)")
        check_finite(Y, "targets")
        if Y.shape != (X.shape[0], self.output_dim):
            raise ShapeError(
                f"targets: expected ({X.shape[0]}, {self.output_dim}) (one row per input, this GP's outputs), got "
                f"{tuple(Y.shape)}"
            )
        noise = self._check_noise(noise, Y.shape[0], Y.shape[1])
        new = copy.copy(self)
        new.fixed = dict(self.fixed)
        for name in [k for k in vars(new) if k.endswith("_") and not k.startswith("_")]:
            delattr(new, name)  # records of this model's fit (cross_validation_, samples_, state_noise_, ...)
        new.input_names_ = getattr(self, "input_names_", None)  # the same inputs: their names stay
        new.library_suffices_ = None  # kernel="auto": no check made on these data (None, as before any fit)
        new._cache = None
        covar = copy.deepcopy(self.covar_module)
        lik = copy.deepcopy(self.likelihood)
        if noise is not None or isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
            known = None if noise is None else noise.T.clone(memory_format=torch.contiguous_format)
            lik = new._modules(batch=Y.shape[1], noise=known)[1]
            with torch.no_grad():
                new._floor(lik).noise = self._floor(self.likelihood).noise.detach().clone()
        new.model = IndependentOutputsGP(X, Y.T.contiguous(), lik, covar, Y.shape[1]).eval()
        new.n_iterations_, new.n_evaluations_, new.log_marginal_likelihood_ = 0, 0, None
        new._freeze()
        new._posterior_cache()
        return new

    @property
    def weights(self) -> torch.Tensor | None:
        """The feature kernel's term weights ``(p,)`` (``(d_out, p)`` with ``per_output``); ``None`` for other
        kernels or before fitting. A weight of 0 removes its term."""
        if not self.kernel_spec.terms or not self.is_fitted:
            return None
        return self.covar_module.base_kernel.weights.detach().clone()

    def feature_names(self, names=None) -> list[str]:
        """The feature kernel's monomials, e.g. ``["1", "x1", "x2", "x1^2", ...]`` (``names``: one per input; default
        :attr:`input_names_` when the model has them, as :func:`~torchmisspec.fit_correction` records; else x1, x2)."""
        if not self.kernel_spec.terms:
            raise InputError(
                f"feature_names: only the feature kernels have named terms, this GP's kernel is {self.kernel!r}"
            )
        self._require_fitted()
        base = self.covar_module.base_kernel
        powers = base.powers
        if names is None and len(getattr(self, "input_names_", None) or ()) == powers.shape[1]:
            names = list(self.input_names_)
        if names is not None and len(names) != powers.shape[1]:
            raise InputError(f"names: expected {powers.shape[1]} input names, got {len(names)}")
        return base.names(names)

    def terms(self, names=None, *, all_terms: bool = False) -> list[Term]:
        """The learned terms of a feature kernel, with their coefficients' posterior means and standard deviations.

        The posterior of F = sum_j beta_j phi_j(x) given the training samples (and their noise): for each output and
        each term whose weight is not 0 (``all_terms=True``: every term), a :class:`~torchmisspec.gp._features.Term`
        with its posterior probability of being present (``inclusion``)
        whose ``str`` reads like ``"+0.01 +- 0.0003 * y1^2"``. ``names``: the inputs' names (default
        :attr:`input_names_`, the data's names that :func:`~torchmisspec.fit_correction` records, else x1, x2, ...).
        """
        labels = self.feature_names(names)
        base = self.covar_module.base_kernel
        X, Y, known = self.train_inputs_, self.train_targets_, self.train_noise_
        Phi = base.features(X).detach()
        if not self.kernel_spec.feature_space:  # the coefficients' posterior under the whole kernel (RBF term too)
            fac = self._posterior_cache().fac  # dense: C = Phi W Phi^T + a K_rbf + noise
            w = base.weights.detach().reshape(-1) * self.covar_module.outputscale.detach().reshape(())
            out = []
            with torch.no_grad():
                for o in range(Y.shape[1]):
                    # one factor for every output, or one per output (known noise that differs between outputs)
                    chol = fac.chol[0 if fac.chol.shape[0] == 1 else o]
                    V = torch.linalg.solve_triangular(chol, Phi * w, upper=False)  # L^-1 Phi W
                    std = (w - V.pow(2).sum(0)).clamp_min(0.0).sqrt()
                    alpha = fac.alpha[0, :, o] if fac.alpha.shape[0] == 1 else fac.alpha[o, :, 0]
                    mean = w * (Phi.T @ alpha)
                    for j, label in enumerate(labels):
                        if all_terms or float(w[j]) > 0:
                            out.append(Term(o, label, float(mean[j]), float(std[j]), float(w[j])))
            return out
        W = base.weights.detach().reshape(-1, Phi.shape[1]) * self.covar_module.outputscale.detach().reshape(-1, 1)
        inclusion = base.inclusion.reshape(W.shape)
        floor = self._floor(self.likelihood).noise.detach().reshape(-1)
        out = []
        for o in range(Y.shape[1]):
            b = o if W.shape[0] > 1 else 0
            D = floor[o if floor.numel() > 1 else 0] + (0.0 if known is None else known[:, o])
            D = torch.as_tensor(D, dtype=self.dtype, device=self.device).expand(Y.shape[0])
            mean, std = coefficient_posterior(Phi, Y[:, o], D, W[b])
            for j, label in enumerate(labels):
                if all_terms or float(W[b, j]) > 0:
                    out.append(Term(o, label, float(mean[j]), float(std[j]), float(W[b, j]), float(inclusion[b, j])))
        return out

    def __repr__(self) -> str:
        state = f"fitted on N={self.train_inputs_.shape[0]}" if self.is_fitted else "not fitted"
        if self.train_noise_ is not None:
            state += " with known noise"
        return (
            f"CorrectionGP(kernel={self.kernel!r}, lengthscale={self.lengthscale}, outputscale={self.outputscale}, "
            f"noise_variance={self.noise_variance}, per_output={self.per_output}; {state})"
        )

    # ------------------------------------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> Path:
        """Save a fitted model (configuration, hyperparameters, training data); see :mod:`._persistence`."""

        return _save(self, path)

    @classmethod
    def load(cls, path: str | Path, *, device: torch.device | str | None = None) -> CorrectionGP:
        """Load a model written by :meth:`save` (no code is executed); the posterior cache is rebuilt."""

        return _load(cls, path, device=device)
