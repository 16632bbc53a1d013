"""The stages of the learning pipeline composed: what :class:`~torchmisspec.Pipeline` runs (its ``fit``, and
:func:`~torchmisspec.fit_correction`).

The steps a user would otherwise chain by hand: correction samples from the states (:func:`~torchmisspec.
correction_samples`, ``derivative="auto"`` by default), a :class:`~torchmisspec.CorrectionGP` on them chosen by
**cross-validation on trajectories** (by default among RBF kernels over a grid of lengthscales and a feature kernel
with automatic relevance, a sparse polynomial correction), and the trajectory-matching refinement
(:func:`~torchmisspec.fit_trajectories`) when a feature kernel is chosen or on request.

Why the model is chosen by cross-validation on trajectories, and how:
:mod:`torchmisspec.learning.choice.cross_validation`.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from dataclasses import dataclass

import torch

from .._errors import FittingError, InputError, IntegrationError, LinearAlgebraError, TorchMisspecWarning, warn
from ..data import Trajectories
from ..gp import CorrectionGP
from ..gp._exact import median_distance
from ..gp._features import FEATURE_DEGREE
from ..gp._selection import fit_and_score
from ..systems import MisspecifiedSystem
from ._units import fit_in_units
from .choice._do_no_harm import _do_no_harm, announce_known
from .choice._one_trajectory import refined_rival
from .choice._partial_choice import fit_partly_measured
from .choice._time_pieces import time_pieces
from .choice.cross_validation import (
    SIGNIFICANCE,
    CrossValidation,
    _check_cv_inputs,
    cross_validate,
    predicted_residuals,
)
from .refinement._first_model import feature_template
from .refinement._known_fit import KNOWN_MODEL_OUTPUTSCALE, known_model_template
from .refinement._no_worse import no_worse
from .refinement.trajectory_fit import _mean_field, fit_trajectories
from .samples.observations import (
    ESTIMATOR_ADVICE,
    CorrectionSamples,
    _check_trajectories_and_system,
    correction_samples,
)
from .theta.closed_form import _parameter_passes
from .theta.through_ode import fit_parameters

__all__ = [
    "FEATURE_DEGREE",
    "KNOWN_MODEL_OUTPUTSCALE",
    "LENGTHSCALE_GRID",
    "SIGNIFICANCE",
    "CrossValidation",
    "cross_validate",
    "cross_validate_lengthscale",
    "default_candidates",
    "known_model_template",
    "lengthscale_candidates",
]

#: Candidate lengthscales of the cross-validation, as multiples of the median distance between the samples' inputs
#: (the marginal-likelihood lengthscale is always added to them).
LENGTHSCALE_GRID = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
#: Above this many samples :func:`fit_correction` chooses its model on a subsample (each experiment's samples
#: thinned evenly, :meth:`CorrectionSamples.thinned`) and refits the chosen one on all of them: a candidate's
#: marginal-likelihood fit costs O(N^3) per step and the choice needs about 13 of them, while the held-out
#: experiments' predictions that score them change little once the samples are dense (BENCHMARKS.md, "The default
#: fit on a growing lab file": on 20 cultures the subsample and all 1,491 samples choose the same model, same error).
SELECTION_SAMPLES = 1000
#: Do no harm's second look (:func:`_second_look`) runs where the known model with its own parameters fitted predicts
#: the held-out data with at most this fraction of the squared error G has at theta's closed-form mean. Measured:
#: 0.21-0.55 in the absorbed-parameter study's realizations that the second look turned (docs/studies/absorbed.md),
#: 0.64-0.92 on the real-data suite's data sets whose known model wins (orange, chickweight, hare_lynx).
SECOND_LOOK = 0.6


def lengthscale_candidates(samples: CorrectionSamples, template: CorrectionGP | None = None) -> list[float]:
    """The default candidate lengthscales: :data:`LENGTHSCALE_GRID` times the median distance between the samples'
    inputs, plus the marginal-likelihood lengthscale of ``template`` (default ``CorrectionGP()``) on all samples."""
    template = CorrectionGP(device=samples.inputs.device) if template is None else template
    scale = median_distance(samples.inputs)
    candidates = {round(g * scale, 12) for g in LENGTHSCALE_GRID}
    try:
        candidates.add(
            round(float(template.clone(kernel=template.kernel_spec, lengthscale=None).fit(samples).lengthscale), 12)
        )
    except (FittingError, LinearAlgebraError):
        pass
    return sorted(candidates)


def cross_validate_lengthscale(
    system: MisspecifiedSystem,
    trajectories: Trajectories,
    samples: CorrectionSamples,
    *,
    gp: CorrectionGP | None = None,
    lengthscales=None,
    folds: int = 5,
) -> CrossValidation:
    """Score candidate lengthscales of one kernel by how well the corrected model predicts held-out experiments
    (:func:`cross_validate` over ``gp`` with each lengthscale fixed).

    Args:
        system: the misspecified system.
        trajectories: the observations the samples came from (experiment k of the samples is experiment k here).
        samples: the correction samples (:func:`~torchmisspec.correction_samples`).
        gp: a template :class:`CorrectionGP` (kernel, fixed values; default ``CorrectionGP()``): a shared RBF or
            Matern kernel whose lengthscale is not fixed.
        lengthscales: the candidates (default: :func:`lengthscale_candidates`).
        folds: number of folds (experiment k is in fold ``k % folds``); at most the number of experiments.

    Returns:
        :class:`CrossValidation`.
    """
    folds = _check_cv_inputs(system, trajectories, samples, folds)
    template = CorrectionGP(device=samples.inputs.device) if gp is None else gp
    if not isinstance(template, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP template or None, got {type(template).__name__}")
    kernel = "auto" if template.auto else template.kernel  # an unfitted auto model holds an RBF until it is fitted
    searchable = not template.auto and template.kernel_spec.stationary and template.kernel_spec.has_lengthscale
    if not searchable or template.fixed["lengthscale"] is not None or template.per_output:
        raise InputError(
            "gp: cross-validation chooses the lengthscale of a shared RBF or Matern kernel; got kernel "
            f"{kernel!r}, lengthscale={template.fixed['lengthscale']}, per_output={template.per_output}"
        )
    if lengthscales is None:
        lengthscales = lengthscale_candidates(samples, template)
    else:
        lengthscales = sorted(float(v) for v in lengthscales)
        if not lengthscales or not all(math.isfinite(v) and v > 0 for v in lengthscales):
            raise InputError(f"lengthscales: expected positive numbers, got {lengthscales}")
    candidates = [template.clone(kernel=template.kernel_spec, lengthscale=ell) for ell in lengthscales]
    return cross_validate(system, trajectories, samples, candidates, folds=folds)[0]


def default_candidates(samples: CorrectionSamples) -> list[CorrectionGP]:
    """The models :func:`fit_correction` chooses from by default: an RBF GP at each of
    :func:`lengthscale_candidates`, and a feature kernel (monomials up to :data:`FEATURE_DEGREE`, one set of
    relevance weights per output) whose evidence removes the terms the samples do not support."""
    on = {"device": samples.inputs.device}  # the models follow the data's device
    rbf = [CorrectionGP(lengthscale=ell, **on) for ell in lengthscale_candidates(samples)]
    return [*rbf, feature_template(on["device"])]


def _by_evidence(pool: list[CorrectionGP], samples: CorrectionSamples) -> CorrectionGP:
    """The candidate of highest evidence score (:attr:`CorrectionGP.evidence_score`), each fitted by marginal
    likelihood on the samples; one candidate is fitted alone (``kernel="auto"`` then chooses among its own kernels).
    ``result.model_selection_`` records every candidate (as ``kernel="auto"`` does)."""
    if len(pool) == 1:
        return copy.deepcopy(pool[0]).fit(samples)
    fitted = [copy.deepcopy(c) for c in pool]
    records = [fit_and_score(c, samples) for c in fitted]
    ok = [i for i, r in enumerate(records) if r["score"] is not None]
    if not ok:
        raise FittingError(
            "fit_correction: every candidate failed to fit: "
            + "; ".join(f"{r['kernel']}: {r['error']}" for r in records)
        )
    best = max(ok, key=lambda i: records[i]["score"])
    for i, r in enumerate(records):
        r["chosen"] = i == best
    result = fitted[best]
    result.model_selection_ = records
    return result


def _chooser(trajectories: Trajectories, samples: CorrectionSamples, system, derivative: str, estimator: dict):
    """``(the trajectories the candidates are scored on, their samples)``: the data and (at most about
    :data:`SELECTION_SAMPLES` of) their samples; one experiment: its :func:`time_pieces` and their own samples (the
    estimator's warnings were given on the whole); ``(None, None)`` when there is nothing to hold out."""
    if trajectories.num_experiments >= 2:
        return trajectories, samples.thinned(SELECTION_SAMPLES)
    pieces = time_pieces(trajectories)
    if pieces is None:
        return None, None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TorchMisspecWarning)
        return pieces, correction_samples(pieces, system, derivative=derivative, **estimator).thinned(SELECTION_SAMPLES)


