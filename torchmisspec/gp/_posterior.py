"""The posterior of F given a GP's training data: :class:`Posterior` (``gp.posterior()``) and :class:`GPPosterior`.

One factorization of the training covariance C = K + diag(noise) and the solve alpha = C^-1 Y serve every use of
the posterior: the mean k(x, X) alpha (an ODE right-hand side calls it at every step), the variance and covariance
(the bands, the design's information), function draws (:meth:`Posterior.sample_functions`, pathwise conditioning),
and the posterior given other targets at the same inputs (:meth:`Posterior.with_targets`, which the trajectory fit
differentiates through). As BoTorch's ``GPyTorchPosterior`` or tinygp's ``condition()`` result, it is an object the
rest of the package uses instead of the model's internals.

``gp.posterior()`` caches it: the cache is keyed by the values of every parameter and buffer of ``gp.model`` and by
the identity and version of its training tensors, so a change of hyperparameters or data through any public path is
detected at the next call, which factorizes once. ``gp.posterior(differentiable=True)`` builds an uncached one whose
solve keeps the autograd graph to the hyperparameters.

The factor is dense (:class:`~torchmisspec.gp._mll.Factorization`, ``(B, N, N)``: B = 1 when every output shares
C, else one per output) or, for the feature kernels fitted in feature space, a
:class:`~torchmisspec.gp._features.FeatureFactorization` (C never formed).
"""

from __future__ import annotations

from dataclasses import dataclass

import gpytorch
import torch

from .._errors import InputError, ShapeError, warn
from .._validation import as_tensor, check_positive_int
from . import _mll
from ._features import FeatureFactorization, check_dense
from ._inputs import check_inputs
from ._paths import detached, kernel_hyperparameters, kernel_matrix

__all__ = ["GPPosterior", "Posterior", "MEAN_BLOCK", "SUPPORT_TOLERANCE"]

MEAN_BLOCK = 2**19  # kernel entries per row block of the posterior mean (4 MiB in float64)
#: Certified bound on the error of the posterior / prior variance ratio in the extrapolation check
#: (:meth:`Posterior.sd_ratio`): 1e-3, far below the threshold's scale (a ratio of 1/2).
SUPPORT_TOLERANCE = 1e-3


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


