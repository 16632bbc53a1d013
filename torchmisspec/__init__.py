"""torchmisspec: correct misspecified ODE models with Gaussian processes, and design the experiments.

A scientist has dy/dt = G(y) that is almost right. The package learns the missing term F(y) as a GP from
observed trajectories, predicts new trajectories with dy/dt = G(y) + E[F(y) | data], and chooses the initial
conditions of the next experiments to maximise the information gained about F (paper: Shulkind, Horesh, Avron,
"Experimental Design for Non-Parametric Correction of Misspecified Dynamical Models").

Typical use::

    import torchmisspec as tms
    system = tms.systems.paper_linear()
    trajs = tms.simulate(system, y0, times)
    samples = tms.correction_samples(trajs, system, derivative="oracle", noise_std=1e-2)
    gp = tms.CorrectionGP().fit(samples.inputs, samples.targets)
    pred = tms.CorrectedODE(system, gp).predict(y0_new, times)
"""

from . import design, metrics, studies, systems
from ._errors import (
    BudgetError,
    FittingError,
    InputError,
    IntegrationError,
    NotFittedError,
    NotPositiveDefiniteError,
    ShapeError,
    TorchMisspecError,
)
from .data import Trajectories, simulate
from .dynamics import CorrectedODE
from .gp import CorrectionGP, GPPosterior
from .metrics import correction_error, integrated_error, integrated_norm, trajectory_rmse
from .observations import CorrectionSamples, correction_samples, finite_difference, smoothed_derivative
from .systems import MisspecifiedSystem

__version__ = "0.1.0"

__all__ = [
    "BudgetError",
    "CorrectedODE",
    "CorrectionGP",
    "CorrectionSamples",
    "FittingError",
    "GPPosterior",
    "InputError",
    "IntegrationError",
    "MisspecifiedSystem",
    "NotFittedError",
    "NotPositiveDefiniteError",
    "ShapeError",
    "TorchMisspecError",
    "Trajectories",
    "correction_error",
    "correction_samples",
    "design",
    "finite_difference",
    "integrated_error",
    "integrated_norm",
    "metrics",
    "simulate",
    "smoothed_derivative",
    "studies",
    "systems",
    "trajectory_rmse",
]
