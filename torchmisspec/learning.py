"""From observed trajectories to a fitted correction in one call: :func:`fit_correction`.

The steps a user would otherwise chain by hand: correction samples from the states (:func:`~torchmisspec.
correction_samples`, ``derivative="auto"`` by default), a :class:`~torchmisspec.CorrectionGP` on them chosen by
**cross-validation on trajectories** (by default among RBF kernels over a grid of lengthscales and a feature kernel
with automatic relevance, a sparse polynomial correction), and the trajectory-matching refinement
(:func:`~torchmisspec.fit_trajectories`) when a feature kernel is chosen or on request.

Why not maximise the marginal likelihood of the samples for the lengthscale too? The samples come from a derivative
estimator whose errors are correlated along each trajectory (the stencil or the GP in time uses neighbouring states,
and its bias follows the trajectory). Consecutive states are close in state space, so the marginal likelihood reads
the correlated error as signal on a short lengthscale: on paper_linear with 1 % state noise it picks lengthscales
near 0.2 where the correction is a smooth quadratic, and the corrected model is barely better than none
(``scripts/study_observations.py``). Modelling the correlation with the GP in time's posterior covariance did not fix
it (its bias is not in that covariance). The held-out prediction error needs no noise model: experiments are split
into folds; for each candidate lengthscale the GP is fitted on the other folds, the corrected model is integrated
from each held-out experiment's first observed state over its own times, and the squared differences from its
observed states are summed. The known model alone (no correction) is scored the same way: when the best candidate
does not beat it significantly (a paired one-sided Student t test at level 1 - :data:`SIGNIFICANCE`, per
experiment, on log error ratios),
:func:`fit_correction` warns
that the data do not support a correction. To keep the cost at one marginal-likelihood fit per candidate, each
candidate's output scale and noise are fitted once on all samples and the folds only refit the posterior.
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import dataclass

import torch

from ._errors import (
    FittingError,
    InputError,
    IntegrationError,
    LinearAlgebraError,
    NumericalWarning,
    TorchMisspecWarning,
    warn,
)
from ._ode import FITTING_TOLERANCES, solve
from ._parameters_ode import fit_parameters
from ._threads import adaptive_threads
from ._validation import check_flag, check_positive_int, progress_bar
from .data import Trajectories, simulate_known_each
from .gp import CorrectionGP
from .gp._exact import median_distance
from .gp._features import FEATURE_DEGREE
from .gp._paths import detached, kernel_hyperparameters, kernel_matrix
from .gp._selection import fit_and_score
from .observations import CorrectionSamples, _check_trajectories_and_system, correction_samples
from .parameters import posterior_given
from .partial import fit_partly_measured
from .systems import MisspecifiedSystem
from .trajectory_fit import fit_trajectories

__all__ = [
    "FEATURE_DEGREE",
    "LENGTHSCALE_GRID",
    "SELECTION",
    "SIGNIFICANCE",
    "CrossValidation",
    "cross_validate",
    "cross_validate_lengthscale",
    "default_candidates",
    "fit_correction",
    "lengthscale_candidates",
]

#: Candidate lengthscales of the cross-validation, as multiples of the median distance between the samples' inputs
#: (the marginal-likelihood lengthscale is always added to them).
LENGTHSCALE_GRID = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
#: Above this many samples :func:`fit_correction` chooses its model on a subsample (each experiment's samples
#: thinned evenly, :meth:`CorrectionSamples.thinned`) and refits the chosen one on all of them: a candidate's
#: marginal-likelihood fit costs O(N^3) per step and the choice needs about 13 of them, while the held-out
#: experiments' predictions that score them change little once the samples are dense (measured in
#: docs/tutorials/limits.md).
SELECTION_SAMPLES = 1000
#: The rules :func:`fit_correction` chooses a model by (its ``select``).
SELECTION = ("cv", "evidence")
#: Solver steps allowed for one held-out prediction (a candidate whose prediction blows up scores infinity).
_CV_MAX_STEPS = 2000


@dataclass(frozen=True)
class CrossValidation:
    """The scores of :func:`cross_validate` (and :func:`cross_validate_lengthscale`).

    Attributes:
        candidates: a label per candidate model (e.g. ``"rbf lengthscale=0.35"``, ``"features degree=3"``).
        lengthscales: each candidate's lengthscale (``None`` for kernels without one).
        scores: held-out sum of squared state errors of each candidate (``inf`` when a fit or a prediction failed).
        baseline: the same score of the known model alone (no correction).
        best: the label of the chosen candidate (smallest score).
        folds: the number of folds.
        gains: ``(K,)`` per held-out experiment, ``log`` of the known model's squared error over the best
            candidate's (positive: the correction helps on that experiment).
        index: the position of the chosen candidate.
        samples: the number of correction samples the candidates were fitted on (:func:`fit_correction` scores
            them on at most about :data:`SELECTION_SAMPLES`).
    """

    candidates: tuple[str, ...]
    lengthscales: tuple[float | None, ...]
    scores: tuple[float, ...]
    baseline: float
    best: str
    folds: int
    gains: tuple[float, ...] = ()
    index: int = 0
    samples: int = 0

    @property
    def best_lengthscale(self) -> float | None:
        """The chosen candidate's lengthscale (``None`` for a kernel without one)."""
        return self.lengthscales[self.index]

    @property
    def improves(self) -> bool:
        """Whether the best candidate predicts held-out experiments better than the known model alone."""
        return min(self.scores) < self.baseline

    @property
    def significant(self) -> bool:
        """Whether the best candidate beats the known model significantly: a paired comparison over the held-out
        experiments of the log ratio of their errors (log ratios, because the experiments' errors differ by orders
        of magnitude), whose mean must exceed :attr:`critical` standard errors (the one-sided Student t test at
        level 1 - :data:`SIGNIFICANCE`): the evidence that the correction helps at all. An infinite gain (the known
        model alone cannot be integrated over a held-out experiment that the corrected model predicts) is
        significant by itself."""
        n = len(self.gains)
        if not self.improves:
            return False
        if any(g == math.inf for g in self.gains):
            return True
        if n < 2:
            return False
        mean = sum(self.gains) / n
        var = sum((g - mean) ** 2 for g in self.gains) / (n - 1)
        return mean > self.critical * math.sqrt(var / n)

    @property
    def critical(self) -> float:
        """The number of standard errors :attr:`significant` asks for: the :data:`SIGNIFICANCE` quantile of Student's
        t with n - 1 degrees of freedom (2.78 for 5 experiments, 2.26 for 10, 1.96 for many)."""
        return student_t_quantile(SIGNIFICANCE, max(len(self.gains) - 1, 1))


