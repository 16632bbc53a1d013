"""Cross-validation on trajectories: candidate correction models scored by how well the corrected model predicts
held-out experiments (:func:`cross_validate`, the rule :func:`~torchmisspec.fit_correction` chooses by).

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
experiment, on log error ratios), :func:`~torchmisspec.fit_correction` warns that the data do not support a
correction. To keep the cost at one marginal-likelihood fit per candidate, each candidate's output scale and noise
are fitted once on the samples and the folds only re-condition it; ``fit_correction`` scores the candidates on at
most about ``SELECTION_SAMPLES`` samples (:data:`torchmisspec.learning.fit.SELECTION_SAMPLES`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass

import torch

from ..._errors import FittingError, InputError, IntegrationError, LinearAlgebraError, NumericalWarning
from ..._ode import FITTING_TOLERANCES, solve, widened_box
from ..._validation import check_positive_int, progress_bar
from ...data import Trajectories, simulate_known_each
from ...gp import CorrectionGP
from ...gp._paths import detached, kernel_hyperparameters, kernel_matrix
from ...parallel import adaptive_threads
from ...systems import MisspecifiedSystem
from ..samples.observations import CorrectionSamples, _check_trajectories_and_system

__all__ = ["SIGNIFICANCE", "CrossValidation", "cross_validate", "student_t_quantile"]

#: Solver steps allowed for one held-out prediction (a candidate whose prediction blows up scores infinity).
_CV_MAX_STEPS = 2000
#: A held-out prediction that leaves the box of the experiments' states widened this many times its width on each
#: side is stopped there and scores infinity from then on (:func:`~torchmisspec._ode.widened_box`; the posterior's
#: draws stop at the same distance): on the lynx data 9 of 14 candidates' predictions blew up, each integrated until
#: the solver stalled (0.4 s each)
HELD_OUT_WIDTHS = 10.0


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
        known_fitted: with uncertain parameters of G, the known model's score with its *own* parameters fitted
            (F = 0, on every experiment: the classical answer, do no harm's rival); ``baseline`` is the known model
            at the parameters fitted with the correction. ``None`` otherwise.
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
    known_fitted: float | None = None

    def in_units(self, scale: float | None) -> CrossValidation:
        """The record with its lengthscales (and the labels that name them) multiplied by ``scale``, the inputs'
        one scale (:mod:`torchmisspec.learning._units`: the candidates were compared in the data's units); with
        ``None`` (inputs of different scales) the labels say that their lengthscales are in the data's units. The
        scores stay where they were compared."""
        if all(ell is None for ell in self.lengthscales):
            return self
        if scale is None:
            relabel = [c if ell is None else f"{c} (in the data's units)" for c, ell in zip(self.candidates,
                       self.lengthscales, strict=True)]  # fmt: skip
            return dataclasses.replace(self, candidates=tuple(relabel), best=relabel[self.index])
        ells = tuple(None if ell is None else ell * scale for ell in self.lengthscales)
        labels = tuple(
            c if ell is None else c.replace(f"lengthscale={old:.4g}", f"lengthscale={ell:.4g}")
            for c, ell, old in zip(self.candidates, ells, self.lengthscales, strict=True)
        )
        return dataclasses.replace(self, candidates=labels, lengthscales=ells, best=labels[self.index])

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
        return self.improves and significant_gain(self.gains)

    @property
    def critical(self) -> float:
        """The number of standard errors :attr:`significant` asks for: the :data:`SIGNIFICANCE` quantile of Student's
        t with n - 1 degrees of freedom (2.78 for 5 experiments, 2.26 for 10, 1.96 for many)."""
        return student_t_quantile(SIGNIFICANCE, max(len(self.gains) - 1, 1))


#: Standard errors by which the cross-validated correction must beat the known model for :func:`fit_correction`
#: not to warn.
SIGNIFICANCE = 0.975


def significant_gain(gains) -> bool:
    """Whether per-experiment gains (``log`` of the known model's error over a rival's, one per held-out
    experiment) show the rival better: their mean above the :data:`SIGNIFICANCE` quantile of Student's t with
    n - 1 degrees of freedom times its standard error (a one-sided paired test); an infinite gain (the known model
    cannot be integrated where the rival can) is significant by itself, fewer than 2 finite gains never are."""
    gains = list(gains)
    if any(g == math.inf for g in gains):
        return True
    n = len(gains)
    if n < 2 or not all(math.isfinite(g) for g in gains):
        return False
    mean = sum(gains) / n
    var = sum((g - mean) ** 2 for g in gains) / (n - 1)
    return mean > student_t_quantile(SIGNIFICANCE, n - 1) * math.sqrt(var / n)


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


def _held_out_errors(system: MisspecifiedSystem, trajectories: Trajectories, field=None, noise=None) -> torch.Tensor:
    """``(K,)`` sums of squared :func:`predicted_residuals` (0 where not observed; ``inf`` where G alone cannot be
    integrated over an experiment)."""
    r = predicted_residuals(system, trajectories, field, noise)
    if r is None:  # G alone diverges: each experiment alone
        rtol, atol = FITTING_TOLERANCES
        each = simulate_known_each(system, trajectories, rtol=rtol, atol=atol)
        out = torch.empty(trajectories.num_experiments, dtype=torch.float64)
        for k, ((_, y), pred) in enumerate(zip(trajectories.experiments(), each, strict=True)):
            out[k] = math.inf if pred is None else float(_residuals(noise, y, pred).nan_to_num(nan=0.0).pow(2).sum())
        return out
    return r.nan_to_num(nan=0.0).pow(2).sum((-1, -2)).detach().cpu().to(torch.float64)


def predicted_residuals(system: MisspecifiedSystem, trajectories: Trajectories, field=None, noise=None):
    """``(K, T, d)`` residuals of a model's prediction from each experiment's first observed state over its own times
    (those of the :class:`~torchmisspec.noise.NoiseModel` ``noise``, default the differences; NaN where a state was
    not observed or an experiment has ended; ``None`` when G alone cannot be integrated over them together).

    ``field(y, rows, t, u)``: the right-hand side for states ``y (B, d)`` of the experiments ``rows`` (each
    experiment may have its own model: the folds of the cross-validation), at times ``t`` and controls ``u`` (``None``
    for an autonomous system); ``None``: the known model G alone. One batched solve of every experiment (ragged ones
    on their own times, padded at their end), each under its own controls; with ``field``, a path that leaves the box
    of the measured states widened :data:`HELD_OUT_WIDTHS` times is stopped there, its residuals infinite from
    then on."""
    rtol, atol = FITTING_TOLERANCES
    times, states, mask = trajectories.padded()
    first = trajectories.initial_conditions  # missing first entries estimated (Trajectories.filled)
    if times.dim() == 1:
        times = times.expand(states.shape[0], -1)
    controls = trajectories.controls
    floor = None if noise is None else noise.resolution(trajectories)
    if field is None:
        known, timed, jumps = system.solver_field(system.known_rhs, controls)
        try:
            pred = solve(
                known, first, times, rtol=rtol, atol=atol, what="the known model", timed=timed, jumps=jumps, floor=floor
            )[0]
        except IntegrationError:  # the known model alone diverges from some of these states (what F may fix)
            return None
    else:
        rows = torch.arange(states.shape[0], device=states.device)
        model, timed, jumps = system.solver_field(lambda y, t, u: field(y, rows, t, u), controls)
        box = widened_box(_measured_points(states, mask), HELD_OUT_WIDTHS)
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
            box=box,
            partial=True,
            floor=floor,
        )
        left = ((pred < box[0]) | (pred > box[1])).any(-1, keepdim=True).cummax(1).values  # from where it left
        pred = torch.where(left, torch.full_like(pred, math.inf), pred)
    r = _residuals(noise, states, pred)
    return torch.where(mask.unsqueeze(-1), r, torch.full_like(r, math.nan))  # missing entries: not compared


def _measured_points(states: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``(K T, d)``: the padded ``states (K, T, d)`` where measured (``mask (K, T)`` their rows), NaN elsewhere and
    in every component no experiment measures after its first row (a state given only at the start, or estimated
    there, says nothing about how far its path may go: its box is unbounded)."""
    later = torch.isfinite(states[:, 1:]) & mask[:, 1:].unsqueeze(-1)
    kept = mask.unsqueeze(-1) & later.any(1).any(0)
    return torch.where(kept, states, torch.full_like(states, math.nan)).reshape(-1, states.shape[-1])


def _residuals(noise, observed: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
    """The residuals of ``noise`` (a NaN observation stays NaN; a non-finite prediction gives an infinite one)."""
    r = predicted - observed if noise is None else noise.residuals(observed, predicted)
    return torch.where(torch.isnan(observed) | torch.isfinite(r), r, torch.full_like(r, math.inf))


def _check_candidates(candidates) -> list:
    """The candidate templates as a list, or an error naming what was received."""
    if isinstance(candidates, (str, CorrectionGP)) or not isinstance(candidates, Iterable):
        raise InputError(
            f"candidates: expected a non-empty list of CorrectionGP templates, got {candidates!r:.60} "
            f"({type(candidates).__name__})"
        )
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
    noise=None,
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
        noise: the :class:`~torchmisspec.noise.NoiseModel` whose residuals are scored (default: the differences).

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
                    kept_noise = None if samples.noise is None else samples.noise[keep]
                    fold_gp = full.condition(samples.inputs[keep], samples.targets[keep], noise=kept_noise)
                    alphas[f, keep] = fold_gp.posterior().weights  # (N_f, d_out)
                field = _fold_field(system, full, alphas, folds_t)
                errors = _held_out_errors(system, trajectories, field, noise)
        except (IntegrationError, FittingError, LinearAlgebraError):
            errors.fill_(math.inf)
        scores.append(float(errors.sum()))
        per_experiment.append(errors)
        models.append(full)
    bar.close()
    base = _held_out_errors(system, trajectories, noise=noise)
    i = min(range(len(scores)), key=scores.__getitem__)
    tiny = torch.finfo(torch.float64).tiny
    ratio = base.clamp_min(tiny) / per_experiment[i].clamp_min(tiny)
    gains = tuple(ratio.log().tolist()) if math.isfinite(scores[i]) else ()
    labels = tuple(_label(c) for c in candidates)
    ells = tuple(c.fixed["lengthscale"] if c.kernel_spec.stationary else None for c in candidates)
    n = samples.inputs.shape[0]
    result = CrossValidation(labels, ells, tuple(scores), float(base.sum()), labels[i], folds, gains, i, n)
    return result, models
