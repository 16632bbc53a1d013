"""How a :class:`~torchmisspec.gp.CorrectionGP` learns its hyperparameters from samples of F.

* :func:`fit_model` builds the GPyTorch model for the data and learns: by the kernel's own fit where it has one
  (the feature kernels: :func:`fit_features`, :func:`fit_sum_kernel`), otherwise by :func:`optimise`, L-BFGS on the
  exact log marginal likelihood of :mod:`torchmisspec.gp._mll` with its analytic gradient (one O(N^3) factorization
  per evaluation), after a cheap warm start on a subsample for large N;
* :func:`optimise` profiles the output scale out when it can (C = s (R + g I): the same optimum in fewer
  iterations) and keeps the lengthscale within a box of the inputs' scale (:func:`lengthscale_box`).

Positive hyperparameters are optimised in log space (as scikit-learn does), which keeps small output scales and
noise variances (1e-5 .. 1e-4 in the paper) well conditioned for L-BFGS.
"""

from __future__ import annotations

import math

import gpytorch
import torch

from .._errors import FittingError, LinearAlgebraError, NumericalWarning, warn
from .._optim import OptimResult, maximise
from . import _mll
from ._exact import IndependentOutputsGP, median_distance
from ._relevance import fit_relevance, term_inclusion, term_price, unit_information_weights
from ._sum import fit_sum

__all__ = ["fit_model", "optimise", "fit_features", "fit_sum_kernel", "lengthscale_box", "initialise"]

#: smallest noise-to-output-scale ratio the profiled fit considers (relative, so the fit is scale-equivariant)
_MIN_RATIO = 1e-12


def _show(module, name: str) -> str:
    """A hyperparameter's current value(s) for an error message."""
    value = getattr(module, name, None)
    if not isinstance(value, torch.Tensor):
        return "n/a"
    flat = value.detach().reshape(-1).tolist()
    return f"{flat[0]:.4g}" if len(flat) == 1 else "[" + ", ".join(f"{v:.4g}" for v in flat) + "]"


def initialise(gp, X: torch.Tensor, Y: torch.Tensor) -> None:
    """Set the learned hyperparameters to :meth:`starting_values` (the fixed ones are already set)."""
    start = gp.starting_values(X, Y)
    with torch.no_grad():
        if gp.kernel_spec.has_lengthscale and gp.fixed["lengthscale"] is None:
            base = gp.covar_module.base_kernel
            base.lengthscale = start["lengthscale"].expand(base.lengthscale.shape)
        if gp.fixed["outputscale"] is None:
            gp.covar_module.outputscale = start["outputscale"].expand(gp.covar_module.outputscale.shape)
        if gp.fixed["noise_variance"] is None:
            noise = start["noise_variance"]
            gp._floor(gp.likelihood).noise = noise.reshape(-1, 1) if gp.per_output else noise.reshape(1)


