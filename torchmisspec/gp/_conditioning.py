"""Copies of a GP: its settings as a template (``gp.clone``), and its hyperparameters conditioned on other samples
(``gp.condition``), nothing re-learned.

The one way to put a model's hyperparameters on new data: the calibration's folds, the design's conditioned
proxies, a Campaign's models between refits and the Laplace draws all go through it. A copy shares nothing with
the original (its kernel and likelihood are deep copies), and records of the original's fit are not carried over.
"""

from __future__ import annotations

import copy

import gpytorch
import torch

from .._errors import InputError, NotFittedError, ShapeError
from ._exact import IndependentOutputsGP
from ._inputs import check_inputs, check_samples
from ._kernels import as_kernel

__all__ = ["clone", "condition"]


def condition(gp, inputs, targets=None, *, noise=None):
    """:meth:`CorrectionGP.condition <torchmisspec.gp.CorrectionGP.condition>`: ``gp``'s hyperparameters conditioned
    on other samples."""
    if not gp.is_fitted:
        unset = [name for name, _ in gp._free_parameters()]
        if unset:
            raise NotFittedError(
                f"condition: expected a fitted GP, or one whose hyperparameters are all given, but {unset} are "
                "neither; fit it first, or pass them to CorrectionGP(...)"
            )
        return gp.clone().fit(inputs, targets, noise=noise)  # nothing to learn: the given values, on these data
    X, Y, noise = check_samples(gp, inputs, targets, noise)  # as fit() checks them
    X = check_inputs(gp, X, "inputs")  # and as wide as the training inputs
    if Y.shape[1] != gp.output_dim:
        raise ShapeError(
            f"targets: expected ({X.shape[0]}, {gp.output_dim}) (one row per input, this GP's outputs), got "
            f"{tuple(Y.shape)}"
        )
    new = copy.copy(gp)
    new.fixed = dict(gp.fixed)
    for name in [k for k in vars(new) if k.endswith("_") and not k.startswith("_")]:
        delattr(new, name)  # records of this model's fit (cross_validation_, samples_, state_noise_, ...)
    new.input_names_ = getattr(gp, "input_names_", None)  # the same inputs: their names stay
    new.library_suffices_ = None  # kernel="auto": no check made on these data (None, as before any fit)
    new._cache = None
    covar = copy.deepcopy(gp.covar_module)
    lik = copy.deepcopy(gp.likelihood)
    if noise is not None or isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
        known = None if noise is None else noise.T.clone(memory_format=torch.contiguous_format)
        lik = new._modules(batch=Y.shape[1], noise=known)[1]
        with torch.no_grad():
            new._floor(lik).noise = gp._floor(gp.likelihood).noise.detach().clone()
    new.model = IndependentOutputsGP(X, Y.T.contiguous(), lik, covar, Y.shape[1]).eval()
    with torch.no_grad():
        new.kernel_spec.prepare(new, X)  # what the kernel builds from the inputs (a feature space's features)
    new.n_iterations_, new.n_evaluations_, new.log_marginal_likelihood_ = 0, 0, None
    new._freeze()
    new.posterior()
    return new


def clone(gp, **overrides):
    """:meth:`CorrectionGP.clone <torchmisspec.gp.CorrectionGP.clone>`: an unfitted model with ``gp``'s settings."""
    auto = gp.auto
    args = {
        "kernel": "auto" if auto else gp.requested_kernel,  # an RBF stays one (fitted in a feature space if large)
        "lengthscale": None if auto else gp.fixed["lengthscale"],
        "outputscale": None if auto else gp.fixed["outputscale"],
        "noise_variance": gp.fixed["noise_variance"],
        "per_output": gp._auto_per_output if auto else gp.per_output,
        "degree": gp.degree,
        "max_iter": gp.max_iter,
        "dtype": gp.dtype,
        "device": gp.device,
        "library": gp.library,
        "library_names": gp.library_names,
        "min_gain": gp.min_gain,
        "evidence_margin": gp.evidence_margin,
        "exact": gp.exact,
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
            "outputscale": new_auto or (spec.terms != gp.kernel_spec.terms),
            "library": not (new_auto or spec.terms),
            "library_names": not (new_auto or spec.terms),
            "min_gain": not (new_auto or spec.terms),
            "evidence_margin": not new_auto,
            "exact": new_auto or spec.name not in ("rbf", "rbf-features"),
        }
        args.update({name: None for name, drop in dropped.items() if drop})
    args.update(overrides)
    return type(gp)(**args)
