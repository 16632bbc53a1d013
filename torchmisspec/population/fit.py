"""The population and the shared correction F, learned together.

:func:`fit_population` runs the package's own fits in turn:

1. the population for F = 0 (:func:`~torchmisspec.population.nlme.fit_nlme`: every experiment's parameters by
   their conditional mode given the population, the population's typical values, covariate effects and spreads by
   EM): the classical answer (the known model's nonlinear mixed-effects fit), kept as ``result.classical``;
2. every experiment's parameters learned *with* F (:mod:`~torchmisspec.population._integrated`): the population as
   one system whose uncertain parameters are every experiment's, their prior the classical population, F integrated
   out of the derivative samples (the package's theta-and-F fit, its model chosen by evidence). Its F, with the
   population refitted for it (EM), is the first candidate, where it already fits held-out experiments better than
   the classical answer (do no harm's rule, below, judged before that EM: under an F that wiggles every solve is
   stiff, and on nlme's Remifentanil that EM took a minute a round for an F refused in the end). Where some states
   are not measured this step is skipped (there it runs through the ODE, minutes on theophylline), and above
   :data:`MAX_INTEGRATED` parameters in all;
3. F for those parameters: each experiment's own parameters become known constant inputs of G
   (:mod:`~torchmisspec.population._subjects`) and :func:`~torchmisspec.fit_correction` learns F from every
   experiment with the pipeline given (model choice, the fit through the ODE where states are not measured, its do
   no harm);
4. the population for that F (EM again), and F again for the parameters it gives (:data:`ROUNDS` rounds of 3-4):
   the second candidate, where F's own fit kept one;
5. of the candidates, the one whose F, conditioned without them, fits held-out experiments best, if it fits them
   significantly better than the classical answer (do no harm, below).

F is shared: it takes the states (and the system's own controls), never an experiment's parameters; what differs
between experiments is in their parameters, what the mechanism lacks in every one of them is in F.

Why step 2: a correction and a typical value can stand in for each other. The population fitted with F = 0 puts into
its parameters what they can hold of the missing term (on the population study, ``scripts/study_population.py``, the
typical volume 3-5 standard errors off the truth where F = 0 was kept), and F learned at those parameters saw only
the remainder: F was kept in 1 of 10 realizations. Learned with F, the parameters give up what F explains. Learning
only the typical values' shifts with F was tried and dropped: on sparse data the derivative samples moved a shift by
5 prior standard deviations, and on one realization an F far off the truth (integrated error 92 against 3.5 for
F = 0) was kept.

Why two candidates: step 3's learner chooses F by held-out forecasts of each experiment at fixed parameters; on 2 of
the population study's 10 realizations every one of its candidates' forecasts ran away (held-out error 1e7) and it
kept F = 0 even knowing every subject's true parameters, while step 2's F was 0.1 and 0.74 of F = 0's integrated
error. Neither route is better everywhere (step 2's F was the better on 4 of 7 other realizations probed), so both
are scored by the rule that judges the end.

**Do no harm** (:mod:`~torchmisspec.population._held_out`): F is kept only where, conditioned without them, it fits
held-out experiments (each with its own parameters fitted through the ODE) significantly better than the classical
answer does; otherwise the classical answer is returned, with a warning.

**F's own uncertainty** (:mod:`~torchmisspec.population._f_uncertainty`): where F is kept, the typical values' and
covariate effects' standard errors and intervals count how far F's posterior draws move them, not only the
measurements' noise and the experiments' spread.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from .._errors import FittingError, InputError, IntegrationError, LinearAlgebraError, TorchMisspecWarning, warn
from .._validation import check_flag, progress_bar
from ..data import Trajectories
from ..learning.choice.stage import Evidence
from ..learning.pipeline import Pipeline
from ..learning.samples.stage import Samples
from ..noise import as_noise_model
from ..prediction.dynamics import CorrectedODE
from ..systems import MisspecifiedSystem
from . import files
from ._f_uncertainty import correction_shifts
from ._held_out import best_on_unseen_experiments
from ._integrated import integrated_modes, integrated_system, with_experiment_index
from ._misfit import residuals_by_time
from ._modes import mean_correction
from ._subjects import fitted_system, parameter_names, with_subject_inputs
from .calibration import ALONE, FIRST, SubjectCalibration, calibrate_subjects, calibrations
from .model import Population
from .nlme import NLMEFit, fit_nlme

__all__ = ["PopulationFit", "fit_population", "ROUNDS"]

#: rounds of (population, F): the second re-learns F at the parameters the first round's F gave
ROUNDS = 2
#: the stages the progress bar counts: the classical fit, the integrated start, the rounds, do no harm, calibration
STAGES = 4 + ROUNDS
#: the most parameters (experiments x varying parameters) learned with F in the integrated start: its fit checks G's
#: linearity in every pair of them, and R's ChickWeight (49 chicks x 2) did not finish in 15 minutes
MAX_INTEGRATED = 40
#: how many times wider F's own uncertainty makes a typical value's interval before the summary says why
WIDENED = 3.0


@dataclass(frozen=True)
class PopulationFit:
    """A population fitted with its correction (:func:`fit_population`).

    Attributes:
        system: the known model as declared; ``population`` its declaration; ``noise`` the noise model used.
        classical: the population fitted with F = 0 (:class:`~torchmisspec.population.nlme.NLMEFit`): the classical
            answer.
        nlme: the population fitted with the correction ``gp`` (the classical one when F = 0 was kept).
        gp: the correction, a fitted :class:`~torchmisspec.CorrectionGP` over the states of the system whose
            varying parameters are inputs (``subject_system``); ``gp.known_model_`` when F = 0 was kept.
    """

    system: MisspecifiedSystem
    population: Population
    noise: object
    classical: NLMEFit
    nlme: NLMEFit
    gp: object
    subject_system: MisspecifiedSystem
    #: the data fitted
    data: Trajectories | None = None
    #: ``(misfit with F, misfit with F = 0)`` of the held-out experiments that decided do no harm (``None`` where no
    #: correction was a candidate)
    held_out: tuple[float, float] | None = None
    #: how much a new subject's band from its first measurements is widened, measured on held-out subjects
    #: (:func:`~torchmisspec.population.calibration.calibrate_subjects`; ``None``: not calibrated)
    calibration: SubjectCalibration | None = None
    #: the same for a new subject's band from the population alone (its initial state; ``None``: not calibrated)
    calibration_alone: SubjectCalibration | None = None

    @property
    def known_model(self) -> bool:
        """Whether F = 0 (the classical answer: no correction, or do no harm kept F = 0)."""
        return self.gp is None or bool(getattr(self.gp, "known_model_", False))

    @functools.cached_property
    def residuals_by_time(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every measurement's time, squared residual and whether seen
        (:func:`~torchmisspec.population._misfit.residuals_by_time`): solved once, read by every design and every
        new subject's fit (:func:`~torchmisspec.population._misfit.misfit_scale`)."""
        return residuals_by_time(self)

    def as_classical(self) -> PopulationFit:
        """The classical answer as a fit of its own: the population fitted with F = 0, no correction (what
        :func:`~torchmisspec.population.predict.predict_subject` predicts with G alone)."""
        kept = self.known_model  # else measured with F: not the classical answer's
        return dataclasses.replace(
            self, nlme=self.classical, gp=None, calibration=self.calibration if kept else None,
            calibration_alone=self.calibration_alone if kept else None,
        )  # fmt: skip

    @property
    def thetas(self) -> torch.Tensor:
        """``(K, k)`` every experiment's parameters, in the order of ``system.parameters``."""
        return self.nlme.thetas

    @property
    def mean_correction(self):
        """F's posterior mean ``(y, u) -> (..., d)`` on the subject system (``None`` without a correction)."""
        return None if self.known_model else mean_correction(self.subject_system, self.gp)

    @property
    def corrected(self) -> CorrectedODE | None:
        """G with each experiment's parameters as inputs, plus F's posterior mean (``None`` without a correction)."""
        return None if self.gp is None else CorrectedODE(self.subject_system, self.gp)

    def calibration_for(self, first: Trajectories | None) -> SubjectCalibration | None:
        """The calibration of a new subject's band from its measurements ``first`` (:attr:`calibration`), or from
        the population alone where ``first`` is ``None`` (:attr:`calibration_alone`)."""
        return self.calibration if first is not None else self.calibration_alone

    def recalibrated(self, first: int, *, progress: bool = False) -> PopulationFit:
        """This fit with a new subject's band calibrated for subjects predicted from their ``first`` measurements
        (:func:`~torchmisspec.population.calibration.calibrate_subjects`; the fit's own is for
        :data:`~torchmisspec.population.calibration.FIRST`). Its calibration is ``None`` where none can be measured
        (no subject has more measurements, or F's training samples are not recorded, as in a loaded fit)."""
        return dataclasses.replace(self, calibration=calibrate_subjects(self, first=first, progress=progress))

    def save(self, path) -> Path:
        """Write this fit to ``path`` (tensors and plain values only, :mod:`~torchmisspec.population.files`): a
        population fitted once designs and predicts each next subject later. The system is code and is not saved:
        pass it again to :meth:`load`."""
        return files.save(self, path)

    @classmethod
    def load(cls, path, system: MisspecifiedSystem) -> PopulationFit:
        """The fit :meth:`save` wrote to ``path``; ``system`` the one it was fitted with (checked by name, state
        dimension and parameter names)."""
        return files.load(cls, path, system)

    def summary(self) -> str:
        """The population's values in a few lines: each varying parameter's typical value and spread with their
        95 % intervals (:meth:`~torchmisspec.population.nlme.NLMEFit.intervals`), the classical answer's beside."""
        names = self.population.varying
        head = f"{'parameter':<12}{'typical':>11}{'95% interval':>22}{'spread':>9}{'95% interval':>18}{'classical':>11}"
        lines = [head]
        vals, se, ci = self.nlme.values, self.nlme.standard_errors, self.nlme.intervals(0.95)
        dists = self.nlme.layout.distributions
        for j, n in enumerate(names):
            typical, classical = (float(dists[j].from_eta(v.mean[j])) for v in (vals, self.classical.values))
            lo, hi = (float(dists[j].from_eta(v)) for v in ci.mean[j])
            s_lo, s_hi = (float(v) for v in ci.spread[j])
            lines.append(
                f"{n:<12}{typical:>11.4g}{f'[{lo:.4g}, {hi:.4g}]':>22}{float(vals.spread[j]):>9.3g}"
                f"{f'[{s_lo:.3g}, {s_hi:.3g}]':>18}{classical:>11.4g}"
            )
        names_c = self.population.covariate_names
        for j, n in enumerate(names):
            for c, name in enumerate(names_c):
                if bool(vals.acts[j, c]):
                    lo, hi = (float(v) for v in ci.effects[j, c])
                    lines.append(
                        f"  {n} ~ {name}: {float(vals.effects[j, c]):+.4g} per unit (SE {float(se[2][j, c]):.2g}, "
                        f"95% [{lo:+.4g}, {hi:+.4g}]) in eta, around {name} = {float(vals.centre[c]):.4g}"
                    )
        kind = "F = 0 kept (the classical answer)" if self.known_model else "a correction F learned"
        if self.held_out is not None:
            kind += f" (held-out experiments' {_misfits(*self.held_out)})"
        coordinates = ", ".join(dict.fromkeys(f"{d.name}: {_eta(d)}" for d in dists))
        lines.append(f"spread in eta = {coordinates}; {kind}")
        lines += [str(c) for c in (self.calibration_alone, self.calibration) if c is not None]
        return "\n".join(lines + _f_widened(self.nlme, names))


