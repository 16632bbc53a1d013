"""The learning pipeline as one object: :class:`Pipeline`, its stages' options as objects, and
:func:`fit_correction`, the call that builds one from keywords and runs it.

The stages, in the order the data pass through them (each an object of its subpackage, composed by
:mod:`torchmisspec.learning.fit`):

1. ``samples``: :class:`~torchmisspec.learning.samples.stage.Samples`, samples of F from the observed states;
2. ``candidates``: :class:`~torchmisspec.learning.choice.stage.Candidates`, the models of F tried;
3. ``choice``: the rule that chooses among them, :class:`~torchmisspec.learning.choice.stage.HeldOut` (held-out
   experiments, with the known model alone as the rival: do no harm) or
   :class:`~torchmisspec.learning.choice.stage.Evidence`;
4. ``refinement``: :class:`~torchmisspec.learning.refinement.stage.Refinement`, the chosen model through the ODE;
5. G's uncertain parameters and unmeasured initial states, learned with F where the system and data have them
   (:mod:`torchmisspec.learning.theta`, :mod:`torchmisspec.learning.refinement.partial`): no options;
6. the bands' calibration on held-out experiments (:meth:`~torchmisspec.CorrectedODE.calibrate`), whose folds
   refit the chosen model with the stages after the choice.

Every entry point learns through it: :func:`fit_correction`, a :class:`~torchmisspec.design.Campaign`'s ``tell``
(the pipeline of the fit it started from, ``gp.pipeline_``), the command line's ``fit`` and ``design``, and the
studies. Why objects: a call's options stay few and named (as diffrax's ``PIDController`` or scikit-learn's
``Pipeline``), a rule is a variant object rather than a name branched on, and a campaign keeps the pipeline its model
came from and saves it as plain values.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .._errors import InputError
from .._validation import check_flag
from ..data import Trajectories
from ..gp import CorrectionGP
from ..noise import NoiseModel, as_noise_model
from ..parallel import adaptive_threads
from ..systems import MisspecifiedSystem
from .choice.stage import RULES, Candidates, Evidence, HeldOut
from .fit import _fit, _recorded
from .refinement.stage import Refinement
from .samples.observations import _check_trajectories_and_system
from .samples.stage import Samples

__all__ = ["Pipeline", "fit_correction"]

#: The stages of a :class:`Pipeline`, in the order the data pass through them.
STAGES = ("samples", "candidates", "choice", "refinement", "parameters and initial states", "calibration")


@dataclass(frozen=True)
class Pipeline:
    """How F is learned from trajectories: one object per stage, each with its options (the module docstring).

    Args:
        samples: :class:`~torchmisspec.learning.samples.stage.Samples` (default: ``derivative="auto"``).
        candidates: :class:`~torchmisspec.learning.choice.stage.Candidates` (default: RBF kernels over a grid of
            lengthscales and a sparse feature kernel, with the known model alone as their rival).
        choice: :class:`~torchmisspec.learning.choice.stage.HeldOut` (default, 5 folds) or
            :class:`~torchmisspec.learning.choice.stage.Evidence`.
        refinement: :class:`~torchmisspec.learning.refinement.stage.Refinement` (default: the feature kernel
            through the ODE on an autonomous system).
        noise: the measurement noise's model (:mod:`torchmisspec.noise`): ``"auto"`` (default), a name, or a
            :class:`~torchmisspec.noise.NoiseModel`.

    ``Pipeline().fit(trajectories, system)`` is ``fit_correction(trajectories, system)``; a fitted model records
    its pipeline as ``gp.pipeline_`` (``noise`` as the model chosen), which a campaign refits with.
    """

    samples: Samples = Samples()
    candidates: Candidates = Candidates()
    choice: HeldOut | Evidence = HeldOut()
    refinement: Refinement = Refinement()
    noise: str | NoiseModel = "auto"

    stages = STAGES

    def __post_init__(self):
        for name, kind in (("samples", Samples), ("candidates", Candidates), ("refinement", Refinement)):
            if not isinstance(getattr(self, name), kind):
                got = type(getattr(self, name)).__name__
                raise InputError(
                    f"{name}: expected a {kind.__name__} (torchmisspec.learning.{kind.__name__}), got {got}"
                )
        if not isinstance(self.choice, (HeldOut, Evidence)):
            raise InputError(
                f"choice: expected HeldOut(folds=...) or Evidence() (torchmisspec.learning), got "
                f"{type(self.choice).__name__}"
            )
        if not isinstance(self.noise, (str, NoiseModel)):
            raise InputError(
                f"noise: expected 'auto', a noise model's name or a torchmisspec.noise.NoiseModel, got "
                f"{type(self.noise).__name__}"
            )

    @classmethod
    def from_keywords(
        cls,
        *,
        gp=None,
        candidates=None,
        select="cv",
        derivative="auto",
        folds=5,
        refine=None,
        noise="auto",
        **estimator,
    ) -> Pipeline:
        """The pipeline :func:`fit_correction`'s keywords describe (``select``: ``"cv"`` or ``"evidence"``;
        ``estimator``: :class:`~torchmisspec.learning.samples.stage.Samples`' other options)."""
        if not (isinstance(select, str) and select in RULES):
            raise InputError(
                f"select: expected 'cv' (held-out experiments) or 'evidence' (marginal likelihood), got {select!r}"
            )
        unknown = sorted(set(estimator) - {f.name for f in dataclasses.fields(Samples)} - {"derivative"})
        if unknown:
            raise InputError(
                f"fit_correction: unexpected option(s) {unknown}; expected the pipeline's options (gp, candidates, "
                "select, derivative, folds, refine, noise) or the estimator's (noise_std, order, window, degree, "
                "generator, in_noise_space)"
            )
        choice = HeldOut(folds=folds) if select == "cv" else Evidence()
        return cls(
            samples=Samples(derivative=derivative, **estimator),
            candidates=Candidates(gp=gp, models=candidates),
            choice=choice,
            refinement=Refinement(through_ode=refine),
            noise=noise,
        )

    def keywords(self) -> dict:
        """The pipeline as :func:`fit_correction`'s keywords (the inverse of ``Pipeline.from_keywords``)."""
        models = self.candidates.models
        return dict(
            gp=self.candidates.gp,
            candidates=None if models is None else list(models),
            select=self.choice.select,
            derivative=self.samples.derivative,
            folds=self.choice.folds,
            refine=self.refinement.through_ode,
            noise=self.noise,
            **self.samples.estimator,
        )

    @adaptive_threads()
    def fit(self, trajectories: Trajectories, system: MisspecifiedSystem, *, progress: bool = True) -> CorrectionGP:
        """F learned from ``trajectories`` through every stage (:func:`fit_correction`'s steps); ``progress``
        shows bars over the candidates and the refinement's rounds."""
        _check_trajectories_and_system(trajectories, system)
        check_flag(progress, "progress")
        noise = as_noise_model(self.noise, trajectories, announce="fit_correction")
        options = {**self.keywords(), "noise": noise}
        result = _fit(trajectories, system, progress=progress, **options)
        result = _recorded(result, system, trajectories, noise)  # once, in the user's units, on the user's data
        result.trajectories_ = trajectories  # what a Campaign started from this fit holds, and refits with this
        result.pipeline_ = dataclasses.replace(self, noise=noise)
        return result