def check_prediction(value: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Refuse a non-finite prediction at finite inputs (the kernel overflowed: inputs far too large)."""
    if not bool(torch.isfinite(value).all()):
        raise InputError(
            f"x: the prediction is not finite at inputs of size up to {float(x.abs().max()):.3g} (the kernel "
            "overflows there); rescale the inputs so that they are of the size of the training inputs"
        )
    return value


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.device == b.device and torch.equal(a, b)


def state_of(gp) -> tuple[tuple, list[torch.Tensor]]:
    """What the posterior depends on: identities/versions of modules and data, and every parameter's value."""
    m = gp.model
    X, Yt = m.train_inputs[0], m.train_targets
    key = (id(m.covar_module), id(m.likelihood), id(X), X._version, id(Yt), Yt._version)
    values = [t.detach() for t in (*m.parameters(), *m.buffers())]
    if isinstance(m.likelihood, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
        known = m.likelihood.noise_covar.noise  # a plain attribute in GPyTorch (not a buffer): keyed here
        key += (id(known), known._version)
        values.append(known.detach())
    return key, values


def _unbatch(mean: torch.Tensor) -> torch.Tensor:
    """``(1, M, d_out)`` (one covariance) or ``(d_out, M, 1)`` (one per output) -> ``(M, d_out)``."""
    return mean[0] if mean.shape[0] == 1 else mean.squeeze(-1).T


class Posterior:
    """The posterior of F given the GP's training data (``gp.posterior()``): the factor of the training covariance,
    the solve, and everything computed from them.

    Attributes:
        factor: the factorization of C = K + diag(noise) (``chol`` ``(B, N, N)``, ``alpha`` ``(B, N, m)``,
            ``logdet``, ``quad``; B = 1 when the outputs share C).
        log_marginal_likelihood: the exact log marginal likelihood (nats, summed over outputs) of the training data.
    """

    def __init__(self, gp, factor, *, state: tuple | None = None) -> None:
        self._gp = gp
        self.factor = factor
        self.log_marginal_likelihood = float(_mll.exact_mll(factor, gp.train_inputs_.shape[0]).detach())
        self._state = state
        #: the extrapolation check's truncated eigenbasis (:meth:`sd_ratio`), built on first use (a 1-tuple, since
        #: the basis itself may be None: the exact solve)
        self._basis: tuple[torch.Tensor | None] | None = None
        self._own_mean = None  # mean's function of x (means_function of this posterior alone), built on first use

    # ---------------------------------------------------------------------------------------------- building
    @classmethod
    def build(cls, gp, *, differentiable: bool = False) -> Posterior:
        """Factorize ``gp``'s training covariance once; with ``differentiable`` the solve keeps the graph to the
        hyperparameters (and is not checked for accuracy: a prediction's sensitivity, not its value)."""
        X, Y, noise = gp.train_inputs_, gp.train_targets_, gp.train_noise_
        if noise is not None and noise.shape != Y.shape:
            raise ShapeError(
                f"known noise: expected {tuple(Y.shape)} (the training targets' shape) as gp.train_noise_, got "
                f"{tuple(noise.shape)}; refit with gp.fit(inputs, targets, noise=...)"
            )
        if gp.per_output and gp.covar_module.batch_shape != torch.Size([Y.shape[1]]):
            raise ShapeError(
                f"training targets: expected {gp.covar_module.batch_shape[0]} outputs for the per-output kernels, "
                f"got {Y.shape[1]}; refit with gp.fit(inputs, targets)"
            )
        gp.model.num_outputs = Y.shape[1]
        Yb = gp._targets_batched(Y, noise)
        if differentiable:
            check_dense(X.shape[0])
            K, diag = gp._kernel_parts(X, noise)
            return cls(gp, _mll.factorize(K, diag, Yb))
        key, values = state_of(gp)
        with torch.no_grad():
            if gp.kernel_spec.feature_space:  # in feature space: O(N p^2), the N x N matrix is never formed
                base = gp.covar_module.base_kernel
                Phi = base.features(X)
                W = base.weights.detach().reshape(-1, Phi.shape[1]) * gp.covar_module.outputscale.reshape(-1, 1)
                diag = gp._noise_diag(noise)
                fac = FeatureFactorization(Phi, W, diag, Yb)
                # the mean comes from the coefficients' solve: the error it leaves at the training inputs
                resid = torch.tensor([fac.mean_error(Yb)], dtype=Yb.dtype)
            else:
                K, diag = gp._kernel_parts(X, noise)
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
        return cls(gp, fac, state=(key, [v.clone() for v in values]))

    def is_current(self, gp) -> bool:
        """Whether this posterior is still ``gp``'s: nothing it depends on changed since it was built."""
        if self._state is None or gp is not self._gp:
            return False
        key, values = state_of(gp)
        old_key, old_values = self._state
        return (
            old_key == key
            and len(old_values) == len(values)
            and all(_same(a, b) for a, b in zip(old_values, values, strict=True))
        )

    def with_targets(self, targets: torch.Tensor) -> Posterior:
        """The posterior given other targets ``(N, d_out)`` at the same training inputs, with the same factor: one
        triangular solve, differentiable in ``targets`` (the trajectory fit optimises pseudo-targets through it). Its
        factor is dense (a feature-space factor builds the dense one on first use)."""
        gp, fac = self._gp, self.factor
        targets = as_tensor(targets, "targets", dtype=gp.dtype, device=gp.device)
        if targets.shape != gp.train_targets_.shape:
            raise ShapeError(
                f"targets: expected {tuple(gp.train_targets_.shape)} targets (one row per training input), got shape "
                f"{tuple(targets.shape)}"
            )
        Yb = gp._targets_batched(targets, gp.train_noise_)
        alpha = torch.cholesky_solve(Yb, fac.chol)
        return Posterior(gp, _mll.Factorization(fac.chol, alpha, fac.logdet, (Yb * alpha).sum()))

    # ------------------------------------------------------------------------------------------------ the mean
    @property
    def weights(self) -> torch.Tensor:
        """``(N, d_out)``: the representer weights alpha = C^-1 Y, one column per output (mean = k(x, X) alpha)."""
        return _unbatch(self.factor.alpha)

    def _cross(self, x: torch.Tensor) -> torch.Tensor:
        """k(X, x) as ``(B, N, M)``, training inputs first: GPyTorch's distances centre both inputs on the mean of
        the first, so with the queries first one far-away row would shift every other row's distances (a prediction
        would depend on what else is in the batch); centred on the fixed training inputs, each query is its own."""
        K = self._gp.covar_module.forward(self._gp.train_inputs_, x)
        return K.unsqueeze(0) if K.dim() == 2 else K

    def means_of(self, others: list[Posterior], x: torch.Tensor) -> torch.Tensor:
        """``(M, d_out, len(others))``: the means at ``x (M, d_in)`` (checked by the caller, as ``mean(x,
        check=False)``) of posteriors that share this one's kernel and training inputs (:meth:`with_targets`), one
        kernel block for all (:meth:`means_function`)."""
        return self.means_function(others)(x)

    def means_function(self, others: list[Posterior]):
        """``x -> (M, d_out, P)``: :meth:`means_of` the ``P`` posteriors ``others`` with their weights stacked once,
        one kernel block and one product for all. Why: the fit of G's parameters through the ODE evaluates F's mean
        and one such mean per parameter at every step of its solves; on nlme's Remifentanil (16 parameters) the
        kernel and the products were most of the population fit's time."""
        P = len(others)
        with torch.enable_grad():  # built once, maybe under no_grad (a solver's first check): keep the graph to alpha
            stacked = torch.cat([o.factor.alpha for o in others], -1).transpose(-1, -2)  # (B, P m, N)
        B, m = stacked.shape[0], stacked.shape[1] // P
        rows = max(64, MEAN_BLOCK // max(self.factor.alpha.shape[-2], 1))

        def block(x: torch.Tensor) -> torch.Tensor:
            R = (stacked @ self._cross(x)).reshape(B, P, m, -1)  # (B, P, m, M)
            return R[0].permute(2, 1, 0) if B == 1 else R[:, :, 0].permute(2, 0, 1)

        def means(x: torch.Tensor) -> torch.Tensor:
            if x.shape[0] <= rows:
                return block(x)
            return torch.cat([block(x[i : i + rows]) for i in range(0, x.shape[0], rows)])

        return means

    def mean(self, x, *, check: bool = True) -> torch.Tensor:
        """Posterior mean of F at ``x (M, d_in)``: ``(M, d_out)``. One kernel block times the solve.

        Differentiable with respect to ``x`` when ``x`` requires grad (the solve is a constant unless this posterior
        was built ``differentiable``). ``check=False`` skips the input and output checks, for inputs already
        ``(M, d_in)`` in the GP's dtype and device (an ODE right-hand side calls this at every step). Row blocks of
        about ``MEAN_BLOCK`` kernel entries keep the kernel's elementwise passes in cache.
        """
        if check:
            x = check_inputs(self._gp, x, "x")
            with torch.set_grad_enabled(x.requires_grad and torch.is_grad_enabled()):
                return check_prediction(self.mean(x, check=False), x)
        if isinstance(self.factor, FeatureFactorization):  # phi(x)^T (posterior mean of the coefficients)
            return _unbatch(self._gp.covar_module.base_kernel.features(x) @ self.factor.mean)
        if self._own_mean is None:  # the one-posterior case of means_function, its weights stacked once
            self._own_mean = self.means_function([self])
        return self._own_mean(x)[..., 0]

    # ---------------------------------------------------------------------------------------- the uncertainty
    def _term_spread(self, x: torch.Tensor) -> torch.Tensor | None:
        """``(B, p)`` squared features times the variance the feature kernel's removed terms add (their chance of
        being present, :attr:`~torchmisspec.gp._features.FeatureKernel.spread`), as ``(features, spread)``; None
        for other kernels."""
        base = self._gp.covar_module.base_kernel
        if getattr(base, "spread", None) is None:
            return None
        phi = base.features(x)  # (M, p)
        return phi, base.spread.reshape(-1, phi.shape[-1]).to(phi)  # (M, p), (B, p)

    def predict(self, x) -> GPPosterior:
        """Posterior mean and variance of F itself (no observation noise) at ``x (M, d_in)``, each ``(M, d_out)``."""
        gp, fac = self._gp, self.factor
        x = check_inputs(gp, x, "x")
        with torch.no_grad():
            if isinstance(fac, FeatureFactorization):  # phi(x)^T cov phi(x): no N x N factor
                phi = gp.covar_module.base_kernel.features(x)  # (M, p)
                mean = _unbatch(phi @ fac.mean)
                var = ((phi @ fac.cov) * phi).sum(-1).clamp_min(0.0)  # (B, M)
            else:
                Kt = self._cross(x)  # k(X, x): (1, N, M) shared kernel, (d_out, N, M) per output
                mean = _unbatch((fac.alpha.transpose(-1, -2) @ Kt).transpose(-1, -2))
                Kt = Kt.expand(fac.chol.shape[0], -1, -1)
                v = torch.linalg.solve_triangular(fac.chol, Kt, upper=False)
                prior = gp.covar_module.forward(x, x, diag=True)  # (M,) or (d_out, M)
                var = (prior - v.pow(2).sum(-2)).clamp_min(0.0)  # (1 or d_out, M)
            spread = self._term_spread(x)
            if spread is not None:  # + the removed terms' chance of being present
                var = var + (spread[0].pow(2) @ spread[1].T).T
            var = var.T.expand(-1, mean.shape[-1])
        check_prediction(mean, x)
        check_prediction(var, x)
        return GPPosterior(mean=mean, variance=var.contiguous())

    def covariance(self, x1, x2=None) -> torch.Tensor:
        """Posterior covariance of F (no observation noise) between ``x1 (M1, d_in)`` and ``x2 (M2, d_in)``:
        ``(B, M1, M2)``, B = 1 when every output has the same covariance, else one per output. Its diagonal is
        :meth:`predict`'s variance."""
        gp, fac = self._gp, self.factor
        x1 = check_inputs(gp, x1, "x1")
        x2 = x1 if x2 is None else check_inputs(gp, x2, "x2")
        with torch.no_grad():
            if isinstance(fac, FeatureFactorization):
                base = gp.covar_module.base_kernel
                p1, p2 = base.features(x1), base.features(x2)
                cov = (p1 @ fac.cov) @ p2.T  # (B, M1, M2)
            else:
                prior = gp.covar_module.forward(x1, x2)
                prior = prior.unsqueeze(0) if prior.dim() == 2 else prior
                B = fac.chol.shape[0]
                V1 = torch.linalg.solve_triangular(fac.chol, self._cross(x1).expand(B, -1, -1), upper=False)
                V2 = (
                    V1
                    if x2 is x1
                    else torch.linalg.solve_triangular(fac.chol, self._cross(x2).expand(B, -1, -1), upper=False)
                )
                cov = prior - V1.transpose(-1, -2) @ V2
            spread = self._term_spread(x1)
            if spread is not None:
                p2 = spread[0] if x2 is x1 else gp.covar_module.base_kernel.features(x2)
                cov = cov + (spread[0].unsqueeze(0) * spread[1].unsqueeze(1)) @ p2.T
        return cov

    def _eigenbasis(self) -> torch.Tensor | None:
        """``U_r / sqrt(lam_r + s2n)`` ``(B, N, r)`` for :meth:`sd_ratio` (see there), or ``None`` for the exact
        solve (known per-sample noise, or no saving)."""
        gp = self._gp
        if gp.train_noise_ is not None:
            return None
        X = gp.train_inputs_
        K = kernel_matrix(gp.kernel_spec, X, X, detached(kernel_hyperparameters(gp)), gp.degree)  # (B, N, N)
        lam, U = torch.linalg.eigh(K)  # ascending
        lam = lam.clamp_min(0.0)
        s2n = gp._floor(gp.likelihood).noise.detach().reshape(-1, 1)  # (B, 1)
        # the tail sums of the shares lam / (lam + s2n) from the smallest: drop as many as the budget allows
        drop = int((((lam / (lam + s2n)).cumsum(-1)) <= SUPPORT_TOLERANCE).sum(-1).min())
        if X.shape[0] - drop > X.shape[0] // 2:  # not worth it: more than half the rank
            return None
        return U[..., drop:] / (lam[..., drop:] + s2n).sqrt().unsqueeze(-2)

    def sd_ratio(self, x: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
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
        gp, fac = self._gp, self.factor
        X = gp.train_inputs_
        x = as_tensor(x, "x", dtype=gp.dtype, device=gp.device)  # paths that left the box may hold inf: no finiteness
        if x.dim() != 2 or x.shape[1] != gp.input_dim:
            raise ShapeError(f"x: expected (M, {gp.input_dim}) inputs, got shape {tuple(x.shape)}")
        chunk = check_positive_int(chunk, "chunk")
        if x.shape[0] == 0:
            return x.new_zeros(0)
        with torch.no_grad():
            prior = gp.covar_module.forward(x, x, diag=True).reshape(-1, x.shape[0])  # (1 or d_out, M)
            if isinstance(fac, FeatureFactorization):  # exact, in feature space
                phi = gp.covar_module.base_kernel.features(x)
                post = ((phi @ fac.cov) * phi).sum(-1).clamp_min(0.0)
                ratio = (post / prior.clamp_min(torch.finfo(prior.dtype).tiny)).clamp(0.0, 1.0).sqrt()
                return ratio.amax(0)
            params = detached(kernel_hyperparameters(gp))
            if self._basis is None:  # once per factorization, not at every extrapolation check
                self._basis = (self._eigenbasis(),)
            (basis,) = self._basis
            explained = []
            for start in range(0, x.shape[0], chunk):
                K = kernel_matrix(gp.kernel_spec, x[start : start + chunk], X, params, gp.degree)  # (B, m, N)
                if basis is not None:
                    V = K @ basis  # (B, m, r): (u_i^T k_x) / sqrt(lam_i + s2n)
                else:
                    K = K.expand(fac.chol.shape[0], -1, -1)
                    V = torch.linalg.solve_triangular(fac.chol.transpose(-1, -2), K, upper=True, left=False)  # K L^-T
                explained.append(V.pow(2).sum(-1))
            post = (prior - torch.cat(explained, -1)).clamp_min(0.0)
            ratio = (post / prior.clamp_min(torch.finfo(prior.dtype).tiny)).clamp(0.0, 1.0).sqrt()
        return ratio.amax(0)

    # --------------------------------------------------------------------------------------------- draws of F
    def sample_functions(self, num_samples: int, **options):
        """``num_samples`` posterior draws of F as whole functions: :meth:`CorrectionGP.sample_functions`."""
        return self._gp.sample_functions(num_samples, **options)

    def training_covariance_times(self, V: torch.Tensor) -> torch.Tensor:
        """``C V`` for ``V (B, N, k)``, C = K + diag(noise) at the training inputs (B as for
        :meth:`training_covariance`): in feature space without forming C, else with the dense C."""
        if isinstance(self.factor, FeatureFactorization):
            return self.factor.times(V)
        return self.training_covariance() @ V

    def training_covariance(self) -> torch.Tensor:
        """C = K + diag(noise) at the training inputs: ``(B, N, N)`` (B = 1 when the outputs share it)."""
        gp = self._gp
        check_dense(gp.train_inputs_.shape[0])
        K, diag = gp._kernel_parts(gp.train_inputs_, gp.train_noise_)
        return K + torch.diag_embed(diag.expand(K.shape[0], K.shape[-1]))

    def __repr__(self) -> str:
        N, d_out = self._gp.train_targets_.shape
        kind = "feature-space" if isinstance(self.factor, FeatureFactorization) else "dense"
        mll = f"{self.log_marginal_likelihood:.6g}"
        return f"Posterior(N={N}, d_out={d_out}, {kind} factor, log_marginal_likelihood={mll})"
