"""One trajectory: the feature kernel refined through the ODE as the rival of the choice made on time pieces.

With one experiment, :func:`~torchmisspec.fit_correction` scores its candidates on pieces of the trajectory cut in
time (:func:`~torchmisspec.learning.time_pieces`), each candidate fitted to the derivative samples alone. The
feature kernel is then judged by its unrefined fit, whose terms come from the derivative estimator's errors as much
as from F (on the UDE Lotka-Volterra protocol its samples' fit kept a constant and cubic terms the data do not have):
it lost to an RBF in 6 of 10 realizations there and 6 of 10 on the GP-ODE Van der Pol protocol. Refined through
the ODE, as :func:`~torchmisspec.fit_correction` does whenever it keeps it, the same kernel found F within 0.005-0.16
of its size on Van der Pol (the RBF: 0.8-0.95) and forecast far better on both protocols, while a zero-mean RBF's
correction returns to 0 off the one path the data follow.

:func:`refined_rival` gives the refined feature kernel its own held-out test, on the same last piece of time as the
chosen candidate's: fitted and refined on the pieces before it, both forecast it from its first state, and the one
whose forecast misses less in the noise model's space is kept.
"""

from __future__ import annotations

import warnings

import torch

from ..._errors import FittingError, IntegrationError, LinearAlgebraError, TorchMisspecWarning
from ...data import Trajectories
from ...gp import CorrectionGP
from ...systems import MisspecifiedSystem
from ..refinement._first_model import feature_template
from ..refinement.trajectory_fit import _mean_field, fit_trajectories
from ..samples.observations import CorrectionSamples, correction_samples
from .cross_validation import _held_out_errors

__all__ = ["refined_rival"]


def _split(pieces: Trajectories) -> tuple[Trajectories, Trajectories]:
    """``(early, last)``: the pieces before the last joined into one experiment, and the last piece."""
    parts = pieces.experiments()
    t = torch.cat([p[0] for p in parts[:-1]])
    y = torch.cat([p[1] for p in parts[:-1]])
    controls = None if pieces.controls is None else pieces.controls[[0]]
    early = Trajectories(t, y.unsqueeze(0), state_names=pieces.state_names, controls=controls)
    last_t, last_y = parts[-1]
    last_controls = None if pieces.controls is None else pieces.controls[[len(parts) - 1]]
    last = Trajectories(last_t, last_y.unsqueeze(0), state_names=pieces.state_names, controls=last_controls)
    return early, last


def _score(system: MisspecifiedSystem, gp: CorrectionGP, last: Trajectories, noise) -> float:
    """The squared misfit of ``gp``'s corrected mean forecast of ``last`` from its first state (``inf`` when it
    cannot be integrated)."""
    mean = _mean_field(system, gp.posterior())
    try:
        return float(_held_out_errors(system, last, lambda y, rows, t=None, u=None: mean(y, t, u), noise).sum())
    except IntegrationError:
        return float("inf")


def refined_rival(
    system: MisspecifiedSystem, pieces: Trajectories, samples: CorrectionSamples, chosen: CorrectionGP, noise, estimator
) -> tuple[bool, dict]:
    """``(whether the refined feature kernel forecasts the last piece better, the record)``: ``chosen`` (fitted on
    the pieces' ``samples``) conditioned on the samples of the pieces before the last, against the feature kernel
    fitted on those pieces' own samples (``estimator``: :func:`~torchmisspec.correction_samples`' keywords) and
    refined through the ODE on them (:func:`~torchmisspec.fit_trajectories`); the record holds both misfits and the
    known model's alone (F = 0) on the same piece."""
    early, last = _split(pieces)
    keep = samples.experiment < pieces.num_experiments - 1
    noise_kept = None if samples.noise is None else samples.noise[keep]
    before = chosen.condition(samples.inputs[keep], samples.targets[keep], noise=noise_kept)
    score_chosen = _score(system, before, last, noise)
    try:
        with warnings.catch_warnings():  # the estimator's advice was given on the whole trajectory
            warnings.simplefilter("ignore", TorchMisspecWarning)
            early_samples = correction_samples(early, system, **estimator)
        features = feature_template(early_samples.inputs.device)
        refined = fit_trajectories(features.fit(early_samples), system, early)
        score_features = _score(system, refined, last, noise)
    except (FittingError, IntegrationError, LinearAlgebraError):
        score_features = float("inf")
    try:
        score_known = float(_held_out_errors(system, last, None, noise).sum())
    except IntegrationError:
        score_known = float("inf")
    record = {
        "chosen": score_chosen,
        "refined features": score_features,
        "known model": score_known,
        "held out": "the last time piece",
    }
    return score_features < score_chosen, record