def _f_widened(nlme: NLMEFit, names: list[str]) -> list[str]:
    """A line where F's own uncertainty widens a typical value's interval more than :data:`WIDENED` times (in eta):
    the intervals without it beside, and why (on nlme's Remifentanil, V's was [1.68, 1028] L with it)."""
    if nlme.shifts is None:
        return []
    wide, plain = nlme.intervals(0.95).mean, dataclasses.replace(nlme, shifts=None).intervals(0.95).mean
    ratio = (wide[:, 1] - wide[:, 0]) / (plain[:, 1] - plain[:, 0]).clamp_min(torch.finfo(wide.dtype).tiny)
    if not bool((ratio > WIDENED).any()):
        return []
    dists = nlme.layout.distributions
    said = ", ".join(
        f"{n} [{float(dists[j].from_eta(plain[j, 0])):.4g}, {float(dists[j].from_eta(plain[j, 1])):.4g}]"
        for j, n in enumerate(names)
    )
    return [
        "the typical values' intervals count F's own uncertainty: F and they can stand in for each other (a part of "
        f"F acts as a change of them), so read G and F together, not each; without it: {said}"
    ]


def _eta(distribution) -> str:
    return "log(theta)" if distribution.name == "lognormal" else "theta"


def fit_population(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    population: Population,
    *,
    covariates=None,
    pipeline: Pipeline | None = None,
    noise="auto",
    calibrate: bool = True,
    progress: bool = True,
) -> PopulationFit:
    """Fit a population of experiments that differ in some of G's parameters, and the correction F they share.

    Args:
        trajectories: K experiments (subjects, trees, batches), at least 2.
        system: the known model with uncertain ``parameters``; those named by ``population`` vary between
            experiments, the others are shared.
        population: :class:`~torchmisspec.population.Population`: which parameters vary, their distribution, and
            the covariates that shift them.
        covariates: ``{name: (K,) values}`` for the covariates ``population`` names.
        pipeline: how F is learned (:class:`~torchmisspec.Pipeline`; default its defaults with dy/dt estimated in
            the noise model's space, ``Samples(in_noise_space=True)``: on nlme's Remifentanil, one noise size for
            every derivative sample left F free at low concentrations, and paths drawn with F stalled there).
        noise: the noise model (:mod:`torchmisspec.noise`; default ``"auto"``).
        calibrate: measure how much a new subject's band from its first measurements, and from the population alone,
            must widen or narrow, by predicting held-out subjects
            (:func:`~torchmisspec.population.calibration.calibrate_subjects`; ``result.calibration`` and
            ``result.calibration_alone``, used by :func:`~torchmisspec.population.predict.predict_subject`); seconds
            more.
        progress: show progress bars (the stage the fit is in, EM rounds, F's fit).

    Returns:
        :class:`PopulationFit` (the module's notes).
    """
    if not isinstance(trajectories, Trajectories) or trajectories.num_experiments < 2:
        got = type(trajectories).__name__ if not isinstance(trajectories, Trajectories) else "one experiment"
        raise InputError(
            f"trajectories: expected Trajectories of at least 2 experiments (a population's spread needs several), "
            f"got {got}; fit one experiment with fit_correction"
        )
    if not isinstance(population, Population):
        raise InputError(f"population: expected a torchmisspec.population.Population, got {type(population).__name__}")
    calibrate = check_flag(calibrate, "calibrate")
    pipeline = Pipeline(samples=Samples(in_noise_space=True)) if pipeline is None else pipeline
    if pipeline.noise != "auto":  # the pipeline's own noise model is the fit's
        noise = pipeline.noise
    noise = as_noise_model(noise, trajectories, announce="fit_population")
    pipeline = dataclasses.replace(pipeline, noise=noise)
    options = dict(covariates=covariates, progress=progress)
    with progress_bar(progress, STAGES, "population: the classical fit (F = 0, EM)", "stage") as stages:
        fitted = _fitted(system, trajectories, population, noise, pipeline, options, stages)
        if not calibrate:
            return fitted
        stages.set_description("population: a new subject's bands calibrated on held-out subjects")
        found = calibrations(fitted, (ALONE, FIRST), progress=progress)
        return dataclasses.replace(fitted, calibration=found[FIRST], calibration_alone=found[ALONE])


