"""What a fitted :class:`~torchmisspec.gp.CorrectionGP` reports: the hyperparameters in use, how many were learned
and the evidence score ``kernel="auto"`` compares, their Laplace posterior, and the feature kernels' terms.

A base class of :class:`~torchmisspec.gp.CorrectionGP` (it reads the model's GPyTorch modules and training data).
"""

from __future__ import annotations

import math

import torch

from .._errors import InputError
from . import _laplace, _terms
from ._features import Term

__all__ = ["Readout"]


class Readout:
    """The read-out of a fitted model (see the module docstring); mixed into :class:`CorrectionGP`."""

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

    @property
    def approximation(self) -> dict | None:
        """How far the kernel in use is from the one it stands for, or ``None`` for an exact kernel: for
        ``kernel="rbf-features"`` (:mod:`torchmisspec.gp._large`) the kind of features (``"quadrature"``: a
        certified uniform bound over ``box``; ``"random"``: a root-mean-square bound), their number, the bound on
        ``|k_hat - k|`` relative to the output scale, the box, and the settings (``feature_error``, ``subsample``)."""
        self._require_fitted()
        describe = getattr(self.covar_module.base_kernel, "describe", None)
        return None if describe is None else {**describe(), **self.kernel_spec.config()}

    # ------------------------------------------------------------------------------------------ hyperparameters
    def laplace_covariance(self) -> tuple[list[str], torch.Tensor, torch.Tensor]:
        """A Laplace approximation of the posterior of the learned log hyperparameters: ``(names, mean, covariance)``
        (:func:`torchmisspec.gp._laplace.laplace_covariance`)."""
        return _laplace.laplace_covariance(self)

    def hyperparameter_samples(self, num_samples: int, *, generator: torch.Generator | None = None) -> list:
        """``num_samples`` copies of this GP conditioned on the same data, with hyperparameters drawn from their
        Laplace posterior (:func:`torchmisspec.gp._laplace.hyperparameter_samples`)."""
        return _laplace.hyperparameter_samples(self, num_samples, generator=generator)

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
        """The learned terms of a feature kernel, with their coefficients' posterior means and standard deviations
        (:func:`torchmisspec.gp._terms.terms`): a :class:`~torchmisspec.gp._features.Term` per output and kept term
        (``all_terms=True``: every term), whose ``str`` reads like ``"+0.01 +- 0.0003 * y1^2"``. ``names``: the
        inputs' names (default :attr:`input_names_`, else x1, x2, ...)."""
        return _terms.terms(self, names, all_terms=all_terms)

    def __repr__(self) -> str:
        state = f"fitted on N={self.train_inputs_.shape[0]}" if self.is_fitted else "not fitted"
        if self.train_noise_ is not None:
            state += " with known noise"
        return (
            f"CorrectionGP(kernel={self.kernel!r}, lengthscale={self.lengthscale}, outputscale={self.outputscale}, "
            f"noise_variance={self.noise_variance}, per_output={self.per_output}; {state})"
        )
