"""The first model of F for partly measured data (:mod:`torchmisspec.learning.refinement.partial`): the feature kernel
fitted through the ODE to what was measured, with the initial states the data do not give (and G's uncertain
parameters), for as long as a :class:`FirstModel` says. It completes the data for the model choice that follows, and is
the rival correction's fit in :mod:`torchmisspec.learning.choice._partial_choice`."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..._ode import FITTING_TOLERANCES
from ...data import Trajectories
from ...gp import CorrectionGP
from ...gp._features import FEATURE_DEGREE
from ...systems import MisspecifiedSystem
from ._trajectory_map import _fit_relevance
from .trajectory_fit import _shooting

__all__ = ["FIRST_MODEL", "FIRST_MODEL_ROUNDS", "FirstModel", "feature_template", "first_model"]

#: rounds of relevance updates of the first model of F (it only completes the data for the model choice that
#: follows): on the chemostat and drug-model studies' data, 4 rounds gave the same final model as 10 at half the
#: cost, 2 rounds a worse one
FIRST_MODEL_ROUNDS = 4


@dataclass(frozen=True)
class FirstModel:
    """How long the first model of F is fitted through the ODE: at most ``rounds`` rounds of relevance updates, the
    first of at most ``max_iter`` Levenberg-Marquardt iterations (the later ones of at most 10)."""

    rounds: int = FIRST_MODEL_ROUNDS
    max_iter: int = 30


#: The correction's own first model.
FIRST_MODEL = FirstModel()


def feature_template(device) -> CorrectionGP:
    """The default candidates' feature kernel (monomials up to :data:`~torchmisspec.gp._features.FEATURE_DEGREE`,
    one set of relevance weights per output), unfitted."""
    return CorrectionGP(kernel="features", degree=FEATURE_DEGREE, per_output=True, device=device)


def first_model(
    system: MisspecifiedSystem,
    trajectories: Trajectories,
    completed,
    samples,
    noise,
    progress,
    parameters=False,
    theta_start=None,
    first: FirstModel = FIRST_MODEL,
):
    """The first model of F and the initial states, fitted to what was measured: the feature kernel (monomials up to
    :data:`~torchmisspec.learning.fit.FEATURE_DEGREE`, one set of relevance weights per output) through the ODE, its
    term weights by sparse Bayesian learning (:func:`~torchmisspec.fit_trajectories`' relevance fit), starting
    from F = 0 with a prior as large as G on F's outputs (the missing term may be as large as the known one), for
    at most :data:`FIRST_MODEL_ROUNDS` rounds of relevance updates; with ``parameters``, G's uncertain parameters
    are learned with it (their Laplace posterior in the result's ``parameters_laplace_``), from ``theta_start``
    (default their prior mean)."""
    filled = completed.filled()
    g = system.select_outputs(system.known_rhs(filled.flat_states(), filled.flat_times(), filled.flat_controls()))
    start = g.pow(2).mean(0).clamp_min(torch.finfo(g.dtype).tiny)  # (d_out,)
    gp = feature_template(samples.inputs.device).fit(samples)
    solver = dict(rtol=FITTING_TOLERANCES[0], atol=FITTING_TOLERANCES[1], max_steps=None, what="fit_correction")
    residuals, n_obs, offsets = _shooting(trajectories, "single", solver, system)
    return _fit_relevance(
        gp,
        system,
        trajectories,
        residuals,
        n_obs,
        offsets,
        noise,
        max_iter=first.max_iter,
        progress=progress,
        start=start,
        rounds=first.rounds,
        parameters=parameters,
        theta_start=theta_start,
    )