def _fitted(system, trajectories, population, noise, pipeline, options, stages) -> PopulationFit:
    """:func:`fit_population`'s fit before its bands are calibrated: the classical fit, the candidates with F, and
    do no harm's judgement of them."""
    classical = fit_nlme(system, trajectories, population, noise, **options)
    stages.update()
    progress = options["progress"]
    candidates = [
        PopulationFit(system, population, noise, classical, nlme, gp, fitted_system(system, nlme), trajectories)
        for nlme, gp in _learn(system, trajectories, population, noise, pipeline, classical, progress, stages)
    ]
    if not candidates:
        warn(
            "fit_population: no correction F predicts held-out experiments better than the population without it "
            "(each experiment with its own parameters); returning the classical answer, the population with F = 0 "
            "(do no harm: known_model is True on the fit, and its summary says F = 0 kept)",
            TorchMisspecWarning,
        )
        return PopulationFit(
            system, population, noise, classical, classical, None, fitted_system(system, classical), trajectories
        )
    return _judged(candidates, classical, trajectories, stages)


def _judged(candidates: list, classical: NLMEFit, trajectories: Trajectories, stages) -> PopulationFit:
    """Do no harm (the module's notes): the candidate whose F, conditioned without them, fits held-out experiments
    best, kept where it fits them significantly better than the classical answer (its standard errors then count
    F's own uncertainty); otherwise the classical answer, with a warning."""
    stages.set_description("population: do no harm, F judged on held-out experiments")
    fitted, kept, with_f, without = best_on_unseen_experiments(candidates, classical, trajectories)
    fitted = dataclasses.replace(fitted, held_out=(with_f, without))
    stages.update()
    if kept:  # F's own uncertainty counted in the population's standard errors (_f_uncertainty's notes)
        stages.set_description("population: F's own uncertainty in the population's values")
        return dataclasses.replace(fitted, nlme=fitted.nlme.with_shifts(correction_shifts(fitted)))
    lower = " lower in total, but" if with_f < without else ""
    warn(
        f"fit_population: with the correction conditioned without them, held-out experiments (each with its own "
        f"parameters fitted) are not fitted significantly better than by the population without it "
        f"({_misfits(with_f, without)}:{lower} F is kept only where it helps experiment by experiment: a one-sided "
        "paired t-test of the log-ratio of their misfits over the held-out experiments at the 97.5 % level, or "
        "better in every one, not where a few experiments carry the total); returning the classical answer, the "
        "population with F = 0 (do no harm: known_model is True on the fit, and its summary says F = 0 kept). "
        "Collect more experiments",
        TorchMisspecWarning,
    )
    return fitted.as_classical()


