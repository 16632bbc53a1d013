"""The next subject's experiment: its sampling times under a budget, and its dose (initial state), chosen by the
information they bring.

Targets (what the design is for), as objects:

* :class:`SubjectParameters` (default): the subject's own varying parameters. Bayesian design averaged over the
  population (as PopED and PFIM compute it for a new subject): a criterion of the information
  ``M = I + sum_t J_t^T W_t J_t`` averaged over draws of the subject from the population, J_t the sensitivity of what
  is measured at time t (the noise model's space) to the subject's eta in units of the population's spread (the
  prior's information the identity), W_t the inverse of the population fit's residual variance near time t
  (:func:`~torchmisspec.population._misfit.misfit_scale`: the measurement noise and the model's own misfit there;
  the subject's fit weights its samples alike). The criterion is an object: :class:`ExpectedError` (default,
  A-optimality: the expected sum of the posterior variances, what the subject's parameters are known to) or
  :class:`Determinant` (D-optimality, ED as PopED names it). Times are added greedily (the log-determinant of a
  growing information matrix is submodular in the times for a fixed draw).

  **F's error.** The subject's fit holds F at its posterior mean, so wherever F is off, its samples are off too, and
  the subject's parameters absorb it. The criterion is therefore of the parameters' expected error covariance
  ``E = M^-1 + M^-1 B M^-1``, B the covariance over F's posterior draws (:data:`F_DRAWS` of them, along each drawn
  subject's path) of ``sum_t J_t^T W_t dz_t``, dz_t how a draw moves what is measured at t: a sandwich, the
  misspecified-model covariance of a least-squares estimate. Why: in issue 43's design study, where a correction
  was kept, the design without it chose the late hours, where F (learned from few low concentrations) is least
  known; with the true F those times gave 0.65x the standard schedule's error, with the fitted F 1.27x. Without a
  correction (F = 0 kept) B = 0.

  Why the expected error by default: the determinant rewards volume. On one realization of issue 43's design study
  (seed 43509), its four times pinned the depot's absorption rate to a hundredth of its spread (a depot measured
  late shows its rate best) and left the volume at half its spread; the standard schedule's first four times left
  a fifth. The study's numbers are in ``docs/studies/population-design.md``.
* :class:`Correction`: the information the subject's samples bring about F, conditioned on the population's data
  (:func:`~torchmisspec.design.sampling_times` on the subject's path at its typical parameters).

Each candidate initial state (a dose level) is designed in turn and the best kept; the design's score and every
candidate's are returned with the times.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch

from .._errors import InputError, TorchMisspecWarning
from .._validation import check_positive_int
from ..data import Trajectories
from ._f_uncertainty import transformed_deviations
from ._misfit import misfit_scale
from ._modes import _paths
from ._subjects import drawn_controls
from .model import covariate_matrix
from .predict import _on

__all__ = ["Correction", "Determinant", "ExpectedError", "SubjectDesign", "SubjectParameters", "design_subject"]

#: eta's finite-difference step for the sensitivities
STEP = 1e-5
#: posterior draws of F whose spread along each drawn subject's path enters the expected error (the module's notes)
F_DRAWS = 16


class Determinant:
    """D-optimality: the expected ``-log det`` of the subject's parameters' error covariance E (in units of the
    spread; its score: half of it, the expected information gain in nats where E is the posterior's). It rewards the
    volume of the parameters' uncertainty: a parameter already pinned down gains as much from more samples as one
    still uncertain."""

    def __call__(self, E: torch.Tensor) -> torch.Tensor:
        return -torch.linalg.slogdet(E).logabsdet

    def score(self, E: torch.Tensor) -> float:
        return 0.5 * float(self(E).mean())

    def describe(self, score: float) -> str:
        return f"expected information about its parameters {score:.3g} nats"

    def __repr__(self) -> str:
        return "Determinant()"


class ExpectedError:
    """A-optimality (default): the expected sum of the parameters' squared errors, each in units of its population
    spread: the trace of their error covariance E (its score: the fraction of the prior's variance removed). What the
    subject's parameters are known to after the samples: the samples go to the parameter known least."""

    def __call__(self, E: torch.Tensor) -> torch.Tensor:
        return -E.diagonal(dim1=-2, dim2=-1).sum(-1)

    def score(self, E: torch.Tensor) -> float:
        return 1.0 + float(self(E).mean()) / E.shape[-1]

    def describe(self, score: float) -> str:
        return (
            f"expected to remove {score:.0%} of the variance its parameters have before any sample (the population's "
            "spread), averaged over subjects drawn from the population"
        )

    def __repr__(self) -> str:
        return "ExpectedError()"


class SubjectParameters:
    """Design for the subject's own varying parameters (the module's notes); ``draws`` population draws, the
    ``criterion`` :class:`ExpectedError` (default) or :class:`Determinant`.

    Why 64 draws by default: the criterion is an average over them, and near ties between sets of times are decided
    by its sampling error. On theophylline's 12th subject, 10 seeds gave 4 different designs at 16 draws, 4 at 64 (6
    of 10 the same) and 2 at 256 (5 h against 7 h), at 0.18, 0.22 and 0.45 s per design."""

    def __init__(self, draws: int = 64, criterion=None) -> None:
        self.draws = check_positive_int(draws, "draws")
        criterion = ExpectedError() if criterion is None else criterion
        if not isinstance(criterion, (ExpectedError, Determinant)):
            raise InputError(f"criterion: expected ExpectedError() or Determinant(), got {criterion!r:.80}")
        self.criterion = criterion

    def describe(self, score: float) -> str:
        """What ``score`` means, in words (the criterion's)."""
        return self.criterion.describe(score)

    def __repr__(self) -> str:
        return f"SubjectParameters(draws={self.draws}, criterion={self.criterion!r})"


class Correction:
    """Design for F: the information about F of the subject's samples (the module's notes)."""

    def describe(self, score: float) -> str:
        """What ``score`` means, in words."""
        return f"expected information about F {score:.3g} nats"

    def __repr__(self) -> str:
        return "Correction()"


@dataclass(frozen=True)
class SubjectDesign:
    """A new subject's design (:func:`design_subject`): its sampling ``times`` (increasing), its ``initial_state``
    (the chosen candidate), the design's ``score`` (the target's criterion: the fraction of the parameters'
    variance removed, or nats), every candidate initial state's ``scores``, and ``description``: the score in
    words."""

    times: torch.Tensor
    initial_state: torch.Tensor
    score: float
    scores: torch.Tensor
    description: str = ""


def _subject_profile(system, controls):
    """The subject's input profile, checked: one for a system with inputs, none for one without."""
    from ..signals import Controls

    if not system.num_controls:
        if controls is not None:
            raise InputError(f"controls: expected None for system '{system.name}' (it takes no inputs u(t)), got one")
        return None
    if not isinstance(controls, Controls) or controls.num_experiments != 1:
        got = type(controls).__name__ if not isinstance(controls, Controls) else f"{controls.num_experiments} profiles"
        raise InputError(
            f"controls: expected the subject's input profile, a torchmisspec.Controls of one experiment with "
            f"{list(system.control_names)} (system '{system.name}' takes inputs u(t)), got {got}"
        )
    return controls


def _sensitivities(fit, y0: torch.Tensor, times: torch.Tensor, eta: torch.Tensor, controls=None) -> torch.Tensor:
    """``(S, T, o, k_v)``: d(transformed outputs at ``times``)/d(eta) for S draws ``eta (S, k_v)`` from ``y0 (d,)``
    under the subject's input profile ``controls`` (or ``None``) by forward differences, one batched solve."""
    nlme, layout = fit.nlme, fit.nlme.layout
    S, kv = eta.shape
    d = y0.shape[-1]
    dummy = _outline(fit, times, y0, S, controls)
    steps = torch.cat([torch.zeros(1, kv, dtype=eta.dtype), STEP * torch.eye(kv, dtype=eta.dtype)])  # (1 + kv, kv)
    etas = eta[None] + steps[:, None]  # (1 + kv, S, kv)
    theta = layout.theta(etas, nlme.modes.shared)
    correction = fit.mean_correction
    floor = None if fit.data is None else fit.noise.resolution(fit.data)  # the depths the population was measured to
    pred = _paths(layout, correction, dummy, floor)(theta, y0.expand(1 + kv, S, d))  # (1 + kv, S, T, o)
    z = fit.noise.transform(pred)
    return ((z[1:] - z[:1]) / STEP).permute(1, 2, 3, 0)


def _outline(fit, times: torch.Tensor, y0: torch.Tensor, S: int, controls=None) -> Trajectories:
    """``S`` experiments from ``y0 (d,)`` at ``times``, every state measured, each under ``controls`` (one profile,
    or ``None``): only their layout counts (what is read of a path, :meth:`~torchmisspec.Trajectories.observe`)."""
    states = torch.zeros(S, times.shape[0], y0.shape[-1], dtype=torch.float64)
    states[:, 0] = y0
    every = None if controls is None else controls.repeat(S)
    return Trajectories(times, states, state_names=fit.system.state_names, controls=every)


def _greedy_parameters(J: torch.Tensor, weights: torch.Tensor, criterion, budget: int, allowed, deviations=None):
    """Greedy times for the expected ``criterion`` of the parameters' error covariance in units of the spread (``J``
    the sensitivities to those units, the prior the identity; the module's notes), ``weights`` ``(o,)`` or
    ``(T, o)``, ``deviations`` ``(S, F, T, o)`` F's draws' deviations of what is measured (``None``: F exact):
    ``(indices, score)``."""
    S, T, o, kv = J.shape
    weights = weights.expand(T, o)
    per_time = torch.einsum("stoa,to,stob->stab", J, weights, J)  # (S, T, kv, kv)
    M = torch.eye(kv, dtype=J.dtype, device=J.device).expand(S, kv, kv).clone()
    pull = None if deviations is None else torch.einsum("stoa,to,sfto->sfta", J, weights, deviations)  # (S, F, T, kv)
    lean = None if pull is None else pull.new_zeros(S, pull.shape[1], kv)  # what F's error has pushed so far
    chosen: list[int] = []
    for _ in range(budget):
        trial = M[:, None] + per_time  # (S, T, kv, kv)
        E = torch.linalg.inv(trial)
        if pull is not None:  # the sandwich: E + E B E, B the covariance of F's push on the normal equations
            push = lean[:, :, None] + pull  # (S, F, T, kv)
            B = torch.einsum("sfta,sftb->stab", push, push) / push.shape[1]
            E = E + E @ B @ E
        value = criterion(E).mean(0)
        value[~allowed] = -math.inf
        if chosen:
            value[torch.tensor(chosen)] = -math.inf
        best = int(value.argmax())
        chosen.append(best)
        M, error = trial[:, best], E[:, best]
        lean = None if pull is None else push[:, :, best]
    return sorted(chosen), criterion.score(error)


def design_subject(
    fit, times, budget: int, *, initial_states, covariates=None, target=None, controls=None,
    generator: torch.Generator | None = None,
) -> SubjectDesign:  # fmt: skip
    """Choose a new subject's ``budget`` sampling times among the candidate ``times (T,)`` (the first is the time of
    its initial state, never a sample) and its initial state among ``initial_states (C, d)`` (dose levels), under the
    population ``fit`` (:class:`~torchmisspec.population.fit.PopulationFit`), for the ``target`` (default
    :class:`SubjectParameters`); ``covariates`` the subject's (``{name: value}``); ``controls`` its input profile
    (a :class:`~torchmisspec.Controls` of one experiment) for a system with inputs u(t)."""
    target = SubjectParameters() if target is None else target
    if not isinstance(target, (SubjectParameters, Correction)):
        raise InputError(f"target: expected SubjectParameters() or Correction(), got {target!r:.80}")
    grid = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    budget = check_positive_int(budget, "budget")
    if budget > grid.numel() - 1:
        raise InputError(
            f"budget: expected at most the {grid.numel() - 1} candidate times after the first (the initial state's), "
            f"got {budget}; pass more candidate times"
        )
    starts = torch.as_tensor(initial_states, dtype=torch.float64)
    starts = starts[None] if starts.dim() == 1 else starts
    X = covariate_matrix(fit.population, covariates, 1)
    controls = _subject_profile(fit.system, controls)
    designs = [_one(fit, grid, budget, y0, X, target, generator, controls) for y0 in starts]
    scores = torch.tensor([s for _, s in designs], dtype=torch.float64)
    best = int(scores.argmax())
    score = float(scores[best])
    return SubjectDesign(grid[designs[best][0]], starts[best], score, scores, target.describe(score))


def _one(fit, grid, budget, y0, X, target, generator, controls):
    """``(indices, score)`` of the best times from ``y0`` for ``target``."""
    nlme = fit.nlme
    typical, spread = nlme.values.typical(X)[0], nlme.values.spread  # as the subject's fit (predict's notes)
    if isinstance(target, Correction):
        return _for_correction(fit, grid, budget, y0, typical, controls)
    eta = typical + spread * torch.randn(target.draws, spread.shape[0], dtype=spread.dtype, generator=generator)
    J = _sensitivities(fit, y0, grid, eta, controls) * spread  # per unit of the spread
    scale = misfit_scale(fit, grid)
    weights = torch.where(torch.isfinite(scale), 1 / scale.pow(2), torch.zeros_like(scale))
    allowed = torch.arange(grid.numel()) > 0
    deviations = _correction_deviations(fit, y0, grid, eta, generator, controls)
    return _greedy_parameters(J, weights, target.criterion, budget, allowed, deviations)


def _correction_deviations(fit, y0: torch.Tensor, grid: torch.Tensor, eta: torch.Tensor, generator, controls=None):
    """``(S, F, T, o)``: how :data:`F_DRAWS` posterior draws of F move what is measured of each drawn subject
    ``eta (S, k_v)`` from F's mean, in the noise model's space to first order (``None`` without a correction). The
    subject's fit holds F at its mean, so these are errors its parameters absorb (the module's notes). A draw whose
    path left the region (NaN there) counts as 0: it understates F's error for those rare draws."""
    if fit.known_model:
        return None
    S, d = eta.shape[0], y0.shape[-1]
    drawn = drawn_controls(fit.system, fit.nlme.layout, eta, fit.nlme.modes.shared, grid[:1], controls)
    with warnings.catch_warnings():  # the draws' own notes (support, calibration) are not the design's to say
        warnings.simplefilter("ignore", TorchMisspecWarning)
        post = fit.corrected.posterior(
            y0.expand(S, d), grid, num_samples=F_DRAWS, controls=drawn, generator=_on(generator),
            scale=1.0,
        )  # fmt: skip
    paths = _outline(fit, grid, y0, S, controls).observe(post.samples.to(torch.float64)).transpose(0, 1)  # (S, F, T, o)
    return transformed_deviations(fit.noise, paths, 1)


def _for_correction(fit, grid, budget, y0, typical, controls):
    """The times that teach most about F along the subject's path at its typical parameters."""
    from ..design import sampling_times

    if fit.known_model:
        raise InputError(
            "target: Correction() designs for F, but the population's fit kept F = 0 (no correction to learn more "
            "about); design for SubjectParameters() instead"
        )
    drawn = drawn_controls(fit.system, fit.nlme.layout, typical[None], fit.nlme.modes.shared, grid[:1], controls)
    chosen = sampling_times(
        y0[None], grid, budget, system=fit.subject_system, gp=fit.gp, controls=drawn, skip_first=True
    )  # its start is known: never a sample
    return chosen.indices[0].tolist(), float(chosen.design.information_gain)
