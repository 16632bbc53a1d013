"""How well the population's values are known: their standard errors and confidence intervals.

**Standard errors** come from the Fisher information of the linearised marginal model: experiment i's mode
estimates its eta_i with a data-only variance tau_i^2 (1 / C_i = 1 / tau_i^2 + 1 / omega^2, C_i its Laplace
variance), so that the modes' marginal variance is omega^2 + tau_i^2; then Cov(beta) = (X^T W X)^-1,
W = diag(1 / (omega^2 + tau_i^2)), and Var(omega^2) = 2 / (sum_i W_i^2 (K - p) / K), p the parameter's fixed effects
(REML's count, as the fit's spread; :mod:`~torchmisspec.population.nlme`), SE(omega) = SE(omega^2) / (2 omega).

**F's uncertainty.** Where the population is fitted with a correction, F is held at its posterior mean, and its
error moves every experiment's parameters alike. The covariance of the population's values over F's posterior draws
(:mod:`~torchmisspec.population._f_uncertainty`, ``shifts``) is added to Cov(beta): the typical values' and the
covariates' effects' standard errors and intervals, and a new experiment's prior, count it. The spread's is left as
the information's (why: that module's notes).

**Intervals** (:func:`intervals`) have the shapes of the exact ones where every experiment's eta is known:

* a typical value or a covariate's effect: beta +- t SE, Student's t with K - p degrees of freedom (the one-sample t
  interval where the experiments are known exactly);
* a spread: omega^2 as a scaled chi-square with Satterthwaite's degrees of freedom nu = 2 omega^4 / Var(omega^2)
  (K - p where the experiments are known exactly: the textbook interval of a normal sample's variance).

**A new experiment's prior** (:func:`new_subject_prior`): its eta is drawn from the population, whose values are
themselves estimates. With the typical value known to its standard error and omega^2 a scaled chi-square with nu
degrees of freedom (above), the predictive distribution of a new eta is Student's t with nu degrees of freedom,
scale sqrt(omega^2 + SE^2), SE the typical value's standard error at the new experiment's covariates; the package
takes the normal with the same central 95 % interval (a Laplace posterior,
:func:`~torchmisspec.population.predict.subject_parameters`, needs a normal prior): spread
q sqrt(omega^2 + SE^2), q = t_nu(0.975) / z(0.975). Where the experiments are known exactly that interval is the
textbook prediction interval of a new observation (a normal sample's, or a regression's at the covariates). A
population of few subjects knows its spread poorly: from 4 trees (nu about 3) q is 1.6, from 12 subjects about 1.1,
from many 1. A new subject predicted from the population alone takes this prior; the fit to its first measurements
keeps the point estimates (why: :mod:`~torchmisspec.population.predict`).

Why not omega +- 2 SE: a spread's sampling distribution is skewed. At 12 subjects, a sample whose spread comes out
at 70 % of the truth has a Wald interval that stops short of the truth, while the chi-square interval reaches it;
issue 43's population study counts both (``docs/studies/population.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .._errors import InputError

__all__ = ["Intervals", "fixed_effects", "intervals", "new_subject_prior", "standard_errors"]

#: the central interval a new experiment's normal prior matches of its Student's t (:func:`new_subject_prior`)
MATCHED = 0.95


@dataclass(frozen=True)
class Intervals:
    """Confidence intervals at ``level``, in eta's coordinates: ``mean (k_v, 2)`` the typical values', ``spread
    (k_v, 2)`` the spreads', ``effects (k_v, c, 2)`` the covariates' effects' (NaN where an effect is not estimated);
    the last axis is (lower, upper)."""

    level: float
    mean: torch.Tensor
    spread: torch.Tensor
    effects: torch.Tensor


def fixed_effects(values, X: torch.Tensor, j: int) -> torch.Tensor:
    """``(K, p)``: the intercept and the centred covariates acting on parameter ``j``."""
    Xc = X - values.centre
    return torch.cat([torch.ones(X.shape[0], 1, dtype=X.dtype), Xc[:, values.acts[j]]], -1)


def _weights(values, modes, j: int) -> torch.Tensor:
    """``(K,)`` W_i = 1 / (omega^2 + tau_i^2) of parameter ``j`` (the module's notes; 0 for an experiment its data do
    not inform)."""
    w2 = values.spread[j] ** 2
    var = modes.covariance[:, j, j]
    informed = var < w2 * (1 - 1e-9)
    tau2 = torch.where(informed, var * w2 / (w2 - var), torch.full_like(var, math.inf))
    return 1 / (w2 + tau2)


def _spread_variance(values, modes, j: int, K: int, p: int) -> float:
    """Var(omega_j^2): the inverse of its information, sum_i W_i^2 / 2 times REML's (K - p) / K; inf where
    uninformed."""
    info = 0.5 * float(_weights(values, modes, j).pow(2).sum()) * max(K - p, 1) / K
    return 1 / info if info > 0 else math.inf


def _dof(values, variance: float, j: int) -> float:
    """Satterthwaite's degrees of freedom of omega_j^2: 2 omega^4 / Var(omega^2) (0 where uninformed)."""
    return 2 * float(values.spread[j]) ** 4 / variance if math.isfinite(variance) else 0.0


