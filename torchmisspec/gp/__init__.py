"""The correction model: :class:`CorrectionGP`, a Gaussian process for F trained by exact marginal likelihood.

One idea per module, each readable in one sitting:

* :mod:`._model` - :class:`CorrectionGP`, the front; :mod:`._settings` - its checked settings; :mod:`._inputs` -
  the checks of what it is given; :mod:`._exact` - the GPyTorch modules and ``ExactGP`` view;
* :mod:`._kernels` - the kernels as objects (:class:`Kernel`, :class:`RBF`, ...; :func:`register` a kernel of your
  own); :mod:`._features` - the feature kernel, its terms and its feature-space posterior; :mod:`._sum` - the
  library plus an RBF; :mod:`._large` - the RBF kernel in a feature space for many samples;
* :mod:`._mll` - the exact log marginal likelihood and its analytic gradient (pure functions); :mod:`._fit` - how
  a model learns (through the package's one L-BFGS loop, :mod:`torchmisspec._optim`); :mod:`._relevance` - the
  feature weights' sparse Bayesian learning; :mod:`._selection` - ``kernel="auto"``'s choice by evidence;
  :mod:`._prior` - hyperparameters before data;
* :mod:`._posterior` - :class:`Posterior` (``gp.posterior()``) and :class:`GPPosterior`; :mod:`._conditioning` -
  copies and conditioning; :mod:`._laplace` - the hyperparameters' Laplace posterior; :mod:`._terms` - the feature
  kernels' read-out; :mod:`._paths` and :mod:`._quadrature` - draws of F as functions; :mod:`._calibration` - the
  bands' calibration record; :mod:`._persistence` - save / load without pickled code.
"""

from __future__ import annotations

from ._exact import log_positive
from ._kernels import RBF, Features, FeaturesRBF, Kernel, Matern52, Polynomial, Stationary, register
from ._large import Matern52Features, RBFFeatures
from ._model import KERNELS, CorrectionGP
from ._posterior import GPPosterior, Posterior

__all__ = [
    "CorrectionGP",
    "GPPosterior",
    "Posterior",
    "KERNELS",
    "Kernel",
    "Stationary",
    "RBF",
    "Matern52",
    "Polynomial",
    "Features",
    "FeaturesRBF",
    "RBFFeatures",
    "Matern52Features",
    "register",
    "log_positive",
]