def fit_model(gp, X, Y, noise, learn: bool, *, progress: bool, max_iter: int, warm_start: int) -> None:
    """Put checked data ``X (N, d_in)``, ``Y (N, d_out)`` and known ``noise`` (or None) into a fresh GPyTorch model of
    ``gp`` and, when ``learn``, learn the free hyperparameters; then freeze them and factorize once."""
    d_out = Y.shape[1]
    covar, lik = gp.covar_module, gp.likelihood
    if gp.kernel_spec.terms and covar.base_kernel.powers.shape[1] != X.shape[1]:  # library: d_in too
        gp._d_in = X.shape[1]  # the library of monomials of these inputs
        covar, lik = gp._modules(batch=d_out)
    if gp.per_output and covar.batch_shape != torch.Size([d_out]):
        covar, lik = gp._modules(batch=d_out)
    if noise is not None or isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
        # the likelihood holds the known noise (or none): a fresh one for these data, fixed values included
        # (a copy: the model never shares storage with the caller's tensor)
        known = None if noise is None else noise.T.clone(memory_format=torch.contiguous_format)
        lik = gp._modules(batch=d_out, noise=known)[1]
    gp.model = IndependentOutputsGP(X, Y.T.contiguous(), lik, covar, d_out).eval()
    gp._cache = None
    own = gp.kernel_spec.fit(gp, X, Y, noise, max_iter=max_iter) if learn else gp.kernel_spec.prepare(gp, X)
    if own is not None:  # the kernel's own fit (the feature kernels')
        gp.n_iterations_, gp.n_evaluations_ = own
    elif learn:
        initialise(gp, X, Y)
        if warm_start and X.shape[0] > 2 * warm_start:
            # a cheap first pass on an evenly spaced subsample puts L-BFGS near the optimum; the second pass
            # on all the data then needs few O(N^3) evaluations (the result maximises the full likelihood)
            sub = torch.linspace(0, X.shape[0] - 1, warm_start, device=X.device).round().long()
            sub_noise = None if noise is None else noise[sub]
            optimise(gp, X[sub], Y[sub], sub_noise, progress=False, max_iter=max_iter)
            if noise is not None and gp.fixed["noise_variance"] is None:
                # beside known noise a subsample often cannot identify the floor, which then collapses towards
                # 0, where its log-space gradient vanishes: the full pass starts it afresh
                start = gp.starting_values(X, Y)["noise_variance"]
                with torch.no_grad():
                    floor = gp._floor(gp.likelihood)
                    floor.noise = start.reshape(-1, 1) if gp.per_output else start.reshape(1)
        result = optimise(gp, X, Y, noise, progress=progress, max_iter=max_iter)
        gp.n_iterations_, gp.n_evaluations_ = result.iterations, result.evaluations
    else:
        gp.n_iterations_, gp.n_evaluations_ = 0, 0
    gp._freeze()
    gp.posterior()


def fit_sum_kernel(gp, X, Y, noise, *, max_iter: int) -> tuple[int, int]:
    """The features+rbf kernel's fit (:func:`~torchmisspec.gp._sum.fit_sum`): ``(iterations, evaluations)``."""
    floor, _, iterations = fit_sum(
        gp.covar_module.base_kernel,
        X,
        Y,
        noise,
        floor=gp.fixed["noise_variance"],
        lengthscale=gp.fixed["lengthscale"],
        max_iter=max_iter,
        outputscale=float(gp.fixed["outputscale"]),
        min_gain=term_price(gp.min_gain, X.shape[0]),
    )
    if gp.fixed["noise_variance"] is None:
        with torch.no_grad():
            gp._floor(gp.likelihood).noise = torch.tensor([floor], dtype=gp.dtype, device=gp.device)
    return iterations, iterations