def _fixed_covariance(values, modes, X: torch.Tensor, j: int, shifts=None) -> torch.Tensor | None:
    """``(p, p)`` Cov of parameter ``j``'s intercept and covariate effects, ``(X^T W X)^-1`` plus F's part
    (``shifts``; the module's notes); ``None`` where singular."""
    D = fixed_effects(values, X, j)
    try:
        cov = torch.linalg.inv(D.T @ (_weights(values, modes, j)[:, None] * D))
    except torch.linalg.LinAlgError:
        return None
    return cov if shifts is None else cov + shifts.fixed_covariance(j).to(cov)


def standard_errors(values, modes, X: torch.Tensor, shifts=None) -> tuple:
    """``(mean (k_v,), spread (k_v,), effects (k_v, c))`` standard errors (the module's notes), F's uncertainty
    counted where ``shifts`` are given."""
    K, kv = modes.eta.shape
    se_mean, se_spread = torch.empty(kv, dtype=X.dtype), torch.empty(kv, dtype=X.dtype)
    se_effects = torch.zeros_like(values.effects)
    for j in range(kv):
        D = fixed_effects(values, X, j)
        cov = _fixed_covariance(values, modes, X, j, shifts)
        if cov is None:
            se_mean[j] = math.inf
        else:
            se_mean[j], se_effects[j, values.acts[j]] = cov.diagonal()[0].sqrt(), cov.diagonal()[1:].sqrt()
        variance = _spread_variance(values, modes, j, K, D.shape[-1])
        se_spread[j] = math.sqrt(variance) / (2 * float(values.spread[j]))
    return se_mean, se_spread, se_effects


def new_subject_prior(values, modes, X: torch.Tensor, x: torch.Tensor, shifts=None) -> tuple:
    """``(typical (1, k_v), spread (k_v,))``: a new experiment's normal prior in eta given its covariates ``x (1,
    c)``, the population's ``values`` fitted with the experiments' ``modes`` and covariates ``X (K, c)``: the
    typical value's standard error and the spread's degrees of freedom folded in (the module's notes)."""
    from scipy import stats

    K, kv = modes.eta.shape
    spread = torch.empty(kv, dtype=X.dtype)
    for j in range(kv):
        p = 1 + int(values.acts[j].sum())
        w2 = float(values.spread[j]) ** 2
        cov = _fixed_covariance(values, modes, X, j, shifts)
        d = fixed_effects(values, x, j)[0]
        known = 0.0 if cov is None else float(d @ cov @ d)  # the typical value's variance at x
        nu = _dof(values, _spread_variance(values, modes, j, K, p), j)
        q = float(stats.t.ppf(0.5 + MATCHED / 2, nu) / stats.norm.ppf(0.5 + MATCHED / 2)) if nu > 0 else 1.0
        spread[j] = q * math.sqrt(w2 + known)
    return values.typical(x), spread


def intervals(values, modes, X: torch.Tensor, level: float = 0.95, shifts=None) -> Intervals:
    """:class:`Intervals` of the population's ``values`` fitted with the experiments' ``modes`` and covariates
    ``X (K, c)`` at ``level`` (the module's notes), F's uncertainty counted where ``shifts`` are given."""
    if isinstance(level, bool) or not isinstance(level, float | int) or not 0 < level < 1:
        raise InputError(f"level: expected a confidence level strictly between 0 and 1 (0.95), got {level!r:.40}")
    from scipy import stats

    K, kv = modes.eta.shape
    tail = (1 - float(level)) / 2
    se_mean, _, se_effects = standard_errors(values, modes, X, shifts)
    mean = torch.empty(kv, 2, dtype=X.dtype)
    spread = torch.empty(kv, 2, dtype=X.dtype)
    effects = torch.full((*values.effects.shape, 2), math.nan, dtype=X.dtype)
    for j in range(kv):
        p = 1 + int(values.acts[j].sum())
        t = float(stats.t.ppf(1 - tail, max(K - p, 1)))
        mean[j] = values.mean[j] + t * se_mean[j] * torch.tensor([-1.0, 1.0], dtype=X.dtype)
        acts = values.acts[j]
        effects[j, acts] = values.effects[j, acts, None] + t * se_effects[j, acts, None] * torch.tensor([-1.0, 1.0])
        w2 = float(values.spread[j]) ** 2
        nu = _dof(values, _spread_variance(values, modes, j, K, p), j)
        if nu > 0:
            chi = stats.chi2.ppf([1 - tail, tail], nu)
            spread[j] = torch.tensor(nu * w2 / chi, dtype=X.dtype).sqrt()
        else:
            spread[j] = torch.tensor([0.0, math.inf], dtype=X.dtype)
    return Intervals(float(level), mean, spread, effects)
