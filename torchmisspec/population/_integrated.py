"""F's step with every experiment's parameters integrated out, under the population as their prior.

Fixing each experiment's parameters at the modes of the population fitted with F = 0 (the classical answer) lets
them keep what they absorbed of the missing term: a volume that stands in for a missing elimination hides it from
F. Here they are learned *with* F instead, by the package's own theta-and-F fit (:mod:`torchmisspec.learning.theta`):
the population becomes one system whose uncertain parameters are every experiment's varying parameters, in eta's
coordinates (:mod:`~torchmisspec.population.distributions`), each with its prior from the population,

    eta_i ~ N(mu + beta^T c_i, omega^2),

and an appended constant control, the experiment's index, that picks experiment i's eta in G. F takes the states
(and the system's own controls) as before, never the index. :func:`~torchmisspec.fit_correction` then integrates
F out of the derivative samples to find every eta's Laplace posterior (Gauss-Newton: G is nonlinear in eta), chooses
F there, and applies its do no harm (the known model with every eta fitted through the ODE as the rival).
:func:`integrated_modes` moves every experiment's eta to that posterior's mean.

On the population study (``scripts/study_population.py``) the classical fit's volumes were 0.23-0.29 off in log;
integrated with F, 0.02-0.03 where a correction was kept (three realizations, probed while building this).
"""

from __future__ import annotations

import dataclasses

import torch

from ..data import Trajectories
from ..systems import MisspecifiedSystem
from ._subjects import _replace_controls, subject_controls, with_appended_controls

__all__ = ["integrated_system", "with_experiment_index", "integrated_modes"]

#: the appended control that holds each experiment's index
INDEX = "experiment index"


def _index_name(system: MisspecifiedSystem) -> str:
    taken = set(system.state_names or ()) | set(system.control_names)
    name = INDEX
    while name in taken:
        name = f"_{name}"
    return name


def integrated_system(system: MisspecifiedSystem, nlme) -> MisspecifiedSystem:
    """The population of ``nlme`` (an :class:`~torchmisspec.population.nlme.NLMEFit`) as one system: G with every
    experiment's varying parameters as uncertain parameters (eta's coordinates, prior the population's), the shared
    ones fixed at the fit's values, and the experiment's index as a last control (the module's notes)."""
    layout, values = nlme.layout, nlme.values
    K, p, m = nlme.covariates.shape[0], len(layout.vary), layout.m
    prior_mean = values.typical(nlme.covariates)  # (K, p)
    spread = values.spread.clamp_min(1e-3)
    names = [system.parameters.names[i] for i in layout.vary]
    parameters = {f"eta {n} [{i}]": (float(prior_mean[i, j]), float(spread[j])) for i in range(K) for j, n in
                  enumerate(names)}  # fmt: skip
    shared, inner = nlme.modes.shared.detach(), layout.inner

    def known(t, y, u, eta):  # eta (K p,) or, a row's own in each column, (K p, B) (MisspecifiedSystem.rows_rhs)
        index = u[..., m].round().long().clamp(0, K - 1)
        if eta.dim() == 1:
            own = eta.reshape(K, p).to(y)[index]
        else:
            own = eta.T.reshape(-1, K, p).to(y)[torch.arange(index.shape[0], device=y.device), index]
        theta = layout.theta(own, shared.to(y))
        inputs = torch.cat([u[..., :m].to(y), theta[..., layout.vary], theta[..., layout.shared]], -1)
        return inner.known(t, y, inputs)

    name = f"{system.name} (every experiment's {', '.join(names)} integrated)"
    return with_appended_controls(system, known, [_index_name(system)], name, parameters)


def with_experiment_index(trajectories: Trajectories, system: MisspecifiedSystem) -> Trajectories:
    """``trajectories`` with each experiment's index appended to its controls (a constant profile)."""
    K = trajectories.num_experiments
    index = torch.arange(K, dtype=torch.float64)[:, None]
    starts = torch.stack([t[0] for t, _ in trajectories.experiments()])
    return _replace_controls(
        trajectories, subject_controls(trajectories.controls, index, [_index_name(system)], starts)
    )


def integrated_modes(gp, nlme):
    """``nlme``'s modes with every experiment's eta moved to ``gp``'s posterior mean (the rest kept)."""
    K, p = nlme.covariates.shape[0], len(nlme.layout.vary)
    eta = gp.parameters_.mean.detach().to(nlme.modes.eta).reshape(K, p)
    return dataclasses.replace(nlme.modes, eta=eta)