def _rival_applies(scored, trajectories, result, system, given: bool) -> bool:
    """Whether :func:`~torchmisspec.learning.choice._one_trajectory.refined_rival` tests the refined feature kernel
    against the choice: one experiment cut in time (``scored`` its pieces), the default candidates (not ``given``), a
    chosen model that is not the feature kernel already, and an autonomous system without uncertain parameters (where
    the refinement through the ODE is what :func:`fit_correction` does by default)."""
    if given or result is None or scored is None or scored is trajectories:
        return False
    features = result.kernel_spec.terms and result.kernel_spec.feature_space
    return not features and system.autonomous and system.parameters is None


def _held_advice(caught) -> list:
    """The derivative estimator's warnings among ``caught`` (held back); every other warning given now."""
    held = []
    for w in caught:
        if issubclass(w.category, TorchMisspecWarning) and str(w.message).startswith(ESTIMATOR_ADVICE):
            held.append(w)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return held


def _give_advice(held: list, cv: CrossValidation | None) -> None:
    """The estimator's held warnings, unless the cross-validation ``cv`` found the correction significantly better
    than the known model on held-out data: the estimator's error then did not stop the correction from predicting
    (the advice would not change what the user does)."""
    if cv is not None and cv.significant:
        return
    for w in held:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def noise_scale(gp: CorrectionGP, system: MisspecifiedSystem, trajectories: Trajectories, noise) -> torch.Tensor:
    """``(d,)``: each component's root mean square residual (:class:`~torchmisspec.noise.NoiseModel` ``noise``'s) of
    the fitted model's mean prediction of every experiment from its first state (its estimated initial states where
    the data lack them), over the measurements after the first: the measurement noise and what the model misses, as
    one scale per component (NaN for a component with no such measurement)."""
    at = system if getattr(gp, "parameters_", None) is None else system.at(gp.parameters_.mean)
    y0 = getattr(gp, "initial_states_", None)
    data = (trajectories if y0 is None else trajectories.with_initial_states(y0)).to(dtype=gp.dtype, device=gp.device)
    mean = _mean_field(at, gp.posterior())
    r = predicted_residuals(at, data, lambda y, rows, t=None, u=None: mean(y, t, u), noise)
    r = r[:, 1:]  # the first row is where each prediction starts
    seen = ~torch.isnan(r)
    count = seen.sum((0, 1))
    total = r.nan_to_num(nan=0.0).pow(2).sum((0, 1))
    return torch.where(count > 0, (total / count.clamp_min(1)).sqrt(), torch.full_like(total, math.nan)).detach()