def _misfits(with_f: float, without: float) -> str:
    """The held-out misfits in words; ``with_f`` is ``inf`` where F's folds stopped once past F = 0's total."""
    said = f"{with_f:.3g}" if math.isfinite(with_f) else f"above {without:.3g} (its folds stopped once past it)"
    return f"misfit {said} with F conditioned without them, {without:.3g} with F = 0"


def _learn(system, trajectories, population, noise, pipeline, classical, progress, stages) -> list[tuple]:
    """The candidates ``[(nlme, gp)]`` of (population, F) with F kept (the module's notes): the integrated fit's F
    with the population refitted for it, and F learned in rounds at the integrated start's parameters."""
    stages.set_description("population: F with every experiment's parameters (through the ODE)")
    start, joint = _integrated_start(system, trajectories, pipeline, classical, progress)
    stages.update()
    out = []
    candidate = PopulationFit(system, population, noise, classical, start, joint, fitted_system(system, start))
    if joint is not None and _helps(candidate, classical, trajectories, stages):
        stages.set_description("population: the population refitted under that F (EM through the ODE)")
        correction = mean_correction(candidate.subject_system, joint)
        refit = fit_nlme(system, trajectories, population, noise, start=start, correction=correction, progress=progress)
        out.append((refit, joint))
    nlme, gp = start, None
    for r in range(ROUNDS):
        stages.set_description(f"population: F at the experiments' parameters, round {r + 1} of {ROUNDS}")
        sub, data = _subject_data(system, nlme, trajectories)
        learned = _without_warnings(pipeline.fit, data, sub, progress=progress)
        if getattr(learned, "known_model_", False):  # F = 0 in the first round; later, the last F and its fit stand
            break
        gp = learned
        correction = mean_correction(fitted_system(system, nlme), gp)
        nlme = fit_nlme(system, trajectories, population, noise, start=nlme, correction=correction, progress=progress)
        stages.update()
    return out if gp is None else out + [(nlme, gp)]


