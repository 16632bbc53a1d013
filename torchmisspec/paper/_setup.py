"""The paper's experimental settings (inputs of the experiments, not results), shared by the studies, figures and
demo of :mod:`torchmisspec.paper`."""

from __future__ import annotations

import torch

__all__ = [
    "NOISE_STD",
    "LINEAR_PRIOR",
    "GRAVITY_PRIOR",
    "DATA_DRIVEN_OUTPUTSCALE",
    "LINEAR_GRID_SIZE",
    "GRAVITY_CANDIDATES",
    "linear_times",
    "gravity_times",
]

NOISE_STD = 1e-2  #: observation noise std of the samples of F (sigma_eps^2 = 1e-4)
LINEAR_PRIOR = {"lengthscale": 1.0, "outputscale": 4e-5, "noise_variance": NOISE_STD**2}  #: §5.1-5.2 RBF prior
GRAVITY_PRIOR = {"lengthscale": 1.0, "outputscale": 1e-3, "noise_variance": NOISE_STD**2}  #: §5.3 RBF prior
DATA_DRIVEN_OUTPUTSCALE = 1e-2  #: §5.2, the fully data-driven GP's "scaled power"
LINEAR_GRID_SIZE = 13  #: §5.2 candidates: a 13 x 13 grid on D
GRAVITY_CANDIDATES = 300  #: §5.3 number of candidates
_LINEAR_TIMES = (6.0, 11)  # t_final, T
_GRAVITY_TIMES = (3.0, 20)


def linear_times(num: int = _LINEAR_TIMES[1]) -> torch.Tensor:
    """§5.1-5.2 observation times: ``(num,)`` equally spaced on [0, 6] (the paper observes T = 11)."""
    return torch.linspace(0.0, _LINEAR_TIMES[0], num, dtype=torch.float64)


def gravity_times(num: int = _GRAVITY_TIMES[1]) -> torch.Tensor:
    """§5.3 observation times: ``(num,)`` equally spaced on [0, 3] (the paper observes T = 20)."""
    return torch.linspace(0.0, _GRAVITY_TIMES[0], num, dtype=torch.float64)