def _recorded(result: CorrectionGP, system: MisspecifiedSystem, trajectories: Trajectories, noise) -> CorrectionGP:
    """``result`` with ``noise_``, ``noise_scale_`` (:func:`noise_scale`, ``None`` where it cannot be computed),
    ``known_model_`` (``False`` unless the known model alone was chosen) and ``derivative_`` (the estimator of dy/dt
    the samples came from, ``derivative="auto"``'s choice included, e.g. ``"central order=4"``)."""
    result.noise_ = noise
    result.known_model_ = bool(getattr(result, "known_model_", False))
    result.derivative_ = getattr(getattr(result, "samples_", None), "derivative", None)
    try:
        result.noise_scale_ = noise_scale(result, system, trajectories, noise)
        result.noise_scale_ = result.noise_scale_ * math.sqrt(getattr(result, "dispersion_", 1.0))
    except (IntegrationError, LinearAlgebraError):
        result.noise_scale_ = None
    return result


def _fit(
    trajectories, system, *, select, derivative, folds, refine, progress, noise, gp=None, candidates=None, **estimator
):
    """:func:`fit_correction`'s steps, ``noise`` a :class:`~torchmisspec.noise.NoiseModel`; what it calls again on
    the data in their own units and on partly measured data completed (the records of :func:`_recorded` are the
    caller's)."""
    _check_trajectories_and_system(trajectories, system)
    options = dict(select=select, derivative=derivative, folds=folds, refine=refine, progress=progress, noise=noise)
    scaled = fit_in_units(_fit, trajectories, system, gp=gp, candidates=candidates, estimator=estimator, **options)
    if scaled is not None:  # fitted in the data's own units, returned in the user's (torchmisspec.learning._units)
        return scaled
    if trajectories.is_partial:  # some components not measured: learned through the ODE (partial.py)
        options = dict(gp=gp, candidates=candidates, select=select, derivative=derivative, folds=folds, refine=refine)
        return fit_partly_measured(trajectories, system, _fit, progress=progress, noise=noise, **options, **estimator)
    user_candidates = candidates is not None
    candidates = None if candidates is None else list(candidates)  # checked by the Pipeline's Candidates
    estimator = _sampled_in(estimator, noise)
    samples, advice = _samples_and_advice(trajectories, system, derivative, estimator)
    taken = refine is None and bool(advice)  # the estimator's advice taken where a correction is kept:
    refine = True if taken else refine  # F refined through the ODE, and the advice not given
    raw, posterior, declared, refine_f = samples, None, system, False
    if system.parameters is not None:  # theta integrated out with F (parameters.py): the choice below at its mean
        refine_f, refine, outputs = bool(refine), False, system.correction_outputs  # F's refinement after theta
        template = CorrectionGP(device=samples.inputs.device) if gp is None or gp.auto else gp
        posterior, samples = _parameter_passes(samples, system, template)
        system, samples = system.at(posterior.mean), samples.shifted(posterior.mean - system.theta, outputs)
    scored, chooser = _chooser(trajectories, samples, system, derivative, estimator) if select == "cv" else (None, None)
    if chooser is None:
        chooser = samples.thinned(SELECTION_SAMPLES)  # the model is chosen on at most about this many samples
    data = _ChoiceData(system, declared, trajectories, samples, raw, chooser, scored, noise,
                       dict(derivative=derivative, **estimator))  # fmt: skip
    cv = rival = result = None
    if scored is not None:
        given = user_candidates or gp is not None
        result, cv, rival, known = _by_cross_validation(data, gp, candidates, given, folds, progress, advice, taken)
        if known is not None and posterior is not None:  # F learned around the known model's own parameters
            result, cv, data, known = _second_look(data, known, cv, candidates, gp, progress)
        if known is not None:
            if taken:  # held while a correction could still be kept and refined
                _give_advice(advice, cv)
            if posterior is not None:  # what a larger F could stand in for stays on record, F = 0 returned
                known.parameters_ = known.parameters_.absorbing(posterior)
                known.parameters_.warn_if_unidentified("fit_correction")
            return known
    if cv is None and not taken:
        _give_advice(advice, None)
    if result is None:  # select="evidence", one experiment, or every candidate failed its cross-validation
        auto = CorrectionGP(kernel="auto", device=samples.inputs.device)
        result = _evidence_choice(candidates if user_candidates else [auto if gp is None else gp], chooser, samples)
    result, samples = _refined(result, data, posterior, refine, refine_f, progress, advice if taken else None)
    result.cross_validation_ = cv
    result.one_trajectory_rival_ = rival  # None unless one_trajectory.refined_rival ran
    result.samples_ = samples
    result.input_names_ = system.input_names(trajectories)  # what gp.terms() calls the inputs
    return result


