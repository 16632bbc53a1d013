"""Partly measured data: a correction learned through the ODE, or the known model alone (do no harm).

:func:`fit_partly_measured` is what :func:`~torchmisspec.fit_correction` does when some component is not measured.
With the default candidates:

1. the known model alone (F = 0) is fitted to the measured values through the ODE: its uncertain parameters and the
   initial states the data do not give, in the noise model's space (:mod:`torchmisspec.learning.refinement._known_fit`,
   the classical answer a scientist would compute);
2. it is fitted again on the first two thirds of each experiment's times; with one experiment it must fail to
   forecast the last third within its own predictive uncertainty
   (:func:`~torchmisspec.learning.refinement._known_fit.forecast_check`: the noise and the spread of its fitted
   parameters and initial states, an F test at the 5 % level), and when it does not fail, the known model of step 1 is
   returned at once (a few held-out values of one path are too few to prefer a fitted rival to the scientist's model;
   with several experiments a parameter can absorb the missing term well enough to pass the check, so the rival is
   always fitted there);
3. otherwise a correction is learned on the first two thirds too (:mod:`torchmisspec.learning.refinement.partial`, its
   joint fit starting from the known model's; without the final refinement through the ODE, which took minutes on the
   lynx data), and kept, learned again on every time, only when it forecasts the last third better
   (:func:`~torchmisspec.learning.refinement._known_fit.forecast_score`), and with several experiments significantly so
   over them (a paired test of the log ratios of their misfits,
   :func:`~torchmisspec.learning.choice.cross_validation.significant_gain`); otherwise the known model of step 1 is
   returned.

The known model returned has ``result.known_model_`` set, a warning saying why, and bands widened by what the
held-out forecast showed (``result.dispersion_``). Real data sets that are one trajectory or partly measured lost to
the classical answer without these steps (theophylline 1.10x, lynx 1.85x, influenza 1.18x the classical forecast
error; docs/studies/real-data-suite.md).
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import torch

from ..._errors import FittingError, IntegrationError, LinearAlgebraError, TorchMisspecWarning, warn
from ...data import Trajectories
from ...systems import MisspecifiedSystem
from ..refinement._first_model import FirstModel
from ..refinement._known_fit import (
    CHECK_LEVEL,
    f_survival,
    fit_known_model,
    forecast_check,
    forecast_score,
    held_out,
    known_model_template,
    time_split,
)
from ..refinement.partial import _corrected, _from_readings, complete, identifiability, initial_guess, laplace_posterior
from ..refinement.trajectory_fit import _mean_field
from ..samples.observations import correction_samples
from .cross_validation import SIGNIFICANCE, significant_gain

__all__ = ["fit_partly_measured"]

#: The rival's first model of F through the ODE (step 3): fewer relevance rounds and Levenberg-Marquardt
#: iterations than the correction's own (:data:`~torchmisspec.learning.refinement._first_model.FIRST_MODEL`); on
#: theophylline its first round ran all 30 iterations for a misfit still falling by 0.04 (of 66) per iteration, 18 of
#: the fit's 28 s
TRIAL_FIRST_MODEL = FirstModel(rounds=2, max_iter=10)


def fit_partly_measured(trajectories: Trajectories, system: MisspecifiedSystem, fit, *, progress: bool, **options):
    """:func:`~torchmisspec.fit_correction` for partly measured data (the steps of the module docstring); ``fit``
    is ``fit_correction``'s steps (called on the completed data for the model choice), ``options`` its keywords.

    **Do no harm**: with the default candidates and ``select="cv"``, the correction is kept only when it forecasts
    held-out later times better than the known model alone (:mod:`torchmisspec.learning.refinement._known_fit`: each
    experiment's last third held out, both fitted on the rest,
    :func:`~torchmisspec.learning.refinement._known_fit.forecast_score`); otherwise the known model is returned with its
    uncertain parameters and initial states fitted to every measurement (F = 0, ``result.known_model_``), with a
    warning."""
    defaults = options.get("gp") is None and options.get("candidates") is None and options.get("select") == "cv"
    noise_model = options["noise"]
    start = initial_guess(trajectories, system)  # its warning for a component never observed, or its refusal
    with warnings.catch_warnings():  # the classical answer: the start of the correction's fit, and its rival
        warnings.simplefilter("ignore", TorchMisspecWarning)
        known = _known_fit_or_none(system, trajectories, noise_model, start)
    split = time_split(trajectories) if defaults and known is not None else None
    if split is None:  # a user's model, nothing to hold out, or no known model to compare with
        return _corrected(trajectories, system, fit, progress=progress, known=known, **options)
    early, keep = split
    with warnings.catch_warnings():  # the held-out check's own fits: their advice is the full fit's
        warnings.simplefilter("ignore", TorchMisspecWarning)
        # from the fit to every time (its initial states and parameters), or where that one started
        known_early = _known_fit_or_none(system, early, noise_model, known.initial_states, known.theta)
        if known_early is None:
            known_early = _known_fit_or_none(system, early, noise_model)
    if known_early is None:  # the known model cannot be fitted on the earlier times: the correction, as before
        return _corrected(trajectories, system, fit, progress=progress, known=known, **options)
    passed, ratio = forecast_check(system, known_early, trajectories, keep, noise_model)
    # one trajectory: its last third is a few values of one path, too few for a fitted rival to be preferred to the
    # model the scientist wrote unless that model demonstrably fails them (influenza: the split alone chose
    # corrections that forecast 2-10 times worse). Several experiments: the rival is always fitted and compared (a
    # parameter can absorb the missing term well enough to pass the check, with a confidently wrong value: the
    # chemostat tutorial's kd, 0.118 +- 0.005 against a true 0.05)
    if trajectories.num_experiments == 1 and passed >= CHECK_LEVEL:
        why = (
            f"the known model fitted on the first two thirds of each experiment forecasts the last third within its "
            f"own uncertainty (p = {passed:.2g}, {CHECK_LEVEL:g} needed to look for a correction)"
        )
        return _known_result(trajectories, system, known, why, ratio)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TorchMisspecWarning)
        try:
            # unrefined (its refinement through the ODE took minutes on the lynx data): a cheaper rival, if anything
            # less accurate than the correction it stands for, so the check leans towards the known model
            trial = _corrected(
                early,
                system,
                fit,
                progress=False,
                known=known_early,
                first=TRIAL_FIRST_MODEL,
                **{**options, "refine": False},
            )
        except (FittingError, IntegrationError, LinearAlgebraError):
            trial = None
    scale = torch.nan_to_num(known_early.scale, nan=1.0).clamp_min(torch.finfo(known_early.scale.dtype).tiny)
    at = system if known_early.theta is None else system.at(known_early.theta)
    y0 = known_early.initial_states
    per_known = forecast_score(at, at.known_rhs, trajectories, y0, keep, noise_model, scale)
    per_trial = torch.full_like(per_known, math.inf)
    if trial is not None:
        found = getattr(trial, "parameters_", None)
        at_trial = system if found is None else system.at(found.mean)
        field = _mean_field(at_trial, trial.posterior())
        per_trial = forecast_score(at_trial, field, trajectories, trial.initial_states_, keep, noise_model, scale)
    score_known, score_trial = float(per_known.sum()), float(per_trial.sum())
    # several experiments: better on the whole and significantly so over them (a paired test of the log ratios, as
    # cross-validation's), or a correction that forecasts some later times better but predicts a new experiment
    # worse is kept (theophylline's subject 8: 1.75 times the classical error); one: the check above failed already
    counts = held_out(trajectories, keep).any(-1).sum(1).cpu()  # held-out times (not values: see below)
    if score_trial < score_known and (
        trajectories.num_experiments == 1
        or significant_gain(_gains(per_known, per_trial))
        or better_in_every_experiment(per_known, per_trial, counts)
    ):
        return _corrected(trajectories, system, fit, progress=progress, known=known, **options)
    trial = "could not be fitted" if not math.isfinite(score_trial) else f"{score_trial:.3g}"
    better = "better" if trajectories.num_experiments == 1 else "significantly better over the experiments"
    why = (
        f"a correction fitted on the first two thirds of each experiment's times does not forecast the last third "
        f"{better} than the known model fitted on the same times (held-out misfit {trial} vs {score_known:.3g}; the "
        f"known model's forecast within its own uncertainty: p = {passed:.2g})"
    )
    return _known_result(trajectories, system, known, why, ratio)


def better_in_every_experiment(known: torch.Tensor, rival: torch.Tensor, counts: torch.Tensor) -> bool:
    """Whether the rival forecasts the held-out values of *every* experiment that has some significantly better:
    in each, the ratio of the two models' sums of squares ``known / rival`` exceeds the
    :data:`~torchmisspec.learning.choice.cross_validation.SIGNIFICANCE` quantile of F(n, n), n its ``counts`` of
    held-out *times* (the variance-ratio test). Requiring every one is an intersection-union test, of level
    1 - SIGNIFICANCE without a correction for the number of experiments.

    Its limits, stated: the two sums are taken on the same held-out values, and a wrong model's forecast errors are
    correlated along the path, so the test's n overstates the independent errors (counting times rather than
    values, components read at one time count once, is the conservative half of that); and offered beside the
    paired test over the experiments, the two together can keep a correction at up to twice the level of either.

    It speaks where the paired test over the experiments cannot: with 2 or 3 experiments Student's t has 1 or 2
    degrees of freedom (a critical value of 12.7 or 4.3 standard errors), and a correction that forecast both of two
    experiments 100-1,000 times better than the known model was refused (the readout design study, K = 2: 9 of 10).
    An experiment the rival forecasts worse, or not significantly better, leaves the decision to the paired test
    (theophylline's subject 8: a correction better on most subjects' later times predicted it 1.75 times worse)."""
    tested = 0
    for k, r, n in zip(known.tolist(), rival.tolist(), counts.tolist(), strict=True):
        if n == 0:  # nothing held out in this experiment
            continue
        if not (math.isfinite(r) and r < k):  # worse, as good (both perfect included), or not integrable
            return False
        if r > 0 and f_survival(k / r, n, n) >= 1.0 - SIGNIFICANCE:
            return False
        tested += 1
    return tested > 0


def _gains(known: torch.Tensor, rival: torch.Tensor) -> list[float]:
    """``log(known / rival)`` per experiment with held-out values (``known > 0``): +inf where only the rival's
    forecast is perfect or only the known model's cannot be integrated, -inf where only the rival's cannot."""
    out = []
    for k, r in zip(known.tolist(), rival.tolist(), strict=True):
        if k <= 0:  # nothing held out in this experiment
            continue
        if r == math.inf:
            out.append(-math.inf)
        elif r == 0 or k == math.inf:
            out.append(math.inf)
        else:
            out.append(math.log(k / r))
    return out


def given_initial_states(trajectories: Trajectories) -> torch.Tensor:
    """``(K, d)`` which initial states the data give (the first rows, or the first readings where a readout pins
    them); the others are estimated with a fit."""
    given = torch.isfinite(trajectories.initial_conditions)
    if trajectories.readout is not None:
        given = given | _from_readings(trajectories, trajectories.initial_conditions)[1]
    return given


def _known_fit_or_none(system: MisspecifiedSystem, trajectories: Trajectories, noise, start=None, theta=None):
    """The known model's fit (:func:`~torchmisspec.learning.refinement._known_fit.fit_known_model`) from the initial
    states ``start`` (default :func:`initial_guess`) and the parameters ``theta`` (default their prior mean), the
    initial states the first rows do not give free; ``None`` when G cannot be integrated from there."""
    given = given_initial_states(trajectories)
    start = initial_guess(trajectories, system) if start is None else start
    try:
        return fit_known_model(system, trajectories.with_initial_states(start), ~given, noise, theta_start=theta)
    except FittingError:
        return None


def _known_result(trajectories: Trajectories, system: MisspecifiedSystem, known, why: str, ratio: float):
    """The known model alone fitted to every measurement (``known``, a
    :class:`~torchmisspec.learning.refinement._known_fit.KnownFit`), as a fitted :class:`CorrectionGP`
    (:func:`~torchmisspec.learning.refinement._known_fit.known_model_template`) with ``parameters_`` (theta's Laplace
    posterior), ``initial_states_`` and ``identifiability_``, and a warning saying why.

    Its bands are widened by what the held-out later times showed: ``ratio`` (``Q / n`` of
    :func:`~torchmisspec.learning.refinement._known_fit.forecast_check`, the forecast's squared errors over their
    predicted variance) when above 1 multiplies theta's covariance and the residual variance (``result.dispersion_``;
    the noise scale :func:`~torchmisspec.fit_correction` records is multiplied by its square root): the model's own
    error beyond the data, which neither the measurement noise nor the parameters' spread accounts for."""
    at = system if known.theta is None else system.at(known.theta)
    completed = complete(at, at.known_rhs, trajectories, known.initial_states)
    report = identifiability(system, trajectories, completed=completed)
    report.check(system.name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TorchMisspecWarning)
        samples = correction_samples(completed, at, derivative="central")
    result = known_model_template(samples).fit(samples)
    dispersion = ratio if math.isfinite(ratio) and ratio > 1 else 1.0
    result.dispersion_ = dispersion
    if known.theta is not None:
        n = samples.inputs.shape[0]
        result.parameters_ = laplace_posterior(system, known.theta, known.covariance, known.fixed, completed, n)
        result.parameters_ = dataclasses.replace(
            result.parameters_, covariance=result.parameters_.covariance * dispersion
        )
    result.initial_states_ = known.initial_states
    result.identifiability_ = report
    result.cross_validation_, result.samples_ = None, samples
    result.input_names_ = system.input_names(trajectories)
    result.known_model_ = True
    fitted = "its parameters and " if known.theta is not None else ""
    warn(
        f"fit_correction: {why}; returning the known model with {fitted}the initial states the data do not give "
        "fitted to every measurement, F = 0 (do no harm; result.known_model_ is True). Collect more experiments or "
        "longer ones, or check the known model",
        TorchMisspecWarning,
    )
    if known.theta is not None:
        result.parameters_.warn_if_unidentified("fit_correction")
    return result
