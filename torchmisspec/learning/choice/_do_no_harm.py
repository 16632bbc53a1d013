"""Do no harm: the known model alone (F = 0, its uncertain parameters fitted) returned by
:func:`~torchmisspec.fit_correction` when no candidate predicts the held-out experiments better than it."""

from __future__ import annotations

from ..._errors import FittingError, IntegrationError, LinearAlgebraError, TorchMisspecWarning, warn
from ...data import Trajectories
from ...systems import MisspecifiedSystem
from ..refinement._known_fit import known_model_template
from ..samples.observations import CorrectionSamples
from ..theta.closed_form import _parameter_passes
from ..theta.through_ode import fit_parameters
from .cross_validation import CrossValidation, _held_out_errors


def _known_model(raw: CorrectionSamples, system: MisspecifiedSystem, trajectories: Trajectories, scored, noise):
    """``(model, its held-out score or None)``: the known model with its uncertain parameters fitted (F = 0; as
    :func:`~torchmisspec.fit_correction` fits them under a correction: the closed form from the samples, then through
    the ODE on the trajectories) as a fitted :class:`~torchmisspec.CorrectionGP`
    (:func:`~torchmisspec.learning.refinement._known_fit.known_model_template`); its score is the sum of squared state
    errors from each experiment's first state (the parameters fitted on every experiment). Without uncertain
    parameters the score is ``None`` (the cross-validation's baseline is it)."""
    template = known_model_template(raw)
    if system.parameters is None:
        return template.fit(raw), None
    posterior, samples = _parameter_passes(raw, system, template)
    samples = samples.shifted(posterior.mean - system.theta, system.correction_outputs)
    model, _ = fit_parameters(template.clone().fit(samples), samples, system, trajectories,
                              posterior.mean - posterior.prior_mean, noise)  # fmt: skip
    score = float(_held_out_errors(system.at(model.parameters_.mean), scored, noise=noise).sum())
    return model, score


def _do_no_harm(cv: CrossValidation, raw, system, trajectories, scored, noise, *, announce: bool = True):
    """``(model, own)``: the known model (:func:`_known_model`, scored on the cross-validation's data ``scored``)
    when no candidate predicts the held-out experiments better than it (``None`` otherwise), with a warning saying
    so (``announce``; else the caller gives it, :func:`announce_known`); ``own`` its score with its own parameters
    fitted (``None`` without uncertain parameters, or when it cannot be fitted)."""
    try:
        model, own = _known_model(raw, system, trajectories, scored, noise)
    except (FittingError, LinearAlgebraError, IntegrationError):
        return None, None
    # the known model alone: at the parameters of the choice (the baseline) or at its own, whichever predicts better
    score = cv.baseline if own is None else min(own, cv.baseline)
    best = min(cv.scores)
    if best < score:
        return None, own
    if announce:
        announce_known(best, score, system)
    model.known_model_ = True
    return model, own


def announce_known(best: float, score: float, system: MisspecifiedSystem) -> None:
    """The warning of a known model returned: the best candidate's held-out error ``best`` against its ``score``."""
    fitted = "with its parameters fitted, " if system.parameters is not None else ""
    warn(
        f"fit_correction: no correction predicts the held-out experiments better than the known model alone "
        f"(best held-out error {best:.3g} vs {score:.3g}); returning the known model {fitted}F = 0 (do no harm; "
        "result.known_model_ is True). Collect more experiments, or check the known model",
        TorchMisspecWarning,
    )