def _sampled_in(estimator: dict, noise) -> dict:
    """:func:`~torchmisspec.correction_samples`' keywords from the estimator's options: ``in_noise_space`` becomes
    the fit's noise model (dy/dt estimated where the errors are alike: samples/_noise_space)."""
    options = {k: v for k, v in estimator.items() if k != "in_noise_space"}
    return {**options, "noise": noise} if estimator.get("in_noise_space") else options


@dataclass(frozen=True)
class _ChoiceData:
    """What :func:`_fit` chooses a model on: the system (at theta's posterior mean) and the one declared, the data,
    every sample (at theta's mean) and the estimator's own (``raw``), the samples the candidates are fitted on
    (``chooser``: at most about :data:`SELECTION_SAMPLES`), the trajectories (or time pieces) they are scored on
    (``scored``; ``None`` without cross-validation), the noise model and the estimator's options (``derivative``
    included)."""

    system: MisspecifiedSystem
    declared: MisspecifiedSystem
    trajectories: Trajectories
    samples: CorrectionSamples
    raw: CorrectionSamples
    chooser: CorrectionSamples
    scored: Trajectories | None
    noise: object
    estimator: dict


def _samples_and_advice(trajectories, system, derivative, estimator: dict):
    """``(the correction samples, the estimator's warnings held back)``: every other warning given now; the held
    ones are given later unless held-out data contradict them (:func:`_give_advice`)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        samples = correction_samples(trajectories, system, derivative=derivative, **estimator)
    return samples, _held_advice(caught)


def _cv_candidates(gp, candidates, chooser: CorrectionSamples) -> list:
    """The candidates the cross-validation scores: the given ones; without, :func:`default_candidates`; a ``gp``
    template with a free lengthscale at each of :func:`lengthscale_candidates`; any other template (auto
    included) scored as it is."""
    if candidates is not None:
        return candidates
    if gp is None:
        return default_candidates(chooser)
    free = not gp.auto and gp.kernel_spec.stationary and gp.fixed["lengthscale"] is None
    if free and not gp.per_output:
        return [gp.clone(kernel=gp.kernel_spec, lengthscale=ell) for ell in lengthscale_candidates(chooser, gp)]
    return [gp]


def _by_cross_validation(data: _ChoiceData, gp, candidates, given: bool, folds, progress, advice, taken=False):
    """``(model or None, cv, the one-trajectory rival's record or None, the known model or None)``: the candidates
    scored on held-out data (:func:`cross_validate`), the chosen one fitted on every sample; the known model alone
    where no candidate beats it (do no harm, unless candidates or a template were ``given``), or the refined feature
    kernel where it forecasts one trajectory's last piece better; the warnings of an unsupported correction. The
    estimator's held ``advice`` is given here unless it was ``taken`` (then the caller gives it where the known model
    is finally returned; a kept correction is refined through the ODE: the advice's fix)."""
    scored, chooser, samples = data.scored, data.chooser, data.samples
    candidates = _cv_candidates(gp, candidates, chooser)
    if scored is not data.trajectories:  # the pieces of one experiment, each its own fold
        folds = scored.num_experiments
    cv, models = cross_validate(
        data.system, scored, chooser, candidates, folds=folds, progress=progress, noise=data.noise
    )
    result = models[cv.index] if math.isfinite(min(cv.scores)) else None
    if result is not None and chooser is not samples:  # the chosen template, fitted on every sample
        result = copy.deepcopy(candidates[cv.index]).fit(samples)
    quiet = data.declared.parameters is not None  # the caller first learns F around the known model's parameters
    known, own = (None, None) if given else _do_no_harm(cv, data.raw, data.declared, data.trajectories, scored,
                                                          data.noise, announce=not quiet)  # fmt: skip
    if own is not None:  # the known model with its own parameters fitted, beside the baseline at the choice's
        cv = dataclasses.replace(cv, known_fitted=own)
    _give_advice([] if taken else advice, cv)  # taken: held until the choice is final (the second look may keep F)
    if known is not None:
        known.cross_validation_, known.samples_ = cv, data.raw
        known.input_names_ = data.declared.input_names(data.trajectories)
        return None, cv, None, known
    rival = None
    if _rival_applies(scored, data.trajectories, result, data.declared, given):
        better, rival = refined_rival(data.system, scored, chooser, models[cv.index], data.noise, data.estimator)
        if better:  # the feature kernel on every sample, refined below through the ODE on the trajectory
            result = feature_template(samples.inputs.device).fit(samples)
    _warn_unsupported(cv, rival, scored, data.trajectories)
    if result is None:
        warn(
            f"fit_correction: every candidate failed cross-validation (a fit or a held-out prediction failed: "
            f"{', '.join(cv.candidates)}); chose among them by evidence instead",
            TorchMisspecWarning,
        )
    return result, cv, rival, None


def _second_look(data: _ChoiceData, known, cv: CrossValidation, candidates, gp, progress):
    """:func:`_around_known` where the closed form's theta is the likely reason the candidates lost: G alone predicts
    the held-out data at least ``1 / SECOND_LOOK`` times better (sum of squares) at its own fitted parameters than
    there. Elsewhere (the two thetas predict alike) the candidates were learned around a theta as good, and the
    known model is returned at once, with do no harm's warning: a second look there costs a second
    cross-validation (a third of the fit's time on the real-data suite) and did not change a choice."""
    own = cv.known_fitted
    if own is None or not own < SECOND_LOOK * cv.baseline:
        announce_known(min(cv.scores), min(own if own is not None else math.inf, cv.baseline), data.declared)
        return None, cv, data, known
    return _around_known(data, known, cv, candidates, gp, progress)


def _around_known(data: _ChoiceData, known, cv: CrossValidation, candidates, gp, progress):
    """``(model, cv, data, known)``: do no harm's second look when G has uncertain parameters. The candidates were
    scored with G at theta's closed-form mean (F integrated out of the derivative samples); the known model won
    with its parameters fitted through the ODE. Before returning it, the candidates are scored again around those
    parameters (the samples r - G(y; theta_known), F learning what G at its own best fit still misses). A candidate
    that predicts the held-out data significantly better than the known model there is kept (``known`` None, the
    data moved to those parameters); otherwise the known model is returned as before, with do no harm's warning.
    Why: the closed form's mean rests on derivative estimates, and on sparse data the correction learned around it
    can lose to G at a better theta, while the same candidates around that theta beat it (the study of
    docs/studies/absorbed.md: held-out error 1.57 at the closed form's theta, 0.14 around the known model's, 0.40
    for the known model alone)."""
    declared, outputs = data.declared, data.declared.correction_outputs
    theta = known.parameters_.mean
    try:
        samples = _samples_around(data, theta).shifted(theta - declared.theta, outputs)
        at = declared.at(theta)
        scored, chooser = _chooser(data.trajectories, samples, at, data.estimator["derivative"],
                                   {k: v for k, v in data.estimator.items() if k != "derivative"})  # fmt: skip
        pool = _cv_candidates(gp, candidates, chooser)
        moved, models = cross_validate(at, scored, chooser, pool, folds=cv.folds, progress=progress, noise=data.noise)
    except (FittingError, LinearAlgebraError, IntegrationError):
        moved = None
    if moved is None or not (math.isfinite(min(moved.scores)) and moved.significant):
        announce_known(min(cv.scores), min(cv.known_fitted or math.inf, cv.baseline), declared)
        return None, cv, data, known
    result = models[moved.index]
    if chooser is not samples:  # the chosen template, fitted on every sample
        result = copy.deepcopy(pool[moved.index]).fit(samples)
    moved = dataclasses.replace(moved, known_fitted=cv.known_fitted)
    data = dataclasses.replace(data, system=at, samples=samples, chooser=chooser, scored=scored)
    return result, moved, data, None


def _samples_around(data: _ChoiceData, theta: torch.Tensor) -> CorrectionSamples:
    """The correction samples of the data with G at ``theta`` (the estimator's self-check of ``derivative="auto"``
    run there: at a prior mean far from the data it can choose another estimator), linearised at ``theta`` and
    expressed from the prior mean as every sample of a G with uncertain parameters is (``shifted`` moves them)."""
    declared = data.declared
    centred = declared.recentred(theta)  # G's parameters still uncertain: residuals and basis at theta
    with warnings.catch_warnings():  # the estimator's advice was given on the declared model's samples
        warnings.simplefilter("ignore", TorchMisspecWarning)
        samples = correction_samples(data.trajectories, centred, **data.estimator)
    step = theta.to(samples.basis) - declared.theta.to(samples.basis)
    return dataclasses.replace(samples, residuals=samples.residuals + samples.basis @ step)


def _warn_unsupported(cv: CrossValidation, rival: dict | None, scored: Trajectories, trajectories) -> None:
    """Warn when the data do not support a correction: the kept rival (the refined feature kernel) does not beat
    the known model on the last piece, or (no rival kept) no candidate predicts the held-out data ``scored`` (the
    ``trajectories`` or their time pieces) significantly better than the known model."""
    if rival is not None and rival["refined features"] < rival["chosen"]:
        # what the kept model was tested on: the last piece, against the known model alone too
        if not rival["refined features"] < rival["known model"]:
            warn(
                f"fit_correction: the feature kernel refined through the ODE forecasts the trajectory's last piece "
                f"better than the time pieces' choice ({rival['refined features']:.3g} vs {rival['chosen']:.3g}) "
                f"but not better than the known model alone ({rival['known model']:.3g}): the data do not "
                "support a correction. Collect more experiments or a longer one, or check the known model",
                TorchMisspecWarning,
            )
    elif not cv.significant:
        held = "experiments" if scored is trajectories else "pieces of the experiment's time"
        warn(
            f"fit_correction: no corrected model predicts held-out {held} significantly better than the "
            f"known model alone (best held-out error {min(cv.scores):.3g} vs {cv.baseline:.3g} without a "
            f"correction, {cv.folds} folds; required: a gain of {cv.critical:.3g} standard errors over the "
            f"{len(cv.gains) or scored.num_experiments} {held}): the data do not support a correction. "
            "Collect more experiments, sample the states more densely or with less noise, or check the known model",
            TorchMisspecWarning,
        )


def _evidence_choice(pool: list, chooser: CorrectionSamples, samples: CorrectionSamples) -> CorrectionGP:
    """The candidate of ``pool`` with the highest evidence on ``chooser`` (:func:`_by_evidence`), refitted on every
    sample when ``chooser`` is a subsample (the chosen kernel: an auto model's choice)."""
    result = _by_evidence(pool, chooser)
    if chooser is not samples:
        chosen = getattr(result, "model_selection_", None)
        result = result.clone(kernel=result.kernel_spec).fit(samples)
        result.model_selection_ = chosen
    return result


def _through_ode(result: CorrectionGP, system, trajectories, progress, advice, guarded=False) -> CorrectionGP:
    """``result`` refined through the ODE (:func:`fit_trajectories`). Where the refinement takes the estimator's
    ``advice`` (a list, possibly empty) rather than the user's ``refine=True`` (``None``), a refinement that cannot be
    fitted or integrated, or (where ``guarded``: every refinement the user did not ask for) that forecasts the data
    worse than ``result`` (``learning/refinement/_no_worse.py``), keeps ``result`` as learned from the derivative
    samples, says so, and gives the advice."""
    if not guarded:  # the user's refine=True (advice is only ever taken guarded)
        return fit_trajectories(result, system, trajectories, progress=progress)
    try:
        refined = fit_trajectories(result, system, trajectories, progress=progress)
    except (FittingError, IntegrationError, LinearAlgebraError) as error:
        if advice is None:
            raise
        why = f"failed ({str(error)[:200]})"
    else:
        kept, before, after = no_worse(result, refined, system, trajectories)
        if kept is refined:
            return refined
        why = f"forecast the data worse than the model it started from (squared misfit {after:.4g} vs {before:.4g})"
    taken = "(the derivative estimator's advice) " if advice is not None else ""
    warn(
        f"fit_correction: refining the correction through the ODE {taken}{why}; the correction is kept as learned "
        f"from the derivative samples",
        TorchMisspecWarning,
    )
    if advice is not None:
        _give_advice(advice, None)
    return result


def _refined(result: CorrectionGP, data: _ChoiceData, posterior, refine, refine_f: bool, progress, advice=None):
    """``(model, samples)``: the chosen model refined through the ODE (``refine``; by default a feature kernel on
    an autonomous system), then with uncertain parameters theta's posterior under it (F conditioned on
    r - H theta_bar, the samples linearised there) and, with ``refine_f``, F refined at theta's posterior mean.
    ``advice``: the estimator's held warnings where the refinement takes their advice (not asked for by the user):
    a refinement that fails then keeps the model unrefined and gives them (:func:`_through_ode`)."""
    trajectories, samples = data.trajectories, data.samples
    guard = refine is None or advice is not None  # a refinement the user did not ask for
    if refine is None:  # the feature kernel's terms, refined through the ODE (fit_trajectories)
        refine = result.kernel_spec.terms and result.kernel_spec.feature_space and data.system.autonomous
    if refine:  # a new model: the record of the evidence's choice carried over
        selection = getattr(result, "model_selection_", None)
        result = _through_ode(result, data.system, trajectories, progress, advice, guard)
        if selection is not None:
            result.model_selection_ = selection
    if posterior is not None:  # theta's posterior under the chosen model, and F conditioned on r - H theta_bar
        delta = (
            data.system.theta.to(posterior.prior_mean) - posterior.prior_mean
        )  # theta's mean, or the known model's (_around_known)
        result, samples = fit_parameters(result, samples, data.declared, trajectories, delta, data.noise)
        result.parameters_ = result.parameters_.absorbing(posterior)
        result.parameters_.warn_if_unidentified("fit_correction")
        if refine_f:  # F through the ODE at theta's mean, theta's posterior kept
            found = result.parameters_
            result = _through_ode(result, data.declared.at(found.mean), trajectories, progress, advice, guard)
            result.parameters_ = found
    return result, samples
