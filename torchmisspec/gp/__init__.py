"""The correction model: :class:`CorrectionGP`, a Gaussian process for F trained by exact marginal likelihood.

* :mod:`torchmisspec.gp._mll` - the exact log marginal likelihood and its analytic gradient (pure functions);
* :mod:`torchmisspec.gp._model` - :class:`CorrectionGP` and :class:`GPPosterior`;
* :mod:`torchmisspec.gp._persistence` - save / load without pickled code.
"""

from __future__ import annotations

import warnings

import torch

from ._model import KERNELS, CorrectionGP, GPPosterior

__all__ = ["CorrectionGP", "GPPosterior", "KERNELS", "cholesky_with_jitter"]


def cholesky_with_jitter(K: torch.Tensor, *, max_tries: int = 6, what: str = "covariance") -> torch.Tensor:
    """Deprecated: use :func:`torchmisspec._linalg.cholesky` (it warns when it adds jitter)."""
    from .._linalg import cholesky

    warnings.warn(
        "torchmisspec.gp.cholesky_with_jitter is deprecated; the package's factorizations go through "
        "torchmisspec._linalg.cholesky, which warns (NumericalWarning) when it adds jitter",
        DeprecationWarning,
        stacklevel=2,
    )
    return cholesky(K, what=what)