#: Standard errors by which the cross-validated correction must beat the known model for :func:`fit_correction`
#: not to warn.
SIGNIFICANCE = 0.975


def student_t_quantile(p: float, df: int) -> float:
    """The ``p`` quantile (``p`` in [0.5, 1)) of Student's t with ``df`` degrees of freedom: exact for 1 and 2, the
    Cornish-Fisher expansion in 1/df about the normal quantile above (relative error below 1e-3 for df >= 3 at
    p = 0.975; e.g. 3.180 for df = 3 against 3.182)."""
    z = math.sqrt(2.0) * torch.erfinv(torch.tensor(2.0 * p - 1.0, dtype=torch.float64)).item()
    if df == 1:
        return math.tan(math.pi * (p - 0.5))
    if df == 2:
        return (2.0 * p - 1.0) / math.sqrt(2.0 * p * (1.0 - p))
    v = float(df)
    g1 = (z**3 + z) / 4
    g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96
    g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384
    g4 = (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160
    return z + g1 / v + g2 / v**2 + g3 / v**3 + g4 / v**4


def _held_out_errors(system: MisspecifiedSystem, trajectories: Trajectories, field=None) -> torch.Tensor:
    """``(K,)`` sums of squared errors of a model from each experiment's first observed state over its own times.

    ``field(y, rows, t, u)``: the right-hand side for states ``y (B, d)`` of the experiments ``rows`` (each
    experiment may have its own model: the folds of the cross-validation), at times ``t`` and controls ``u`` (``None``
    for an autonomous system); ``None``: the known model G alone. One batched solve of every experiment (ragged ones
    on their own times, padded at their end), each under its own controls."""
    rtol, atol = FITTING_TOLERANCES
    out = torch.empty(trajectories.num_experiments, dtype=torch.float64)
    times, states, mask = trajectories.padded()
    first = trajectories.initial_conditions  # missing first entries estimated (Trajectories.filled)
    if times.dim() == 1:
        times = times.expand(states.shape[0], -1)
    controls = trajectories.controls
    if field is None:
        known, timed, jumps = system.solver_field(system.known_rhs, controls)
        try:
            pred = solve(known, first, times, rtol=rtol, atol=atol, what="the known model", timed=timed, jumps=jumps)[0]
        except IntegrationError:
            # the known model alone diverges from some of these states (what a correction may exist to fix):
            # each experiment alone, and an infinite error where G cannot be integrated
            each = simulate_known_each(system, trajectories, rtol=rtol, atol=atol)
            for k, ((_, y), pred) in enumerate(zip(trajectories.experiments(), each, strict=True)):
                out[k] = math.inf if pred is None else float((pred - y).nan_to_num(nan=0.0).pow(2).sum())
            return out
    else:
        rows = torch.arange(states.shape[0], device=states.device)
        model, timed, jumps = system.solver_field(lambda y, t, u: field(y, rows, t, u), controls)
        pred, _ = solve(
            model,
            first,
            times,
            rtol=rtol,
            atol=atol,
            max_steps=_CV_MAX_STEPS,
            what="cross-validation",
            timed=timed,
            jumps=jumps,
        )
    sq = (pred - states).nan_to_num(nan=0.0).pow(2).sum(-1) * mask  # missing entries (NaN) are not compared
    return sq.sum(-1).detach().cpu().to(torch.float64)


def _check_candidates(candidates) -> list:
    """The candidate templates as a list, or an error naming what was received."""
    candidates = list(candidates)
    if not candidates or not all(isinstance(c, CorrectionGP) for c in candidates):
        got = [type(c).__name__ for c in candidates] or "an empty list"
        raise InputError(f"candidates: expected a non-empty list of CorrectionGP templates, got {got}")
    return candidates


def _fold_field(system: MisspecifiedSystem, gp: CorrectionGP, alphas: torch.Tensor, fold_of: torch.Tensor):
    """G(y) + the posterior mean of the GP fitted without experiment k's fold, for the rows of experiments k.

    The fold models share the kernel and the training inputs X (a held-out sample enters with weight 0), so each
    is ``k(x, X) alpha_f``: ``alphas (folds, N, d_out)``, ``fold_of (K,)``; one kernel or one per output."""
    params = detached(kernel_hyperparameters(gp))
    X = gp.train_inputs_

    def field(y: torch.Tensor, rows: torch.Tensor, t=None, u=None) -> torch.Tensor:
        x = system.select_inputs(y, u).to(X)  # the GP's dtype and device (float32 data with a float64 GP)
        Kx = kernel_matrix(gp.kernel_spec, x, X, params, gp.degree)  # (1 or d_out, B, N)
        a = alphas[fold_of[rows]]  # (B, N, d_out)
        if Kx.shape[0] == 1:
            mu = (Kx[0].unsqueeze(1) @ a).squeeze(1)  # (B, d_out)
        else:
            mu = torch.einsum("obn,bno->bo", Kx, a)
        return system.known_rhs(y, t, u) + system.embed(mu.to(y))

    return field


def _label(gp: CorrectionGP) -> str:
    """A candidate's label: its kernel and what distinguishes it."""
    if gp.kernel_spec.stationary:
        ell = gp.fixed["lengthscale"]
        label = gp.kernel + ("" if ell is None else f" lengthscale={ell:.4g}")
    else:
        label = f"{gp.kernel} degree={gp.degree}"
    return label + (" per_output" if gp.per_output else "")


def _check_cv_inputs(system, trajectories, samples, folds) -> int:
    _check_trajectories_and_system(trajectories, system)
    if not isinstance(samples, CorrectionSamples):
        raise InputError(f"samples: expected CorrectionSamples, got {type(samples).__name__}")
    K = trajectories.num_experiments
    folds = check_positive_int(folds, "folds")
    if K < 2 or folds < 2:
        raise InputError(
            f"folds: expected at least 2 experiments and 2 folds for cross-validation, got K={K}, folds={folds}"
        )
    if int(samples.experiment.max()) > K - 1 or len(samples) > trajectories.num_samples:  # missing entries: fewer
        raise InputError(
            f"samples: expected the correction samples of these {K} experiments ({trajectories.num_samples} samples), "
            f"got {len(samples)} samples of {int(samples.experiment.max()) + 1} experiments"
        )
    return min(folds, K)


@adaptive_threads()
def cross_validate(
    system: MisspecifiedSystem,
    trajectories: Trajectories,
    samples: CorrectionSamples,
    candidates,
    *,
    folds: int = 5,
    progress: bool = False,
) -> tuple[CrossValidation, list[CorrectionGP | None]]:
    """Score candidate correction models by how well the corrected model predicts held-out experiments.

    Each candidate (an unfitted :class:`CorrectionGP` template: any kernel, fixed values or not) is fitted once on
    all samples (its hyperparameters by marginal likelihood); for each fold it is then conditioned
    (:meth:`CorrectionGP.condition`, nothing re-learned) on the other folds' samples, and the corrected model is
    integrated from each held-out experiment's first observed state over its own times (all folds' experiments in
    one batched solve). The score is the sum of squared differences from the observed states.

    Args:
        system: the misspecified system.
        trajectories: the observations the samples came from (experiment k of the samples is experiment k here).
        samples: the correction samples (:func:`~torchmisspec.correction_samples`).
        candidates: unfitted :class:`CorrectionGP` templates.
        folds: number of folds (experiment k is in fold ``k % folds``); at most the number of experiments.
        progress: show a progress bar over the candidates.

    Returns:
        ``(CrossValidation, models)``: the scores, and each candidate fitted on all samples (``None`` where the fit
        failed).
    """
    folds = _check_cv_inputs(system, trajectories, samples, folds)
    candidates = _check_candidates(candidates)
    K = trajectories.num_experiments
    experiment = samples.experiment
    fold_of = [k % folds for k in range(K)]
    folds_t = torch.tensor(fold_of, device=samples.inputs.device)
    scores, per_experiment, models = [], [], []
    bar = progress_bar(progress, len(candidates), "fit_correction: cross-validating candidate models", "model")
    for template in candidates:
        bar.update()
        errors = torch.full((K,), math.inf, dtype=torch.float64)
        full = None
        try:
            with warnings.catch_warnings():  # scoring: a candidate's numerical warnings are not the user's
                warnings.simplefilter("ignore", NumericalWarning)
                full = copy.deepcopy(template).fit(samples)
                alphas = torch.zeros((folds, *samples.targets.shape), dtype=full.dtype, device=full.device)
                for f in range(folds):
                    held = [k for k in range(K) if fold_of[k] == f]
                    keep = ~torch.isin(experiment, torch.tensor(held, device=experiment.device))
                    noise = None if samples.noise is None else samples.noise[keep]
                    fold_gp = full.condition(samples.inputs[keep], samples.targets[keep], noise=noise)
                    alphas[f, keep] = fold_gp.posterior().weights  # (N_f, d_out)
                errors = _held_out_errors(system, trajectories, _fold_field(system, full, alphas, folds_t))
        except (IntegrationError, FittingError, LinearAlgebraError):
            errors.fill_(math.inf)
        scores.append(float(errors.sum()))
        per_experiment.append(errors)
        models.append(full)
    bar.close()
    base = _held_out_errors(system, trajectories)
    i = min(range(len(scores)), key=scores.__getitem__)
    tiny = torch.finfo(torch.float64).tiny
    ratio = base.clamp_min(tiny) / per_experiment[i].clamp_min(tiny)
    gains = tuple(ratio.log().tolist()) if math.isfinite(scores[i]) else ()
    labels = tuple(_label(c) for c in candidates)
    ells = tuple(c.fixed["lengthscale"] if c.kernel_spec.stationary else None for c in candidates)
    n = samples.inputs.shape[0]
    result = CrossValidation(labels, ells, tuple(scores), float(base.sum()), labels[i], folds, gains, i, n)
    return result, models


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
    return [*rbf, CorrectionGP(kernel="features", degree=FEATURE_DEGREE, per_output=True, **on)]


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


#: passes of the fit of G's uncertain parameters before the model is chosen: each fits the GP's hyperparameters on
#: the samples at the current estimate of theta and updates theta's posterior (its mean moves the targets)
PARAMETER_PASSES = 3


def _parameter_passes(samples: CorrectionSamples, system: MisspecifiedSystem, template: CorrectionGP):
    """``(theta's posterior, the samples)`` after :data:`PARAMETER_PASSES` alternations of the GP's hyperparameters
    (``template``, by marginal likelihood on the samples at the current theta) and theta's closed-form posterior given
    them; for a G nonlinear in theta, each pass's posterior is Gauss-Newton's to convergence (the samples linearised
    at each step's mean, :mod:`torchmisspec.parameters`), and the samples come back linearised at the last mean."""
    outputs, posterior = system.correction_outputs, None
    for _ in range(PARAMETER_PASSES):
        delta = None if posterior is None else posterior.mean - system.theta
        moved = samples if delta is None else samples.shifted(delta, outputs)
        model = template.clone().fit(moved.inputs, moved.targets, noise=moved.noise)
        posterior, samples = posterior_given(model, samples, system, delta)
    return posterior, samples


@adaptive_threads()
def fit_correction(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    *,
    gp: CorrectionGP | None = None,
    candidates=None,
    select: str = "cv",
    derivative: str = "auto",
    folds: int = 5,
    refine: bool | None = None,
    progress: bool = True,
    **estimator,
) -> CorrectionGP:
    """Learn the correction from observed states: samples, a model chosen among candidates, optionally refined.

    The package's one entry point for choosing a model. Its steps:

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
         likelihood. With fewer than 2 experiments there is nothing to hold out, and ``"evidence"`` is used;
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
       the ODE (by default it does not).

    **Partly measured states** (a component some experiment does not measure, :attr:`Trajectories.measured
    <torchmisspec.Trajectories.measured>`): the correction is learned through the ODE
    (:func:`torchmisspec.partial.fit_partly_measured`: the unmeasured starting values and a first model of F fitted
    to the measured values, the data completed with its paths, then the steps above on the completed data);
    ``result.identifiability_`` says how the measurements see each output of F (an output none sees is refused), and
    ``result.initial_states_`` holds the estimated ``(K, d)`` initial states. Neither is saved with the model. With
    uncertain parameters of G, they are learned with the first model through the ODE (their Laplace posterior, F's
    terms and the initial states marginalised) and F is chosen at their posterior mean.

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

    Returns:
        the fitted :class:`CorrectionGP` (or the refined one); ``result.cross_validation_`` holds the
        :class:`CrossValidation` (``None`` without it) and ``result.samples_`` the correction samples.
    """
    _check_trajectories_and_system(trajectories, system)
    refine = check_flag(refine, "refine", none=True)
    check_flag(progress, "progress")
    if trajectories.is_partial:  # some components not measured: learned through the ODE (partial.py)
        options = dict(gp=gp, candidates=candidates, select=select, derivative=derivative, folds=folds, refine=refine)
        return fit_partly_measured(trajectories, system, fit_correction, progress=progress, **options, **estimator)
    system0 = system
    if gp is not None and not isinstance(gp, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP template or None, got {type(gp).__name__}")
    if candidates is not None and gp is not None:
        raise InputError("candidates: expected either a gp template or a list of candidates, got both")
    if not (isinstance(select, str) and select in SELECTION):
        raise InputError(
            f"select: expected 'cv' (held-out experiments) or 'evidence' (marginal likelihood), got {select!r}"
        )
    user_candidates = candidates is not None
    if user_candidates:
        candidates = _check_candidates(candidates)
    samples = correction_samples(trajectories, system, derivative=derivative, **estimator)
    posterior = None
    if system.parameters is not None:  # theta integrated out with F (parameters.py): the choice below at its mean
        refine_f, refine, outputs = bool(refine), False, system.correction_outputs  # F's refinement after theta
        template = CorrectionGP(device=samples.inputs.device) if gp is None or gp.auto else gp
        posterior, samples = _parameter_passes(samples, system, template)
        system, samples = system.at(posterior.mean), samples.shifted(posterior.mean - system.theta, outputs)
    cv = None
    result = None
    chooser = samples.thinned(SELECTION_SAMPLES)  # the model is chosen on at most about this many samples
    if select == "cv" and trajectories.num_experiments >= 2:
        if candidates is None and gp is None:
            candidates = default_candidates(chooser)
        elif candidates is None:
            # auto: scored as it is
            free = not gp.auto and gp.kernel_spec.stationary and gp.fixed["lengthscale"] is None
            if free and not gp.per_output:
                candidates = [
                    gp.clone(kernel=gp.kernel_spec, lengthscale=ell) for ell in lengthscale_candidates(chooser, gp)
                ]
            else:
                candidates = [gp]
        cv, models = cross_validate(system, trajectories, chooser, candidates, folds=folds, progress=progress)
        result = models[cv.index] if math.isfinite(min(cv.scores)) else None
        if result is not None and chooser is not samples:  # the chosen template, fitted on every sample
            result = copy.deepcopy(candidates[cv.index]).fit(samples)
        if not cv.significant:
            warn(
                f"fit_correction: no corrected model predicts held-out experiments significantly better than the "
                f"known model alone (best held-out error {min(cv.scores):.3g} vs {cv.baseline:.3g} without a "
                f"correction, {cv.folds} folds; required: a gain of {cv.critical:.3g} standard errors over the "
                f"{len(cv.gains) or trajectories.num_experiments} experiments): the data do not support a correction. "
                "Collect more experiments, sample the states more densely or with less noise, or check the known model",
                TorchMisspecWarning,
            )
        if result is None:
            warn(
                f"fit_correction: every candidate failed cross-validation (a fit or a held-out prediction failed: "
                f"{', '.join(cv.candidates)}); chose among them by evidence instead",
                TorchMisspecWarning,
            )
    if result is None:  # select="evidence", one experiment, or every candidate failed its cross-validation
        auto = CorrectionGP(kernel="auto", device=samples.inputs.device)
        pool = candidates if user_candidates else [auto if gp is None else gp]
        result = _by_evidence(pool, chooser)
        if chooser is not samples:  # the chosen kernel (an auto model's choice), fitted on every sample
            chosen = getattr(result, "model_selection_", None)
            result = result.clone(kernel=result.kernel_spec).fit(samples)
            result.model_selection_ = chosen
    if refine is None:  # the feature kernel's terms, refined through the ODE (fit_trajectories)
        refine = result.kernel_spec.terms and result.kernel_spec.feature_space and system.autonomous
    if refine:  # a new model: the record of the evidence's choice carried over
        selection = getattr(result, "model_selection_", None)
        result = fit_trajectories(result, system, trajectories, progress=progress)
        if selection is not None:
            result.model_selection_ = selection
    if posterior is not None:  # theta's posterior under the chosen model, and F conditioned on r - H theta_bar
        delta = posterior.mean - posterior.prior_mean
        result, samples = fit_parameters(result, samples, system0, trajectories, delta)
        result.parameters_.warn_if_unidentified("fit_correction")
        if refine_f:  # F through the ODE at theta's mean, theta's posterior kept
            found = result.parameters_
            result = fit_trajectories(result, system0.at(found.mean), trajectories, progress=progress)
            result.parameters_ = found
    result.cross_validation_ = cv
    result.samples_ = samples
    result.input_names_ = system.input_names(trajectories)  # what gp.terms() calls the inputs
    return result
