"""Do no harm for a population: F is kept only where the population fitted with it forecasts later times better.

The F step's own check (:func:`~torchmisspec.fit_correction`'s) compares F with the known model at every
experiment's parameters as they were fitted to *all* its times, so its held-out experiments are not held out from
those parameters. Here both population models are fitted again on the first two thirds of each experiment's times
(:func:`~torchmisspec.learning.refinement._known_fit.time_split`): the classical one (F = 0) and the one with F, the
whole procedure of :func:`~torchmisspec.population.fit.fit_population`. Each experiment's later third is forecast
with its own parameters from each fit; F is kept when its forecasts are better on the whole and significantly so over
the experiments (the paired test of :func:`~torchmisspec.learning.choice.cross_validation.significant_gain`, or every
experiment better by the variance-ratio test of
:func:`~torchmisspec.learning.choice._partial_choice.better_in_every_experiment`), the rule of the package's
partly-measured do no harm.
"""

from __future__ import annotations

import math

import torch

from .._errors import FittingError, IntegrationError, LinearAlgebraError
from ..learning.choice._partial_choice import _gains, better_in_every_experiment
from ..learning.choice.cross_validation import significant_gain
from ..learning.refinement._known_fit import held_out
from ._modes import _paths

__all__ = ["forecasts_better"]


def _scores(nlme, correction, trajectories, keep, noise, scale) -> torch.Tensor:
    """``(K,)`` each experiment's misfit of its later times (past ``keep``) in ``noise``'s space over ``scale``:
    its path from ``nlme``'s parameters and initial states over every time; ``inf`` where it cannot be integrated."""
    K = trajectories.num_experiments
    try:
        pred = _paths(nlme.layout, correction, trajectories)(nlme.thetas[None], nlme.modes.initial_states[None])[0]
    except IntegrationError:
        return torch.full((K,), math.inf, dtype=torch.float64)
    values, _ = trajectories.observed_values()
    held = held_out(trajectories, keep)
    r = (noise.transform(pred) - noise.transform(values)) / scale.to(values)
    per = torch.where(held, r, torch.zeros((), dtype=r.dtype)).pow(2).sum((1, 2))
    return torch.where(torch.isfinite(per), per, torch.full_like(per, math.inf)).cpu().to(torch.float64)


def forecasts_better(fit_early, classical_early, trajectories, keep, noise) -> tuple[bool, float, float]:
    """``(kept, misfit with F, misfit without)``: the module's rule, ``fit_early`` / ``classical_early`` the two
    population fits on the earlier times (``fit_early`` ``None`` where it failed)."""
    scale = classical_early.modes.scale.nan_to_num(nan=1.0).clamp_min(torch.finfo(torch.float64).tiny)
    known = _scores(classical_early, None, trajectories, keep, noise, scale)
    if fit_early is None or fit_early.known_model:
        return False, math.inf, float(known.sum())
    rival = _scores(fit_early.nlme, fit_early.mean_correction, trajectories, keep, noise, scale)
    counts = held_out(trajectories, keep).any(-1).sum(1).cpu()
    better = float(rival.sum()) < float(known.sum()) and (
        significant_gain(_gains(known, rival)) or better_in_every_experiment(known, rival, counts)
    )
    return better, float(rival.sum()), float(known.sum())


#: what a failed fit on the earlier times raises
FAILURES = (FittingError, IntegrationError, LinearAlgebraError)