def _helps(candidate: PopulationFit, classical: NLMEFit, trajectories: Trajectories, stages) -> bool:
    """Whether the integrated start's F, with the start's population, already fits held-out experiments better than
    the classical answer (do no harm's rule): only then is the population refitted under it. That EM is the fit's
    costliest step where F wiggles (nlme's Remifentanil, 8 subjects: F's lengthscale about 0.6 ng/mL of a 111 ng/mL
    range, a minute per round, up to 60 rounds, for an F do no harm refused)."""
    stages.set_description("population: that F judged on held-out experiments before the population is refitted")
    return best_on_unseen_experiments([candidate], classical, trajectories)[1]


def _integrated_start(system, trajectories, pipeline, classical, progress):
    """``(nlme, F)``: the classical fit with every experiment's parameters moved to where they are learned with F
    (:mod:`~torchmisspec.population._integrated`), and that fit's F; ``(classical, None)`` where that keeps F = 0,
    where some states are not measured (the theta-and-F fit then runs through the ODE: 3-6 minutes on
    theophylline's 12 subjects, against 30 s for the whole population fit), above :data:`MAX_INTEGRATED` parameters
    in all, and where that fit fails (F's own fit and the EM rounds follow, and do no harm judges the end)."""
    if trajectories.is_partial or classical.modes.eta.numel() > MAX_INTEGRATED:
        return classical, None
    evidence = dataclasses.replace(pipeline, choice=Evidence())
    try:
        joint = _without_warnings(
            evidence.fit,
            _indexed(system, classical, trajectories),
            integrated_system(system, classical),
            progress=progress,
        )
    except (FittingError, IntegrationError, LinearAlgebraError):  # the rounds from the classical fit follow
        return classical, None
    if getattr(joint, "known_model_", False) or getattr(joint, "parameters_", None) is None:
        return classical, None
    return dataclasses.replace(classical, modes=integrated_modes(joint, classical)), joint


def _indexed(system, nlme, trajectories):
    """The data of :func:`~torchmisspec.population._integrated.integrated_system`: every experiment's index as a
    control, its initial states the fit's."""
    return with_experiment_index(trajectories.with_initial_states(nlme.modes.initial_states), system)


def _without_warnings(fit, *args, **kwargs):
    """``fit(*args, **kwargs)`` with the package's warnings held: they name the system whose inputs are every
    experiment's parameters, not the user's; the population fit says what it decided
    (:func:`fit_population`)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TorchMisspecWarning)
        return fit(*args, **kwargs)


def _subject_data(system: MisspecifiedSystem, nlme: NLMEFit, trajectories: Trajectories):
    """The system F is learned with (the varying parameters as inputs, the shared ones fixed at the fit's values)
    and the data with every experiment's own parameters as its constant inputs."""
    names = parameter_names(system, nlme.layout.vary)
    data = with_subject_inputs(trajectories, nlme.thetas[:, nlme.layout.vary], names)
    return fitted_system(system, nlme), data.with_initial_states(nlme.modes.initial_states)
