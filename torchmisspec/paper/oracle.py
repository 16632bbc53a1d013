"""The peers the studies measure a fit against on the same data: a system's uncertain parameters fitted through the
ODE alone (F = 0), the classical answer for the scientist's G and the parametric oracle for the truth's own form."""

from __future__ import annotations

import torch

import torchmisspec as tms
from torchmisspec.learning.refinement._known_fit import fit_known_model
from torchmisspec.noise import as_noise_model


def fitted_through_ode(system: tms.MisspecifiedSystem, data: tms.Trajectories, noise: str) -> tms.MisspecifiedSystem:
    """``system`` at its uncertain parameters fitted through the ODE to ``data`` with every initial state free and
    F = 0 (:func:`~torchmisspec.learning.refinement._known_fit.fit_known_model`, residuals of the noise model
    ``noise``: ``"additive"``, ``"relative"``, ...)."""
    free = torch.ones(data.num_experiments, data.state_dim, dtype=torch.bool)
    return system.at(fit_known_model(system, data, free, as_noise_model(noise, data)).theta)
