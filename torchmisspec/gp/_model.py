"""The correction model: a Gaussian process for F with independent outputs sharing one kernel (paper §3.1).

F ~ GP(0, k(y, y') I_{d_out}). Because the kernel is shared, the d_out outputs have the same covariance
K + sigma^2 I, so **one** Cholesky factorization serves all of them, in the marginal likelihood as in the
posterior. The hyperparameters and the training data live in a GPyTorch ``ExactGP`` (``gp.model``: a batch of
d_out independent outputs, GPyTorch kernels, likelihood and constraints). :class:`CorrectionGP` is the front; each
idea behind it has its own module:

* the kernels as objects: :mod:`._kernels`; the checked settings: :mod:`._settings`; the GPyTorch modules:
  :mod:`._exact`;
* the fit by exact marginal likelihood with an analytic gradient (GPyTorch's ``ExactMarginalLogLikelihood`` would
  factorize the shared matrix once per output and switch to conjugate gradients above 800 points): :mod:`._fit`,
  :mod:`._mll`; ``kernel="auto"``'s choice by evidence: :mod:`._selection`;
* the posterior, one cached factorization: :mod:`._posterior` (``gp.posterior()``); copies and conditioning:
  :mod:`._conditioning`; the hyperparameters' Laplace posterior: :mod:`._laplace`; draws of F as functions:
  :mod:`._paths`; save / load: :mod:`._persistence`.

**Known per-sample noise** (``fit(..., noise=...)``, heteroscedastic): the covariance of output j is
K + diag(known_j + floor), the known variances plus the ``noise_variance`` hyperparameter (a learned or fixed floor).
Noise the same for every output (``(N,)``) keeps one factorization for all outputs; noise that differs between
outputs (``(N, d_out)``) needs one per output (the per-output batch layout ``(d_out, N, N)``, with the shared kernel
expanded). ``gp.model`` then holds a GPyTorch ``FixedNoiseGaussianLikelihood`` (known noise plus a learned floor), so
the ExactGP view and the cached posterior still agree.
"""

from __future__ import annotations

from pathlib import Path

import gpytorch
import torch

from .._errors import FittingError, NotFittedError
from .._validation import DEFAULT_DTYPE, as_tensor, check_generator, check_positive_int, check_real
from ..parallel import adaptive_threads
from . import _conditioning
from ._exact import IndependentOutputsGP, build_modules, median_distance, noise_module
from ._fit import fit_model
from ._inputs import check_inputs, check_samples
from ._kernels import Kernel, as_kernel
from ._large import LARGE_N, Matern52Features, RBFFeatures
from ._persistence import load as _load
from ._persistence import save as _save
from ._posterior import GPPosterior, Posterior
from ._prior import prior_hyperparameters
from ._readout import Readout
from ._selection import fit_auto
from ._settings import check_settings

__all__ = ["CorrectionGP", "GPPosterior", "KERNELS"]

KERNELS = ("rbf", "matern52", "polynomial", "features", "features+rbf", "auto")


def _identical_columns(noise: torch.Tensor) -> bool:
    """Known noise ``(N, d_out)`` the same for every output (then one factorization serves all outputs)."""
    return bool((noise == noise[:, :1]).all())


