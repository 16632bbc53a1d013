"""Do no harm for a population: F is kept only where it fits experiments it has not seen better than G alone.

The experiments are held out in folds (experiment k in fold ``k % folds``, :data:`FOLDS` at most, the package's
cross-validation). For each fold, F is conditioned on the other folds' samples, its hyperparameters kept
(:meth:`CorrectionGP.condition <torchmisspec.CorrectionGP.condition>`, as
:func:`~torchmisspec.learning.choice.cross_validation.cross_validate` does), and every held-out experiment's
parameters and free initial states are fitted to its own measurements through the ODE with that F (its conditional
mode under the population fitted with F, the population's values and noise scale held:
:func:`~torchmisspec.population._modes.conditional_modes`). The rival is the classical answer: each experiment's
parameters fitted to its measurements under the population fitted with F = 0. Both are scored by the misfit of every
measurement in the noise model's space over the classical fit's noise scale; F is kept when its total is lower and
significantly so over the experiments (the paired test of
:func:`~torchmisspec.learning.choice.cross_validation.significant_gain`, or every experiment better by the
variance-ratio test of :func:`~torchmisspec.learning.choice._partial_choice.better_in_every_experiment`), the rule of
the package's partly-measured do no harm.

Why experiments and not later times: F learned on the first two thirds of each experiment's times had not seen the
low concentrations of the last third, and its forecasts there were refused on every realization of the population
study where F was learned (``scripts/study_population.py``); a held-out experiment's own parameters, fitted to its
measurements, are what the package predicts it with, and they are fitted for both models alike.
"""

from __future__ import annotations

import math

import torch

from .._errors import FittingError, IntegrationError, LinearAlgebraError
from ..learning.choice._partial_choice import _gains, better_in_every_experiment
from ..learning.choice.cross_validation import significant_gain
from ..learning.refinement._known_fit import held_out
from ._modes import _paths, conditional_modes, held_prior, mean_correction

__all__ = ["best_on_unseen_experiments", "fold_gp", "FOLDS"]

#: the folds experiments are held out in (at most; one per experiment when there are fewer)
FOLDS = 5
#: what a failed fit raises
FAILURES = (FittingError, IntegrationError, LinearAlgebraError)


def _scores(layout, thetas, initial_states, correction, trajectories, noise, scale) -> torch.Tensor:
    """``(K,)`` each experiment's misfit of its measurements in ``noise``'s space over ``scale``: its path from
    ``thetas (K, k)`` and ``initial_states (K, d)``; ``inf`` where it cannot be integrated."""
    K = trajectories.num_experiments
    try:
        floor = noise.resolution(trajectories)
        pred = _paths(layout, correction, trajectories, floor)(thetas[None], initial_states[None])[0]
    except IntegrationError:
        return torch.full((K,), math.inf, dtype=torch.float64)
    values, _ = trajectories.observed_values()
    seen = held_out(trajectories, torch.zeros(K, dtype=torch.long))
    r = (noise.transform(pred) - noise.transform(values)) / scale.to(values)
    per = torch.where(seen, r, torch.zeros((), dtype=r.dtype)).pow(2).sum((1, 2))
    return torch.where(torch.isfinite(per), per, torch.full_like(per, math.inf)).cpu().to(torch.float64)


def fold_gp(fit, keep: torch.Tensor):
    """F conditioned on the samples of the experiments ``keep (K,)`` marks (hyperparameters kept); ``None`` where the
    model's training samples are not the recorded ones (then nothing can be held out)."""
    gp, samples = fit.gp, getattr(fit.gp, "samples_", None)
    X, Y = gp.train_inputs_, gp.train_targets_
    if samples is None or X is None or X.shape[0] != len(samples) or not torch.allclose(X, samples.inputs.to(X)):
        return None
    rows = keep.to(samples.experiment.device)[samples.experiment]
    noise = gp.train_noise_
    return gp.condition(X[rows], Y[rows], noise=None if noise is None else noise[rows])


def _fold_correction(fit, keep: torch.Tensor):
    """F's posterior mean conditioned on the samples of the experiments ``keep (K,)`` marks (:func:`fold_gp`);
    ``None`` where nothing can be held out."""
    fold = fold_gp(fit, keep)
    return None if fold is None else mean_correction(fit.subject_system, fold)


def _held_out_scores(fit, trajectories, scale, stop: float = math.inf) -> torch.Tensor:
    """``(K,)`` each experiment's misfit with F conditioned without its fold and its parameters fitted with it; the
    folds left once the total passes ``stop`` are not fitted (their experiments ``inf``: the rival that set
    ``stop`` is better whatever they give)."""
    nlme, K = fit.nlme, trajectories.num_experiments
    folds = min(FOLDS, K)
    out = torch.full((K,), math.inf, dtype=torch.float64)
    shared = nlme.modes.shared
    prior = held_prior(shared)
    typical = nlme.values.typical(nlme.covariates)
    for f in range(folds):
        held = torch.tensor([k for k in range(K) if k % folds == f])
        correction = _fold_correction(fit, ~torch.isin(torch.arange(K), held))
        if correction is None:
            return out
        data = trajectories[held.tolist()].with_initial_states(nlme.modes.initial_states[held])
        try:
            modes = conditional_modes(
                nlme.layout, correction, data, nlme.free[held], fit.noise, typical[held], nlme.values.spread,
                prior, scale=nlme.modes.scale,
            )  # fmt: skip
        except FAILURES:
            continue
        thetas = nlme.layout.theta(modes.eta, modes.shared)
        out[held] = _scores(nlme.layout, thetas, modes.initial_states, correction, data, fit.noise, scale)
        if float(out[torch.isfinite(out)].sum()) > stop:
            break
    return out


def best_on_unseen_experiments(fits: list, classical, trajectories) -> tuple[object, bool, float, float]:
    """``(fit, kept, misfit with F, misfit without)``: of the population ``fits`` (each a
    :class:`~torchmisspec.population.fit.PopulationFit` with a correction), the one whose F, conditioned without
    them, fits the held-out experiments best (the lowest total misfit; the first on a tie), and whether the module's
    rule keeps it against ``classical`` (its :class:`~torchmisspec.population.nlme.NLMEFit` with F = 0). The folds
    of a fit are fitted until its misfit passes the classical's or a better fit's total (then it cannot be kept, and
    its misfit is ``inf``): on nlme's Remifentanil an F that wiggles made each fold's fits take a minute."""
    scale = classical.modes.scale.nan_to_num(nan=1.0).clamp_min(torch.finfo(torch.float64).tiny)
    known = _scores(
        classical.layout, classical.thetas, classical.modes.initial_states, None, trajectories, fits[0].noise, scale
    )
    rivals = []
    for fit in fits:  # a fit whose folds so far miss by more than the classical's or the best total cannot be kept
        rivals.append(
            _held_out_scores(fit, trajectories, scale, min([float(known.sum())] + [float(r.sum()) for r in rivals]))
        )
    best = min(range(len(fits)), key=lambda i: float(rivals[i].sum()))
    rival = rivals[best]
    counts = held_out(trajectories, torch.zeros(trajectories.num_experiments, dtype=torch.long)).any(-1).sum(1)
    kept = float(rival.sum()) < float(known.sum()) and (
        significant_gain(_gains(known, rival)) or better_in_every_experiment(known, rival, counts.cpu())
    )
    return fits[best], kept, float(rival.sum()), float(known.sum())
