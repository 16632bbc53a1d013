"""The correction model: :class:`CorrectionGP`, a Gaussian process for F trained by exact marginal likelihood.

* :mod:`torchmisspec.gp._mll` - the exact log marginal likelihood and its analytic gradient (pure functions);
* :mod:`torchmisspec.gp._kernels` - the kernels as objects (:class:`Kernel`, :class:`RBF`, ...; :func:`register`
  a kernel of your own);
* :mod:`torchmisspec.gp._model` - :class:`CorrectionGP` and :class:`GPPosterior`;
* :mod:`torchmisspec.gp._persistence` - save / load without pickled code.
"""

from __future__ import annotations

from ._kernels import RBF, Features, FeaturesRBF, Kernel, Matern52, Polynomial, Stationary, register
from ._model import KERNELS, CorrectionGP, GPPosterior

__all__ = [
    "CorrectionGP",
    "GPPosterior",
    "KERNELS",
    "Kernel",
    "Stationary",
    "RBF",
    "Matern52",
    "Polynomial",
    "Features",
    "FeaturesRBF",
    "register",
]