class CorrectionGP(Readout):
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
        exact: how a shared RBF or Matern 5/2 kernel is computed (:mod:`torchmisspec.gp._large`): ``None``
            (default) exactly up to :data:`~torchmisspec.gp._large.LARGE_N` samples and in a feature space above
            (``kernel_spec`` is then :class:`~torchmisspec.gp.RBFFeatures` or
            :class:`~torchmisspec.gp.Matern52Features`, ``approximation`` reports its bound); ``True`` always exactly
            (O(N^3)); ``False`` always in the feature space.
        dtype: of the model's tensors (float64 by default: recommended for GP maths).
        device: of the model's tensors (the CPU by default).

    After :meth:`fit`: ``lengthscale``, ``outputscale`` and ``noise_variance`` hold the values in use (floats, or
    tensors ``(d_out,)`` when ``per_output``; with known per-sample noise, ``noise_variance`` is the floor added to
    it); ``train_noise_`` the known noise ``(N, d_out)`` or ``None``; ``log_marginal_likelihood_`` the exact log
    marginal likelihood (nats, summed over outputs) at those values; ``n_iterations_`` (-1: stopped at a trial it
    could not factorize) and ``n_evaluations_`` the final optimisation pass's; ``model`` the GPyTorch ``ExactGP``
    holding the hyperparameters and the training data. With ``kernel="auto"``, ``kernel`` is the kernel chosen and
    ``model_selection_`` a list of dictionaries (``kernel``, ``log_marginal_likelihood``, ``hyperparameters``
    (the number learned), ``score`` (:attr:`evidence_score`), ``seconds``, ``error`` of a candidate that failed,
    ``eligible`` (allowed by :func:`library_check`), ``chosen``; features+rbf's also ``library_score``, the score of
    the feature kernel it nests) and ``library_suffices_`` the outcome of that check (``None``: not made; neither is
    saved with the model).
    """

    #: the :class:`~torchmisspec.prediction.calibration.BandCalibration` of this fit's bands
    #: (``CorrectedODE.calibrate``), saved with the model; ``None`` until calibrated, and again after a refit
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
        exact: bool | None = None,
    ) -> None:
        c = check_settings(
            kernel=kernel,
            lengthscale=lengthscale,
            outputscale=outputscale,
            noise_variance=noise_variance,
            per_output=per_output,
            degree=degree,
            max_iter=max_iter,
            dtype=dtype,
            device=device,
            library=library,
            library_names=library_names,
            min_gain=min_gain,
            evidence_margin=evidence_margin,
            exact=exact,
        )
        #: kernel="auto": every fit chooses among AUTO_KERNELS by evidence (self.kernel is then the one chosen)
        self.auto: bool = c["auto"]
        #: the kernel object (:mod:`torchmisspec.gp._kernels`); ``kernel`` is its name (an RBF until an auto fit)
        self.kernel_spec: Kernel = c["kernel"]
        #: the kernel asked for; with ``exact=None`` an RBF or Matern 5/2 is fitted in a feature space above LARGE_N
        #: samples, and ``kernel_spec`` is then its features kernel (``RBFFeatures``) until a fit on fewer samples
        self.requested_kernel: Kernel = c["kernel"]
        #: None: exact up to LARGE_N samples, in a feature space above (RBF, Matern); True: always exact; False: always
        #: in a feature space
        self.exact: bool | None = c["exact"]
        #: the hyperparameters given (held fixed), ``None`` for those learned
        self.fixed: dict = c["fixed"]
        #: the feature kernel's price of a term in nats per learned weight (None: half the log of the sample count)
        self.min_gain: float | None = c["min_gain"]
        #: kernel="auto": the nats by which a candidate must outscore the RBF to be chosen instead (None otherwise)
        self.evidence_margin: float | None = c["evidence_margin"]
        #: user features replacing the monomials (callables x (..., d_in) -> (...,)), and their names
        self.library, self.library_names = c["library"], c["library_names"]
        self.per_output: bool = c["per_output"]
        self._auto_per_output = self.per_output  # what kernel="auto" was asked for (the chosen model may differ)
        self.degree: int = c["degree"]
        self.max_iter: int = c["max_iter"]
        self.dtype: torch.dtype = c["dtype"]
        self.device: torch.device = c["device"]
        #: kernel="auto": whether the last fit's library check found the library sufficient (None: not checked)
        self.library_suffices_: bool | None = None
        self._d_in = 1  # the feature kernel's input dimension (set by fit)
        self.log_marginal_likelihood_: float | None = None
        self.n_iterations_: int = 0
        self.n_evaluations_: int = 0
        self._cache: Posterior | None = None
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
        * ``lengthscale = lengthscale_fraction *`` the mean side length of D (``system.domain``); where D's sides
          differ (a biomass over 3 units and a temperature over 12 degrees) the kernel sees each input divided by its
          side over the mean side (``input_scale``), so that each input's lengthscale is that fraction of its own
          side;
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
                in the correction inputs (states, then controls: F may depend on the system's inputs, and G is then
                evaluated at those controls, at t = 0), the other components at 0. A system with controls takes
                the default only.
            grid_size: points per axis of the default grid (at least 2).
            **kwargs: other constructor arguments (``dtype``, ``device``, ``max_iter``).
        """
        return cls(
            **prior_hyperparameters(
                system,
                noise_variance=noise_variance,
                relative_size=relative_size,
                lengthscale_fraction=lengthscale_fraction,
                kernel=kernel,
                states=states,
                grid_size=grid_size,
                dtype=kwargs.get("dtype", DEFAULT_DTYPE),
                device=kwargs.get("device"),
            ),
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
        for p in self.model.parameters():  # no stale gradient of the fit, to add to a user's own backward
            p.grad = None

    def _hyperparameters_require_grad(self) -> bool:
        return any(p.requires_grad for p in self.model.parameters())

    # ------------------------------------------------------------------------------------------------ building
    def _modules(self, batch: int, noise: torch.Tensor | None = None):
        return build_modules(self, batch, noise)

    @staticmethod
    def _floor(lik) -> gpytorch.likelihoods.noise_models.HomoskedasticNoise:
        return noise_module(lik)

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
        kd = dict(dtype=X.dtype, device=X.device)
        var = Y.pow(2).mean(dim=0)  # (d_out,)
        var = torch.where(var > 0, var, var.max()) if self.per_output else var.mean()
        out = {"outputscale": var, "noise_variance": 1e-2 * var}
        if self.kernel_spec.has_lengthscale:  # in the units the kernel sees (an input_scale's)
            out["lengthscale"] = torch.tensor(median_distance(self.kernel_spec.scaled_inputs(X)), **kd)
        return out

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
        X, Y, noise = check_samples(self, inputs, targets, noise)
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
        spec_before = self.kernel_spec
        try:
            spec = self._kernel_for(X.shape[0])
            if spec != self.kernel_spec:  # an RBF on many samples (or on few again): the other kernel's modules
                self.kernel_spec = spec
                covar, lik = self._modules(batch=1)
                self.model = IndependentOutputsGP(None, None, lik, covar, 1).eval()
                free = [name for name, _ in self._free_parameters()]
            fit_model(self, X, Y, noise, bool(free), progress=progress, max_iter=max_iter, warm_start=warm_start)
        except BaseException:
            self.kernel_spec = spec_before
            self.model, self._cache, self.n_iterations_, self.n_evaluations_, self.log_marginal_likelihood_ = before
            self.covar_module.load_state_dict(saved[0])
            self.likelihood.load_state_dict(saved[1])
            raise
        self.__dict__.pop("calibration_", None)  # a calibration of the bands belongs to the fit it was made for
        self.__dict__.pop("refinement_", None)  # and so does a refinement through the ODE
        return self

    def _kernel_for(self, n: int) -> Kernel:
        """The kernel a fit on ``n`` samples uses: the one asked for, except a shared RBF's (without an
        ``input_scale``), which is computed in a feature space above :data:`~torchmisspec.gp._large.LARGE_N` samples
        (``exact=None``) or always (``exact=False``)."""
        asked = self.requested_kernel
        large = {"rbf": RBFFeatures, "matern52": Matern52Features}.get(asked.name)
        scaled = getattr(asked, "input_scale", None) is not None  # the feature space has no scale per input
        if self.auto or self.per_output or large is None or self.exact is True or scaled:
            return asked
        return large() if self.exact is False or n > LARGE_N else asked

    # --------------------------------------------------------------------------------------------- the posterior
    def posterior(self, *, differentiable: bool = False) -> Posterior:
        """The posterior of F given the training data (:class:`~torchmisspec.gp._posterior.Posterior`): its mean,
        variance and covariance, the factor of the training covariance, function draws.

        Cached: rebuilt (one factorization) only when a hyperparameter or the training data changed since the last
        call. ``differentiable=True``: a fresh one whose solve keeps the autograd graph to the hyperparameters that
        require grad (for sensitivities of predictions), not cached.
        """
        self._require_fitted()
        if differentiable:
            self.posterior()  # the cached one validates the training data and noise (no second factorization)
            return Posterior.build(self, differentiable=True)
        if self._cache is not None and self._cache.is_current(self):
            return self._cache
        self._cache = Posterior.build(self)
        self.log_marginal_likelihood_ = self._cache.log_marginal_likelihood
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
        x1 = check_inputs(self, x1, "x1")
        x2 = x1 if x2 is None else check_inputs(self, x2, "x2")
        with torch.no_grad():
            return self.covar_module.forward(x1, x2)

    def predict_mean(self, x) -> torch.Tensor:
        """Posterior mean of F at ``x (M, d_in)``: ``(M, d_out)`` (:meth:`Posterior.mean`). One kernel block times
        the cached solve.

        Differentiable with respect to ``x`` when ``x`` requires grad (autograd flows through the kernel; the cached
        solve is a constant, so no gradient reaches the hyperparameters). Never refactorizes unless the
        hyperparameters or the training data changed since the last prediction.
        """
        return self.posterior().mean(x)

    def predict(self, x) -> GPPosterior:
        """Posterior mean and variance of F itself (no observation noise) at ``x (M, d_in)``, each ``(M, d_out)``."""
        return self.posterior().predict(x)

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
                :mod:`torchmisspec.prediction.calibration`); 1 by default.

        Returns:
            :class:`~torchmisspec.gp._paths.FunctionSamples`: ``samples(x)`` maps ``(M, d_in)`` or ``(S, M, d_in)``
            inputs to ``(S, M, d_out)``.
        """
        from ._paths import FunctionSamples, feature_map

        self._require_fitted()
        num_samples = check_positive_int(num_samples, "num_samples")
        generator = check_generator(generator, self.device)
        features = feature_map(self, num_features=num_features, feature_error=feature_error, generator=generator)
        if update_error is not None:
            update_error = check_real(update_error, "update_error", positive=True)
        scale = check_real(scale, "scale", positive=True)
        return FunctionSamples(self, num_samples, features, generator, update_error, scale=scale)

    def clone(self, **overrides) -> CorrectionGP:
        """An unfitted model with this one's settings, ``overrides`` replacing any of the constructor's arguments:
        the one way to copy a template.

        The settings are the constructor's: the kernel (``"auto"`` for an auto model; pass ``kernel=gp.kernel_spec``
        for the kernel it chose), the fixed hyperparameters, ``per_output``, ``degree``, the feature library and
        price, ``max_iter``, dtype and device. Settings the new kernel has no use for (a lengthscale for the feature
        kernel, a price of terms for the RBF) are dropped when ``kernel`` is overridden.
        """
        return _conditioning.clone(self, **overrides)

    def condition(self, inputs, targets=None, *, noise=None) -> CorrectionGP:
        """A new CorrectionGP with exactly this one's hyperparameters (every kind of kernel, per-output ones too)
        conditioned on other samples: nothing is re-learned; the one way to condition a model on data.
        ``condition(samples)`` takes a :class:`~torchmisspec.CorrectionSamples` object; ``noise`` is known per-sample
        noise as in :meth:`fit` (the floor ``noise_variance`` is this one's). An unfitted model conditions with the
        hyperparameters it was given (all of them: e.g. :meth:`prior`)."""
        return _conditioning.condition(self, inputs, targets, noise=noise)

    # ------------------------------------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> Path:
        """Save a fitted model (configuration, hyperparameters, training data); see :mod:`._persistence`."""

        return _save(self, path)

    @classmethod
    def load(cls, path: str | Path, *, device: torch.device | str | None = None) -> CorrectionGP:
        """Load a model written by :meth:`save` (no code is executed); the posterior cache is rebuilt."""

        return _load(cls, path, device=device)