def _differs(value, default) -> bool:
    return value is not default and value != default


def fit_correction(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    *,
    pipeline: Pipeline | None = None,
    gp: CorrectionGP | None = None,
    candidates=None,
    select: str = "cv",
    derivative: str = "auto",
    folds: int = 5,
    refine: bool | None = None,
    progress: bool = True,
    noise="auto",
    **estimator,
) -> CorrectionGP:
    """Learn the correction from observed states: samples, a model chosen among candidates, optionally refined.

    The package's one entry point for choosing a model: ``Pipeline.from_keywords(...).fit(trajectories, system)``
    (:class:`Pipeline`, whose stages hold these options as objects), or ``pipeline.fit(...)`` for a given
    ``pipeline`` (then no other option). Its steps:

    1. ``samples = correction_samples(trajectories, system, derivative=derivative, **estimator)`` (its warning
       when the derivative estimator is unreliable applies);
    2. a model is fitted on the samples and chosen among candidates by the rule ``select`` names:

       * ``"cv"`` (default): by :func:`cross_validate`, the error of the corrected model's predictions of held-out
         experiments (robust to the derivative estimator's correlated errors, see the module's notes). Candidates:
         with neither ``gp`` nor ``candidates`` given, :func:`default_candidates` (RBF kernels over a grid of
         lengthscales and a feature kernel with automatic relevance, a sparse polynomial correction); with a ``gp``
         template of an RBF or Matern kernel with a free lengthscale, that kernel at each of
         :func:`lengthscale_candidates`; any other template, that model alone (scored, for the warning below);
         ``candidates``, the given unfitted templates. Each candidate's other hyperparameters by marginal
         likelihood. With one experiment, the pieces of its trajectory (:func:`time_pieces`, cut in time) are held
         out in turn (each forecast from its first state); when it is too short for two pieces, ``"evidence"`` is
         used. With one experiment and the default candidates, a chosen model other than the feature kernel is
         then tested against the feature kernel refined through the ODE on the pieces before the last (its
         derivative-samples fit alone is what the pieces scored): whichever forecasts the last piece better is
         kept (:mod:`torchmisspec.learning.choice._one_trajectory`; ``result.one_trajectory_rival_`` records both
         misfits);
       * ``"evidence"``: by the marginal likelihood of the samples alone (:attr:`CorrectionGP.evidence_score`, no
         solve): with neither ``gp`` nor ``candidates``, ``CorrectionGP(kernel="auto")`` (RBF, Matern, feature
         kernels and the library check, see :mod:`torchmisspec.gp`); a ``gp`` template is fitted as it is; among
         ``candidates`` the highest score wins. Cheaper, and right when the samples' errors are independent (exact
         or GP-in-time derivatives of dense data); a fixed lengthscale is a template's:
         ``gp=CorrectionGP(lengthscale=0.5)``.
    3. with ``refine=True``, :func:`~torchmisspec.fit_trajectories` refines it through the ODE; by default
       (``refine=None``) exactly when the chosen model is a feature kernel, whose term weights are then re-learned
       from the trajectories (the derivative estimator's bias shows up in the samples as spurious terms, which
       the trajectories do not support), for autonomous systems (with inputs or time the fit through the ODE runs
       each experiment under its own profile, but is not yet validated by a study: ask for it with ``refine=True``);
       with uncertain parameters, ``refine=True`` refines F at theta's posterior mean after theta's own fit through
       the ODE (by default it does not). A refinement made without ``refine=True`` (a feature kernel's, or the
       derivative estimator's advice) is kept only where its forecasts of the data from their first states are no
       worse, in the noise model's residuals, than those of the model it started from; otherwise that model is
       returned, with a warning (``learning/refinement/_no_worse.py``).

    **Partly measured states** (a component some experiment does not measure, :attr:`Trajectories.measured
    <torchmisspec.Trajectories.measured>`): the correction is learned through the ODE
    (:func:`torchmisspec.learning.choice._partial_choice.fit_partly_measured`: the unmeasured starting values and a
    first model of F fitted to the measured values, the data completed with its paths, then the steps above on the
    completed data); ``result.identifiability_`` says how the measurements see each output of F (an output none sees is
    refused), and ``result.initial_states_`` holds the estimated ``(K, d)`` initial states. Neither is saved with the
    model. With uncertain parameters of G, they are learned with the first model through the ODE (their Laplace
    posterior, F's terms and the initial states marginalised) and F is chosen at their posterior mean.

    **Units**: every step runs on the states divided by a power of ten near each component's size (and readings by
    their own), so that states in the thousands or in thousandths are fitted as states near 1 (data near 1 are left
    as they are); the model is returned in the user's units (:mod:`torchmisspec.learning._units`).
    ``cross_validation_``'s scores are in the scaled units, where the candidates were compared.

    **Do no harm**: with ``"cv"`` and the default candidates, the known model alone (F = 0) with its uncertain
    parameters fitted is returned (``result.known_model_`` is ``True``, with a warning) when no candidate predicts
    the held-out experiments (or pieces) better than it. With partly measured states, the known model's parameters
    and the initial states the data do not give are fitted through the ODE to the measured values (the classical
    answer, :func:`torchmisspec.learning.refinement._known_fit.fit_known_model`), the correction's own fit starts there,
    and the correction is kept only when, fitted on the first two thirds of each experiment's times, it forecasts the
    last third better than the known model fitted on the same times (with several experiments, significantly so over
    them: :mod:`torchmisspec.learning.choice._partial_choice`).

    With ``"cv"``, a :class:`~torchmisspec.TorchMisspecWarning` is issued when no candidate predicts the held-out
    experiments significantly better than the known model alone (:attr:`CrossValidation.significant`): the data do
    not support a correction (too few experiments, or a correction smaller than the measurement noise can reveal).

    Cost: one marginal-likelihood fit per candidate (the folds only re-condition it) and, with ``"cv"``, one batched
    solve of the held-out experiments per candidate; about 13 candidates by default. Above
    :data:`SELECTION_SAMPLES` samples the candidates are fitted and scored on a subsample (each experiment's
    samples thinned evenly, :meth:`CorrectionSamples.thinned`; the held-out experiments are still predicted over all
    their times) and the chosen one is refitted on every sample (an RBF kernel above ``LARGE_N`` samples then in a
    feature space, see :class:`CorrectionGP`): the choice costs what it costs at that size, whatever N. ``progress``
    (default on) shows bars over the candidates and the refinement's rounds; ``progress=False`` is silent.

    **Noise**: ``noise`` (:mod:`torchmisspec.noise`: ``"auto"``, ``"additive"``, ``"relative"``, ``"counts"``, or a
    :class:`~torchmisspec.noise.NoiseModel`) says in which space the measurement errors are alike; the held-out
    predictions are scored and G's uncertain parameters fitted through the ODE with its residuals (logs for
    ``"relative"``). ``"auto"`` takes relative errors for positive states spanning a factor of 5 or more, and says
    so. ``result.noise_`` records the model used, ``result.noise_scale_`` (:func:`noise_scale`) the scale of the
    fitted model's residuals in its space (for bands of new measurements); ``result.derivative_`` the estimator of
    dy/dt used (``"auto"``'s choice, e.g. ``"central order=4"``).

    Returns:
        the fitted :class:`CorrectionGP` (or the refined one); ``result.cross_validation_`` holds the
        :class:`CrossValidation` (``None`` without it), ``result.samples_`` the correction samples,
        ``result.trajectories_`` the data and ``result.pipeline_`` the :class:`Pipeline` of this call (``noise`` as the
        model chosen): a :class:`~torchmisspec.design.Campaign` started from the result holds those data and refits
        with that pipeline. None of these is saved with the model.
    """
    keywords = dict(gp=gp, candidates=candidates, select=select, derivative=derivative, folds=folds, refine=refine)
    keywords.update(noise=noise, **estimator)
    if pipeline is None:
        refine = check_flag(refine, "refine", none=True)
        pipeline = Pipeline.from_keywords(**keywords)
    elif not isinstance(pipeline, Pipeline):
        raise InputError(f"pipeline: expected a torchmisspec.Pipeline or None, got {type(pipeline).__name__}")
    else:
        defaults = Pipeline().keywords()
        given = sorted(k for k, v in keywords.items() if k not in defaults or _differs(v, defaults[k]))
        if not given:
            return pipeline.fit(trajectories, system, progress=progress)
        raise InputError(
            f"fit_correction: expected either a pipeline or the options it holds, got both (pipeline and {given}); "
            "put the options in the pipeline's stages"
        )
    return pipeline.fit(trajectories, system, progress=progress)
