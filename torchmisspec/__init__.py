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

from importlib.metadata import PackageNotFoundError as _PackageNotFoundError
from importlib.metadata import version as _version

from . import design, metrics, noise, parallel, parameters, population, signals, systems
from ._errors import (
    BudgetError,
    FittingError,
    InputError,
    IntegrationError,
    LinearAlgebraError,
    NotFittedError,
    NotPositiveDefiniteError,
    NumericalWarning,
    ShapeError,
    TorchMisspecError,
    TorchMisspecWarning,
)
from .data import Readout, Trajectories, simulate
from .gp import CorrectionGP, GPPosterior, Posterior
from .learning.fit import cross_validate
from .learning.pipeline import Pipeline, fit_correction
from .learning.refinement.trajectory_fit import fit_trajectories
from .learning.samples.observations import CorrectionSamples, correction_samples, finite_difference, smoothed_derivative
from .metrics import correction_error, integrated_error, integrated_norm, trajectory_rmse
from .prediction.calibration import BandCalibration, calibrate_bands
from .prediction.dynamics import CorrectedODE, TrajectoryPosterior
from .prediction.solver import Solver
from .signals import Controls
from .systems import MisspecifiedSystem

try:
    __version__ = _version("torchmisspec")
except _PackageNotFoundError:  # pragma: no cover - running from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = [
    "BandCalibration",
    "BudgetError",
    "Controls",
    "LinearAlgebraError",
    "NumericalWarning",
    "TorchMisspecWarning",
    "__version__",
    "CorrectedODE",
    "TrajectoryPosterior",
    "CorrectionGP",
    "CorrectionSamples",
    "FittingError",
    "GPPosterior",
    "Posterior",
    "Readout",
    "InputError",
    "IntegrationError",
    "MisspecifiedSystem",
    "NotFittedError",
    "NotPositiveDefiniteError",
    "ShapeError",
    "Solver",
    "TorchMisspecError",
    "Trajectories",
    "calibrate_bands",
    "correction_error",
    "correction_samples",
    "cross_validate",
    "design",
    "finite_difference",
    "fit_correction",
    "Pipeline",
    "fit_trajectories",
    "integrated_error",
    "integrated_norm",
    "metrics",
    "noise",
    "parallel",
    "parameters",
    "population",
    "signals",
    "simulate",
    "smoothed_derivative",
    "systems",
    "trajectory_rmse",
]
