"""The population model: which of G's parameters vary between experiments, how, and with which covariates.

:class:`Population` is the declaration (a scientist's words: ``Population(["ka", "ke", "V"])``, log-normal by
default, ``covariates={"V": ["weight"]}`` for a volume that grows with body weight). :class:`PopulationValues` holds
the population's fitted values: for varying parameter j, in the coordinate eta where it is Gaussian
(:mod:`~torchmisspec.population.distributions`),

    eta_ij = mu_j + sum_c beta_jc (x_ic - centre_c) + omega_j z_ij,      z_ij ~ N(0, 1) independent,

x_ic experiment i's covariate c, centred (:func:`covariate_centre`): a covariate that takes only the values 0 and 1 (a
group: a diet, a formulation, coded against a reference) at 0, the reference group; any other at the fitted
experiments' mean. mu_j is then the typical value of the reference group at the average of the other covariates
(centring a 0/1 covariate at its mean gave the typical value of a group that does not exist, R's BodyWeight's
"diet2 = 0.25"). The other uncertain parameters of G are shared by every experiment.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

from .._errors import InputError, ShapeError
from .distributions import Distribution, LogNormal

__all__ = ["Population", "PopulationValues", "covariate_centre", "covariate_matrix"]


@dataclass(frozen=True)
class Population:
    """Which uncertain parameters of G vary between experiments.

    Args:
        varying: names among the system's ``parameters`` (each experiment gets its own value).
        distribution: their population distribution, one :class:`~torchmisspec.population.distributions.Distribution`
            for all (default :class:`~torchmisspec.population.distributions.LogNormal`) or a mapping name ->
            distribution.
        covariates: ``{parameter: [covariate names]}``: the covariates that shift a parameter's typical value
            (linearly in eta: a log-normal parameter proportional to ``exp(beta x)``); their values per experiment
            are given to the fit.
    """

    varying: Sequence[str]
    distribution: Distribution | Mapping[str, Distribution] = field(default_factory=LogNormal)
    covariates: Mapping[str, Sequence[str]] | None = None

    def __post_init__(self) -> None:
        names = self.varying
        if isinstance(names, str) or not isinstance(names, Sequence) or not names:
            raise InputError(
                f"varying: expected a non-empty list of parameter names, got {names!r:.80}; e.g. "
                "Population(['ka', 'V'])"
            )
        if not all(isinstance(n, str) for n in names) or len(set(names)) != len(names):
            raise InputError(f"varying: expected distinct parameter names, got {list(names)!r:.120}")
        object.__setattr__(self, "varying", tuple(names))
        dist = self.distribution
        if isinstance(dist, Distribution):
            dist = {n: dist for n in names}
        if not isinstance(dist, Mapping) or set(dist) != set(names):
            raise InputError(
                f"distribution: expected one Distribution (Normal() or LogNormal()) or a mapping of {list(names)} to "
                f"them, got {self.distribution!r:.120}"
            )
        bad = [n for n, d in dist.items() if not isinstance(d, Distribution)]
        if bad:
            raise InputError(f"distribution: expected Normal() or LogNormal() for {bad}, got {[dist[n] for n in bad]}")
        object.__setattr__(self, "distribution", dict(dist))
        cov = dict(self.covariates or {})
        unknown = [n for n in cov if n not in names]
        if unknown:
            raise InputError(f"covariates: expected keys among the varying parameters {list(names)}, got {unknown}")
        for n, cs in cov.items():
            if isinstance(cs, str) or not isinstance(cs, Sequence) or not all(isinstance(c, str) for c in cs):
                raise InputError(f"covariates[{n!r}]: expected a list of covariate names, got {cs!r:.80}")
        object.__setattr__(self, "covariates", {n: tuple(cs) for n, cs in cov.items()})

    @property
    def covariate_names(self) -> tuple[str, ...]:
        """Every covariate named, in first-mention order."""
        out: list[str] = []
        for cs in self.covariates.values():
            out += [c for c in cs if c not in out]
        return tuple(out)

    def indices(self, system) -> tuple[list[int], list[int]]:
        """``(varying, shared)``: the positions of the varying and of the other uncertain parameters in
        ``system.parameters`` (checked: every varying name is one of them)."""
        priors = system.parameters
        if priors is None:
            raise InputError(
                f"system '{system.name}': expected uncertain parameters to vary between experiments, got none; declare "
                "them with MisspecifiedSystem(..., parameters={'k': (value, scale)})"
            )
        missing = [n for n in self.varying if n not in priors.names]
        if missing:
            raise InputError(
                f"varying: expected names among system '{system.name}''s parameters {list(priors.names)}, got "
                f"{missing}; declare them in MisspecifiedSystem(..., parameters=...)"
            )
        for n in self.varying:
            self.distribution[n].check(n, float(priors.mean[priors.names.index(n)]))
        vary = [priors.names.index(n) for n in self.varying]
        return vary, [i for i in range(len(priors)) if i not in vary]


def covariate_matrix(population: Population, covariates, num_experiments: int) -> torch.Tensor:
    """``(K, c)`` the experiments' covariates in :attr:`Population.covariate_names` order, from a mapping name ->
    ``(K,)`` values (checked: each named, finite, one value per experiment); ``(K, 0)`` without covariates."""
    names = population.covariate_names
    if not names:
        return torch.zeros(num_experiments, 0, dtype=torch.float64)
    if not isinstance(covariates, Mapping):
        raise InputError(
            f"covariates: expected a mapping of {list(names)} to one value per experiment, got "
            f"{type(covariates).__name__}; pass covariates={{'{names[0]}': [...]}}"
        )
    missing = [n for n in names if n not in covariates]
    if missing:
        raise InputError(f"covariates: expected values of {list(names)}, got none for {missing}")
    cols = []
    for n in names:
        v = torch.as_tensor(covariates[n], dtype=torch.float64).reshape(-1)
        if v.shape[0] != num_experiments:
            raise ShapeError(
                f"covariates[{n!r}]: expected {num_experiments} values (one per experiment), got {v.shape[0]}"
            )
        if not bool(torch.isfinite(v).all()):
            raise InputError(
                f"covariates[{n!r}]: expected finite values, got NaN or inf; fill in the missing covariate"
            )
        cols.append(v)
    return torch.stack(cols, -1)


def covariate_centre(X: torch.Tensor) -> torch.Tensor:
    """``(c,)`` where each covariate of ``X (K, c)`` is centred (the module's notes): 0 for a 0/1 covariate, else the
    experiments' mean."""
    binary = ((X == 0) | (X == 1)).all(0)
    return torch.where(binary, torch.zeros_like(X[0]), X.mean(0)) if X.shape[0] else X.mean(0)


@dataclass
class PopulationValues:
    """The population's values (float64): ``mean (k,)`` mu, ``spread (k,)`` omega, ``effects (k, c)`` beta (zero
    where a covariate does not act on a parameter), ``centre (c,)`` where the covariates are centred
    (:func:`covariate_centre`), and ``acts (k, c)`` which
    effects are estimated."""

    mean: torch.Tensor
    spread: torch.Tensor
    effects: torch.Tensor
    centre: torch.Tensor
    acts: torch.Tensor

    def typical(self, covariates: torch.Tensor) -> torch.Tensor:
        """``(K, k)`` each experiment's typical eta from its covariates ``(K, c)``."""
        shift = (covariates.to(self.mean) - self.centre) @ (self.effects * self.acts).T
        return self.mean + shift
