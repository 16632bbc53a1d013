"""The correction model: a Gaussian process for F with independent outputs sharing one kernel (paper §3.1).

F ~ GP(0, k(y, y') I_{d_out}). Because the kernel is shared, the d_out outputs have the same covariance
K + sigma^2 I, so **one** Cholesky factorization serves all of them, in the marginal likelihood as in the
posterior. The model is a GPyTorch ``ExactGP`` (batch of d_out independent outputs), with GPyTorch kernels,
likelihood and parameter constraints. Two choices depart from GPyTorch's defaults, on purpose:

* Training maximises the exact log marginal likelihood computed with one Cholesky of the shared N x N
  covariance. GPyTorch's ``ExactMarginalLogLikelihood`` would factorize the same matrix once per output and,
  above 800 points, switch to conjugate gradients and stochastic Lanczos (an approximation).
* The posterior solve alpha = (K + sigma^2 I)^-1 Y and the Cholesky factor are cached once after fitting;
  ``predict_mean`` then costs one kernel block k(x, X) @ alpha, which is what an ODE right-hand side needs.

Positive hyperparameters are optimised in log space (as scikit-learn does), which keeps small output scales and
noise variances (1e-5 .. 1e-4 in the paper) well conditioned for L-BFGS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import gpytorch
import torch

from ._errors import FittingError, InputError, NotFittedError, NotPositiveDefiniteError, ShapeError
from ._validation import DEFAULT_DTYPE, as_tensor, check_finite, check_ndim, progress_bar

__all__ = ["CorrectionGP", "GPPosterior", "KERNELS", "cholesky_with_jitter"]

KERNELS = ("rbf", "matern52", "polynomial")
_MIN_VALUE = 1e-12  # floor of every positive hyperparameter


def _log_positive() -> gpytorch.constraints.Interval:
    """A positive constraint whose raw value is the log of the hyperparameter."""
    return gpytorch.constraints.GreaterThan(_MIN_VALUE, transform=torch.exp, inv_transform=torch.log)


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


def cholesky_with_jitter(K: torch.Tensor, *, max_tries: int = 6, what: str = "covariance") -> torch.Tensor:
    """Lower Cholesky factor of ``K (..., n, n)``; adds growing jitter (1e-10 .. 1e-5 of the mean diagonal).

    Raises:
        NotPositiveDefiniteError: if the factorization fails even with the largest jitter.
    """
    L, info = torch.linalg.cholesky_ex(K)
    if not bool((info != 0).any()):
        return L
    scale = K.diagonal(dim1=-2, dim2=-1).abs().mean().clamp_min(torch.finfo(K.dtype).tiny)
    eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
    for i in range(max_tries):
        jitter = scale * 10.0 ** (-10 + i)
        L, info = torch.linalg.cholesky_ex(K + jitter * eye)
        if not bool((info != 0).any()):
            return L
    raise NotPositiveDefiniteError(
        f"{what}: expected a positive definite matrix of size {K.shape[-1]}, but its Cholesky factorization "
        f"failed even with jitter {float(jitter):.1e} added to the diagonal (is the noise variance zero with "
        "repeated inputs, or are there NaNs?); use a larger noise_variance or remove duplicate inputs"
    )


def _solve(K: torch.Tensor, diag: torch.Tensor, Yb: torch.Tensor):
    """Factorize C = K + diag I ``(B, N, N)`` once: (L, alpha = C^-1 Yb, total logdet C, sum Yb * alpha)."""
    C = K + torch.diag_embed(diag.expand(-1, K.shape[-1]))
    L = cholesky_with_jitter(C, what="K + noise_variance * I")
    alpha = torch.cholesky_solve(Yb, L)
    logdet = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum()
    return L, alpha, logdet, (Yb * alpha).sum()


class _IndependentOutputsGP(gpytorch.models.ExactGP):
    """GPyTorch ExactGP: d_out independent outputs (a batch) sharing one kernel."""

    def __init__(self, train_x, train_y, likelihood, covar_module, num_outputs: int) -> None:
        super().__init__(train_x, train_y, likelihood)  # train_y: (d_out, N)
        self.num_outputs = num_outputs
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=torch.Size([num_outputs]))
        self.covar_module = covar_module

    def forward(self, x):
        mean = self.mean_module(x)
        covar = self.covar_module(x)
        if covar.dim() == 2:  # shared kernel: the same covariance for every output
            covar = covar.expand(self.num_outputs, *covar.shape)
        return gpytorch.distributions.MultivariateNormal(mean, covar)


class CorrectionGP:
    """Gaussian-process model of the correction F, trained by exact marginal likelihood.

    Args:
        kernel: ``"rbf"`` (exp(-||y - y'||^2 / (2 l^2))), ``"matern52"``, or ``"polynomial"``
            ((1 + <y, y'>)^degree, the paper's polynomial kernel); each scaled by ``outputscale``.
        lengthscale, outputscale, noise_variance: a value passed here is held fixed; ``None`` means learned.
            ``lengthscale`` is the RBF/Matern l (the paper's sigma_k^2 = l^2); it does not apply to the polynomial
            kernel. ``noise_variance`` is the variance of the observation noise on the samples of F.
        per_output: one set of hyperparameters per output (costs one factorization per output) instead of the
            paper's shared kernel.
        degree: the polynomial kernel's order m.
        max_iter: most L-BFGS iterations when fitting.
        dtype, device: of the model's tensors (float64 by default: recommended for GP maths).

    After :meth:`fit`, ``lengthscale``, ``outputscale`` and ``noise_variance`` hold the values in use (floats, or
    tensors ``(d_out,)`` when ``per_output``), and ``log_marginal_likelihood_`` the total exact log marginal
    likelihood (nats, summed over outputs) at those values.
    """

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
    ) -> None:
        if kernel not in KERNELS:
            raise InputError(f"kernel: expected one of {KERNELS}, got {kernel!r}")
        if kernel == "polynomial" and lengthscale is not None:
            raise InputError("lengthscale: the polynomial kernel (1 + <y, y'>)^m has no lengthscale; pass None")
        if kernel == "polynomial" and (isinstance(degree, bool) or not isinstance(degree, int) or degree < 1):
            raise InputError(f"degree: expected a positive integer, got {degree!r}")
        for name, value in (
            ("lengthscale", lengthscale),
            ("outputscale", outputscale),
            ("noise_variance", noise_variance),
        ):
            if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name}: expected a positive finite number or None (learned), got {value!r}")
        if not dtype.is_floating_point:
            raise InputError(f"dtype: expected a floating dtype, got {dtype}")
        self.kernel = kernel
        self.fixed = {"lengthscale": lengthscale, "outputscale": outputscale, "noise_variance": noise_variance}
        self.per_output = bool(per_output)
        self.degree = degree
        self.max_iter = int(max_iter)
        self.dtype = dtype
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.covar_module: gpytorch.kernels.ScaleKernel | None = None
        self.likelihood: gpytorch.likelihoods.GaussianLikelihood | None = None
        self.model: _IndependentOutputsGP | None = None
        self.train_inputs_: torch.Tensor | None = None
        self.train_targets_: torch.Tensor | None = None
        self.log_marginal_likelihood_: float | None = None
        self.n_iter_: int = 0
        self._chol: torch.Tensor | None = None  # (B, N, N), B = 1 shared or d_out per output
        self._alpha: torch.Tensor | None = None  # (B, N, d_out) or (d_out, N, 1)
        if not self.per_output:
            self._build(batch=1)

    def fixed_copy(self) -> CorrectionGP:
        """A new, unfitted CorrectionGP with every hyperparameter fixed at this one's values in use.

        ``gp.fixed_copy().fit(inputs, targets)`` conditions on new samples without re-learning anything (the paper's
        studies fit every realization with the same prior). Needs every hyperparameter to be set (given or fitted).
        """
        values = {
            "lengthscale": self.lengthscale,
            "outputscale": self.outputscale,
            "noise_variance": self.noise_variance,
        }
        if self.kernel == "polynomial":
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
            kernel=self.kernel,
            degree=self.degree,
            max_iter=self.max_iter,
            dtype=self.dtype,
            device=self.device,
            **{k: float(v) for k, v in values.items()},
        )

    # ------------------------------------------------------------------------------------------------ building
    def _build(self, batch: int) -> None:
        shape = torch.Size([]) if not self.per_output else torch.Size([batch])
        if self.kernel == "rbf":
            base = gpytorch.kernels.RBFKernel(batch_shape=shape, lengthscale_constraint=_log_positive())
        elif self.kernel == "matern52":
            base = gpytorch.kernels.MaternKernel(nu=2.5, batch_shape=shape, lengthscale_constraint=_log_positive())
        else:
            base = gpytorch.kernels.PolynomialKernel(power=self.degree, batch_shape=shape)
            base.offset = 1.0
            base.raw_offset.requires_grad_(False)
        covar = gpytorch.kernels.ScaleKernel(base, batch_shape=shape, outputscale_constraint=_log_positive())
        lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=shape, noise_constraint=_log_positive())
        covar, lik = covar.to(self.device, self.dtype), lik.to(self.device, self.dtype)

        # GPyTorch's setters would round a Python float through float32: pass tensors of the model's dtype
        def value(name):
            return torch.tensor(self.fixed[name], dtype=self.dtype, device=self.device)

        if self.fixed["lengthscale"] is not None:
            base.lengthscale = value("lengthscale")
        if self.fixed["outputscale"] is not None:
            covar.outputscale = value("outputscale")
        if self.fixed["noise_variance"] is not None:
            lik.noise = value("noise_variance")
        self.covar_module, self.likelihood = covar, lik

    def _free_parameters(self) -> list[tuple[str, torch.nn.Parameter]]:
        params = []
        if self.kernel != "polynomial" and self.fixed["lengthscale"] is None:
            params.append(("lengthscale", self.covar_module.base_kernel.raw_lengthscale))
        if self.fixed["outputscale"] is None:
            params.append(("outputscale", self.covar_module.raw_outputscale))
        if self.fixed["noise_variance"] is None:
            params.append(("noise_variance", self.likelihood.noise_covar.raw_noise))
        return params

    def _initialise(self, X: torch.Tensor, Y: torch.Tensor) -> None:
        """Data-driven starting values for the learned hyperparameters (the fixed ones are already set)."""
        var = Y.var(dim=0, unbiased=False).clamp_min(1e-10)  # (d_out,); floored for constant targets
        var = var if self.per_output else var.mean()
        with torch.no_grad():
            if self.kernel != "polynomial" and self.fixed["lengthscale"] is None:
                sub = X[torch.linspace(0, X.shape[0] - 1, min(X.shape[0], 500), device=X.device).long()]
                dist = torch.cdist(sub, sub)
                positive = dist[dist > 0]
                med = positive.median() if positive.numel() else torch.ones((), dtype=X.dtype, device=X.device)
                self.covar_module.base_kernel.lengthscale = med.clamp_min(1e-6).expand(
                    self.covar_module.base_kernel.lengthscale.shape
                )
            if self.fixed["outputscale"] is None:
                self.covar_module.outputscale = var.expand(self.covar_module.outputscale.shape)
            if self.fixed["noise_variance"] is None:
                noise = (1e-2 * var).reshape(-1, 1) if self.per_output else (1e-2 * var).reshape(1)
                self.likelihood.noise = noise

    # ----------------------------------------------------------------------------------------------- the maths
    def _kernel_parts(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """C = K + sigma^2 I as kernel part ``(B, N, N)`` and diagonal ``(B, 1)``; B = 1 shared, d_out per output."""
        K = self.covar_module.forward(X, X)
        return (K.unsqueeze(0) if K.dim() == 2 else K), self.likelihood.noise.reshape(-1, 1)

    def _targets_batched(self, Y: torch.Tensor) -> torch.Tensor:
        """Targets arranged to match ``(B, N, N)``: shared -> ``(1, N, d_out)``; per output -> ``(d_out, N, 1)``."""
        return Y.T.unsqueeze(-1) if self.per_output else Y.unsqueeze(0)

    def _exact_mll(self, X: torch.Tensor, Y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exact log marginal likelihood summed over outputs, with one factorization per distinct covariance."""
        n, d_out = Y.shape
        L, alpha, logdet, quad = _solve(*self._kernel_parts(X), self._targets_batched(Y))
        outputs_per_factor = 1 if self.per_output else d_out
        mll = -0.5 * quad - 0.5 * outputs_per_factor * logdet - 0.5 * n * d_out * math.log(2 * math.pi)
        return mll, L, alpha

    # ------------------------------------------------------------------------------------------------- fitting
    def _check_inputs(self, x, name: str) -> torch.Tensor:
        x = as_tensor(x, name, dtype=self.dtype, device=self.device)
        if x.dim() == 1 and self.train_inputs_ is not None and self.train_inputs_.shape[1] == 1:
            x = x.unsqueeze(-1)
        check_ndim(x, 2, name, "(M, d_in)")
        check_finite(x, name)
        if self.train_inputs_ is not None and x.shape[1] != self.train_inputs_.shape[1]:
            raise ShapeError(
                f"{name}: expected {self.train_inputs_.shape[1]} input columns (as in training), got "
                f"shape {tuple(x.shape)}"
            )
        return x

    def fit(
        self, inputs, targets, *, progress: bool = False, max_iter: int | None = None, warm_start: int = 500
    ) -> CorrectionGP:
        """Fit to samples of F: ``inputs (N, d_in)``, ``targets (N, d_out)``. Returns ``self``.

        The learned hyperparameters maximise the exact log marginal likelihood (L-BFGS with strong Wolfe line
        search, in log space, from data-driven starting values). When N > 2 * ``warm_start``, a first pass on an
        evenly spaced subsample of ``warm_start`` points provides the starting values (0 disables it).
        ``progress=True`` shows a progress bar.
        """
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
        d_out = Y.shape[1]
        if self.per_output and (self.covar_module is None or self.covar_module.batch_shape != torch.Size([d_out])):
            self._build(batch=d_out)
        self.train_inputs_, self.train_targets_ = X, Y
        free = self._free_parameters()
        if any(name in ("outputscale", "noise_variance") for name, _ in free) and not bool((Y != 0).any()):
            raise FittingError(
                "targets: expected some non-zero samples to learn the output scale and noise from, got all zeros "
                "(the likelihood grows without bound as both shrink to 0); fix them: CorrectionGP(outputscale=..., "
                "noise_variance=...)"
            )
        if free:
            self._initialise(X, Y)
            params = [p for _, p in free]
            if warm_start and X.shape[0] > 2 * warm_start:
                # a cheap first pass on an evenly spaced subsample puts L-BFGS near the optimum; the second pass
                # on all the data then needs few O(N^3) evaluations (the result maximises the full likelihood)
                sub = torch.linspace(0, X.shape[0] - 1, warm_start, device=X.device).round().long()
                self._optimise(params, X[sub], Y[sub], progress=False, max_iter=max_iter or self.max_iter)
            self._optimise(params, X, Y, progress=progress, max_iter=max_iter or self.max_iter)
        self._refresh_cache()
        return self

    def _optimise(self, params, X, Y, *, progress: bool, max_iter: int) -> None:
        """L-BFGS on the exact log marginal likelihood with analytic gradients.

        The gradient of the log marginal likelihood with respect to any hyperparameter theta of C = K + sigma^2 I is
        0.5 * sum(Q * dC/dtheta) with Q = alpha alpha^T - m C^-1 (m outputs share C). Q is formed from one Cholesky;
        autograd then only differentiates the cheap O(N^2) kernel evaluation sum(Q.detach() * C(theta)), never
        the O(N^3) factorization (3-4x cheaper than backpropagating through ``torch.linalg.cholesky``).

        When the output scale and the noise are both learned with a shared kernel, the output scale s is profiled
        out in closed form: C = s (R + g I), s* = y^T (R + g I)^-1 y / (N d_out), leaving only the lengthscale
        and the noise ratio g for L-BFGS (the same optimum of the same likelihood, in fewer iterations).
        """
        n, d_out = Y.shape
        profile = not self.per_output and self.fixed["outputscale"] is None and self.fixed["noise_variance"] is None
        Yb = self._targets_batched(Y)
        m = 1 if self.per_output else d_out
        const = 0.5 * n * d_out * math.log(2 * math.pi)
        if profile:
            log_ratio = (self.likelihood.noise.detach() / self.covar_module.outputscale.detach()).log().reshape(1)
            log_ratio = log_ratio.clone().requires_grad_(True)
            params = [
                p
                for p in params
                if p is not self.covar_module.raw_outputscale and p is not self.likelihood.noise_covar.raw_noise
            ] + [log_ratio]

        def matrices(with_grad: bool):
            """(kernel part (B, N, N), diagonal (B, 1)) of C, the unit-scale kernel and ratio g when profiling."""
            with torch.set_grad_enabled(with_grad):
                if profile:
                    return self.covar_module.base_kernel.forward(X, X).unsqueeze(0), log_ratio.exp().reshape(1, 1)
                return self._kernel_parts(X)

        def evaluate(K: torch.Tensor, diag: torch.Tensor):
            """Log marginal likelihood, Q = dmll/dC * 2 and the profiled scale (None unless profiling)."""
            with torch.no_grad():
                L, alpha, logdet, quad = _solve(K, diag, Yb)
                if profile:
                    scale = quad / (n * d_out)
                    mll = -0.5 * n * d_out * (torch.log(2 * math.pi * scale) + 1.0) - 0.5 * d_out * logdet
                    Q = torch.cholesky_inverse(L).mul_(-d_out).add_(alpha @ alpha.transpose(-1, -2), alpha=1 / scale)
                else:
                    scale = None
                    mll = -0.5 * quad - 0.5 * m * logdet - const
                    Q = torch.cholesky_inverse(L).mul_(-m).add_(alpha @ alpha.transpose(-1, -2))
            return mll, Q, scale

        bar = progress_bar(progress, max_iter, f"fit GP (N={n})", "eval")
        per_sample = float(n * d_out)  # optimise the mean per-sample value: O(1) gradients
        state = {"evals": 0, "scale": None}
        opt = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=max_iter,
            history_size=20,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-7,
            tolerance_change=1e-12,
        )

        def closure():
            opt.zero_grad()
            K, diag = matrices(True)
            mll, Q, scale = evaluate(K.detach(), diag.detach())
            surrogate = 0.5 * (Q * K).sum() + 0.5 * (Q.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True) * diag).sum()
            (-surrogate / per_sample).backward()
            state["evals"] += 1
            state["scale"] = scale
            if bar is not None:
                bar.update(1)
                bar.set_postfix(mll=f"{float(mll):.6g}")
            return -mll / per_sample

        try:
            opt.step(closure)
            if profile:  # write the profiled output scale and the noise back into the GPyTorch modules
                _, _, scale = evaluate(*matrices(False))
                with torch.no_grad():
                    self.covar_module.outputscale = scale.clamp_min(_MIN_VALUE)
                    self.likelihood.noise = (scale * log_ratio.exp()).clamp_min(_MIN_VALUE).reshape(1)
        except NotPositiveDefiniteError as exc:
            raise FittingError(f"fitting failed: {exc}") from exc
        finally:
            if bar is not None:
                bar.close()
        self.n_iter_ = state["evals"]  # evaluations of this pass (on all the data for the final pass)
        for p in params:
            if not bool(torch.isfinite(p).all()):
                raise FittingError(
                    "fitting diverged: a hyperparameter became non-finite; fix some of them "
                    "(lengthscale=..., outputscale=..., noise_variance=...) or rescale the data"
                )

    def _refresh_cache(self) -> None:
        """Factorize once and cache the posterior solve; builds the GPyTorch ExactGP view of the model."""
        X, Y = self.train_inputs_, self.train_targets_
        with torch.no_grad():
            mll, L, alpha = self._exact_mll(X, Y)
        self._chol, self._alpha = L, alpha
        self.log_marginal_likelihood_ = float(mll)
        self.model = _IndependentOutputsGP(X, Y.T.contiguous(), self.likelihood, self.covar_module, Y.shape[1])
        self.model.eval()

    # ---------------------------------------------------------------------------------------------- prediction
    @property
    def is_fitted(self) -> bool:
        return self._alpha is not None

    def _require_fitted(self) -> None:
        if not self.is_fitted:
            raise NotFittedError("this CorrectionGP is not fitted yet; call .fit(inputs, targets) first")

    @property
    def input_dim(self) -> int | None:
        return None if self.train_inputs_ is None else self.train_inputs_.shape[1]

    @property
    def output_dim(self) -> int | None:
        return None if self.train_targets_ is None else self.train_targets_.shape[1]

    def covariance(self, x1, x2=None) -> torch.Tensor:
        """Prior covariance k(x1, x2) of F from the model's GPyTorch kernel (outputscale included).

        Returns a dense ``(M1, M2)`` tensor (``(d_out, M1, M2)`` when ``per_output``). Works before fitting when
        the model has been built (shared kernel), with the hyperparameters given or initialised.
        """
        if self.covar_module is None:
            raise NotFittedError("per-output kernels are built by fit(); call .fit(inputs, targets) first")
        x1 = self._check_inputs(x1, "x1")
        x2 = x1 if x2 is None else self._check_inputs(x2, "x2")
        with torch.no_grad():
            return self.covar_module.forward(x1, x2)

    def _cross(self, x: torch.Tensor) -> torch.Tensor:
        """k(x, X) as ``(B, M, N)``."""
        K = self.covar_module.forward(x, self.train_inputs_)
        return K.unsqueeze(0) if K.dim() == 2 else K

    def predict_mean(self, x) -> torch.Tensor:
        """Posterior mean of F at ``x (M, d_in)``: ``(M, d_out)``. One kernel block times the cached solve.

        Differentiable with respect to ``x`` (autograd flows through the kernel), never refactorizes.
        """
        self._require_fitted()
        if not (
            isinstance(x, torch.Tensor)
            and x.dtype == self.dtype
            and x.device == self.device
            and x.dim() == 2
            and x.shape[1] == self.train_inputs_.shape[1]
        ):
            x = self._check_inputs(x, "x")  # the fast path above skips only the NaN scan (ODE right-hand sides)
        mean = self._cross(x) @ self._alpha  # (1, M, d_out) or (d_out, M, 1)
        return mean[0] if not self.per_output else mean.squeeze(-1).T

    def predict(self, x) -> GPPosterior:
        """Posterior mean and variance of F itself (no observation noise) at ``x (M, d_in)``, each ``(M, d_out)``."""
        self._require_fitted()
        x = self._check_inputs(x, "x")
        with torch.no_grad():
            Kxs = self._cross(x)  # (B, M, N)
            mean = Kxs @ self._alpha
            mean = mean[0] if not self.per_output else mean.squeeze(-1).T
            v = torch.linalg.solve_triangular(self._chol, Kxs.transpose(-1, -2), upper=False)  # (B, N, M)
            prior = self.covar_module.forward(x, x, diag=True)  # (M,) or (d_out, M)
            var = (prior - v.pow(2).sum(-2).squeeze(0)).clamp_min(0.0)
            var = var.T if self.per_output else var.unsqueeze(-1).expand(-1, mean.shape[-1])
        return GPPosterior(mean=mean, variance=var.contiguous())

    # ------------------------------------------------------------------------------------------ hyperparameters
    def _value(self, name: str, t: torch.Tensor) -> float | torch.Tensor | None:
        """The value in use; before fitting only a fixed (given) value is in use, otherwise ``None``."""
        if not self.is_fitted:
            return self.fixed[name]
        t = t.detach().reshape(-1)
        return float(t[0]) if (not self.per_output or t.numel() == 1) else t.clone()

    @property
    def lengthscale(self) -> float | torch.Tensor | None:
        """The kernel lengthscale in use (``None`` for the polynomial kernel, or when unfitted and not given)."""
        if self.kernel == "polynomial":
            return None
        return self._value("lengthscale", self.covar_module.base_kernel.lengthscale if self.covar_module else None)

    @property
    def outputscale(self) -> float | torch.Tensor | None:
        """The kernel output scale in use (``None`` when unfitted and not given)."""
        return self._value("outputscale", self.covar_module.outputscale if self.covar_module else None)

    @property
    def noise_variance(self) -> float | torch.Tensor | None:
        """The observation-noise variance in use (``None`` when unfitted and not given)."""
        return self._value("noise_variance", self.likelihood.noise if self.likelihood else None)

    def __repr__(self) -> str:
        state = f"fitted on N={self.train_inputs_.shape[0]}" if self.is_fitted else "not fitted"
        return (
            f"CorrectionGP(kernel={self.kernel!r}, lengthscale={self.lengthscale}, outputscale="
            f"{self.outputscale}, noise_variance={self.noise_variance}, per_output={self.per_output}; {state})"
        )

    # ------------------------------------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> Path:
        """Save a fitted model (configuration, hyperparameters, training data) with ``torch.save``."""
        self._require_fitted()
        path = Path(path)
        torch.save(
            {
                "config": {
                    "kernel": self.kernel,
                    "per_output": self.per_output,
                    "degree": self.degree,
                    "max_iter": self.max_iter,
                    "fixed": self.fixed,
                    "dtype": str(self.dtype).split(".")[-1],
                },
                "covar_module": self.covar_module.state_dict(),
                "likelihood": self.likelihood.state_dict(),
                "train_inputs": self.train_inputs_.cpu(),
                "train_targets": self.train_targets_.cpu(),
                "n_iter": self.n_iter_,
            },
            path,
        )
        return path

    @classmethod
    def load(cls, path: str | Path, *, device: torch.device | str | None = None) -> CorrectionGP:
        """Load a model written by :meth:`save`; the posterior cache is rebuilt (one factorization)."""
        blob = torch.load(Path(path), map_location="cpu", weights_only=False)
        cfg = blob["config"]
        gp = cls(
            kernel=cfg["kernel"],
            per_output=cfg["per_output"],
            degree=cfg["degree"],
            max_iter=cfg["max_iter"],
            dtype=getattr(torch, cfg["dtype"]),
            device=device,
            **cfg["fixed"],
        )
        X = blob["train_inputs"].to(gp.device, gp.dtype)
        Y = blob["train_targets"].to(gp.device, gp.dtype)
        if gp.per_output:
            gp._build(batch=Y.shape[1])
        gp.covar_module.load_state_dict(blob["covar_module"])
        gp.likelihood.load_state_dict(blob["likelihood"])
        gp.train_inputs_, gp.train_targets_, gp.n_iter_ = X, Y, blob["n_iter"]
        gp._refresh_cache()
        return gp