def fit_features(gp, X: torch.Tensor, Y: torch.Tensor, noise: torch.Tensor | None, *, max_iter: int) -> int:
    """The feature kernel's weights (and the noise floor unless fixed) by sparse Bayesian learning in feature
    space (:func:`~torchmisspec.gp._relevance.fit_relevance`): one set of weights shared by the outputs, or one
    per output with ``per_output``. Returns the number of fixed-point iterations (the most over the outputs)."""
    covar, lik = gp.covar_module, gp.likelihood
    base = covar.base_kernel
    scale = float(gp.fixed["outputscale"])
    Phi = base.features(X) * math.sqrt(scale)  # the output scale folded into the features
    floor = gp.fixed["noise_variance"]
    groups = [[o] for o in range(Y.shape[1])] if gp.per_output else [list(range(Y.shape[1]))]
    # the price of a term: per learned weight (shared by the outputs of a group or not), as evidence_score counts
    price = term_price(gp.min_gain, X.shape[0])
    weights, floors, inclusion, spread, iterations = [], [], [], [], 0
    for cols in groups:
        known = None if noise is None else noise[:, cols]
        try:
            w, s, it = fit_relevance(Phi, Y[:, cols], known, floor=floor, max_iter=10 * max_iter, min_gain=price)
        except FittingError as exc:
            if not gp.per_output:
                raise
            raise FittingError(f"output {cols[0]}: {exc}") from exc
        if it >= 10 * max_iter:
            warn(
                f"the feature weights{f' of output {cols[0]}' if gp.per_output else ''} did not converge in "
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
            value = torch.tensor(floors, dtype=gp.dtype, device=gp.device)
            gp._floor(lik).noise = value.reshape(-1, 1) if gp.per_output else value.reshape(1)
    return iterations


def lengthscale_box(gp, X: torch.Tensor):
    """``(raw lengthscale, lo, hi)``: the learned lengthscale is kept within [1e-4, 1e4] times the median distance
    between the inputs (log space), or ``None`` when it is not learned. Without the box a line-search trial can
    take log l to -1000, where every kernel entry is 0/0."""
    if not gp.kernel_spec.has_lengthscale or gp.fixed["lengthscale"] is not None:
        return None
    scale = median_distance(gp.kernel_spec.scaled_inputs(X))
    return gp.covar_module.base_kernel.raw_lengthscale, math.log(1e-4 * scale), math.log(1e4 * scale)


def optimise(gp, X: torch.Tensor, Y: torch.Tensor, noise: torch.Tensor | None, *, progress: bool, max_iter: int):
    """L-BFGS on the exact log marginal likelihood with the analytic gradient of :mod:`._mll`.

    When the output scale and the noise are both learned with a shared kernel and there is no known noise, the
    output scale s is profiled out: C = s (R + g I), leaving the lengthscale and the noise ratio g for L-BFGS
    (the same optimum of the same likelihood, in fewer iterations); s* and g s* are written back into the
    GPyTorch modules. Known noise does not scale with s, so then every free hyperparameter is optimised directly.
    """
    n, d_out = Y.shape
    free = [p for _, p in gp._free_parameters()]
    profile = (
        not gp.per_output and noise is None and gp.fixed["outputscale"] is None and gp.fixed["noise_variance"] is None
    )
    Yb = gp._targets_batched(Y, noise)
    covar, lik = gp.covar_module, gp.likelihood
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
            return gp._kernel_parts(X, noise)

    box = lengthscale_box(gp, X)
    last: list[torch.Tensor] = []  # the hyperparameters of the last trial that could be factorized
    count = [0]

    def evaluate():
        if box is not None:  # a line-search trial far out in log space (l -> 0 makes K all NaN): project back
            with torch.no_grad():
                box[0].clamp_(box[1], box[2])
        K, diag = matrices()
        with torch.no_grad():
            fac = _mll.factorize(K.detach(), diag.detach(), Yb, warn=False)
            last[:] = [p.detach().clone() for p in params]
            count[0] += 1
            if profile:
                value, scale = _mll.profiled_mll(fac)
                Q = _mll.gradient_weights(fac, scale)
            else:
                value = _mll.exact_mll(fac, n)
                Q = _mll.gradient_weights(fac)
        return value, _mll.gradient_surrogate(Q, K, diag)

    try:
        try:
            result = maximise(
                params,
                evaluate,
                max_iter=max_iter,
                normaliser=float(n * d_out),
                progress=progress,
                desc=f"fit GP (N={n})",
            )
        except LinearAlgebraError:
            if not last:  # the start itself cannot be factorized
                raise
            with torch.no_grad():  # a line-search trial overflowed (K or its noise not finite): stop at the last one
                for p, value in zip(params, last, strict=True):  # that could be factorized, as a failed line search
                    p.copy_(value)
            result = OptimResult(-1, count[0], math.nan)  # iterations unknown
        if profile:  # write the profiled output scale and the noise back into the GPyTorch modules
            with torch.no_grad():
                K, diag = matrices()
                _, scale = _mll.profiled_mll(_mll.factorize(K, diag, Yb, warn=False))
                covar.outputscale = scale
                lik.noise = (scale * (log_ratio.exp() + _MIN_RATIO)).reshape(1)
    except LinearAlgebraError as exc:
        raise FittingError(
            f"fitting failed at lengthscale={_show(gp.covar_module.base_kernel, 'lengthscale')}, "
            f"outputscale={_show(covar, 'outputscale')}, noise_variance={_show(gp._floor(lik), 'noise')}: {exc}"
        ) from exc
    for p in params:
        if not bool(torch.isfinite(p).all()):
            raise FittingError(
                "fitting diverged: a hyperparameter became non-finite; fix some of them "
                "(lengthscale=..., outputscale=..., noise_variance=...) or rescale the data"
            )
    return result
