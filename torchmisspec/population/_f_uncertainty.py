"""F's own uncertainty in the population's values: how far they move over F's posterior draws.

The population's values are fitted with F held at its posterior mean. F is itself an estimate, and where it is off,
every experiment's data are off the model's paths alike, and their parameters absorb it: F and a typical value can
stand in for each other (a volume and an elimination term both set a concentration's level). The standard errors of
:mod:`~torchmisspec.population.uncertainty` count only the measurements' noise and the experiments' spread, as if F
were exact.

Each of :data:`DRAWS` posterior draws of F (pathwise, :meth:`~torchmisspec.CorrectedODE.posterior`) moves what is
measured of experiment i by ``dz_i`` (the noise model's space, to first order) along its fitted path. To first order
the experiments' parameters then move by ``A^-1 J^T w dz`` (the Gauss-Newton step of the population's last E step:
J the residuals' Jacobian, w the fit's weights, A its Hessian with the prior; the shared parameters and the free
initial states move with them), and EM's fixed point carries that into the typical values: for parameter j,
``(I - (D^T D)^-1 D^T diag(c_j) D) d beta_j = (D^T D)^-1 D^T a_j``, D the fixed effects' design, a_j the modes' local
moves, c_ij = C_i,jj / omega_j^2 each mode's pull towards its typical value (every parameter on its own: the
cross-parameter pulls are dropped). The covariance of these moves over the draws is added to
the Fisher information's: a standard error that counts F's uncertainty (the two-step estimator's correction of Murphy
& Topel 1985, with F's posterior in place of the first step's sampling distribution; the two are treated as
independent).

The spread's variance is left as the Fisher information's. Its moves over F's draws were computed too (the M step
on the moved modes) and kept out: on the populations tutorial a few draws, where F is least known (the highest
concentrations, few samples), moved the spread's square by 6 times its value; its degrees of freedom fell below 1
and a new patient's prior spread (Student's t, :func:`~torchmisspec.population.uncertainty.new_subject_prior`) rose
from 0.24 to 7.2 in log k. A first-order move is not the answer to such a draw.

Why: on issue 43's population study (``docs/studies/population.md``), before F's part was counted, the typical
volume's z-scores against the truth had a root mean square of 1.55 over 20 realizations (1 where the standard errors
are right), the typical absorption rate's 1.10: where a correction is kept, its error moves the volume (F acts on the
concentration, which the volume scales), not the absorption rate (read from the depot).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from .._errors import TorchMisspecWarning
from ..learning.refinement._known_fit import component_weights
from ._modes import _Problem, inverse_hessian
from ._subjects import parameter_names, with_subject_inputs
from .uncertainty import fixed_effects

__all__ = ["Shifts", "correction_shifts", "population_moves", "transformed_deviations", "DRAWS"]

#: posterior draws of F whose moves of the population's values give their covariance
DRAWS = 32
#: the draws' seed: a fit is reproducible
SEED = 4_300
#: the fraction of a draw's deviation the noise model's transform is differenced over (first order: a draw that
#: takes a positive state below 0 has no logarithm, its small step has)
LINEAR = 1e-3
#: the least of 1 - a parameter's mean pull towards its typical value in EM's fixed point (a population whose
#: experiments hardly inform a parameter: its typical value's move is bounded by 1 / this times the modes')
LEAST_LEFT = 0.1


@dataclass(frozen=True)
class Shifts:
    """The population's values moved by each posterior draw of F (the module's notes): ``fixed`` one ``(F, p_j)``
    per varying parameter (its typical value and covariates' effects)."""

    fixed: list

    def fixed_covariance(self, j: int) -> torch.Tensor:
        """``(p_j, p_j)`` the covariance over the draws of parameter j's fixed effects."""
        moves = self.fixed[j] - self.fixed[j].mean(0)
        return moves.T @ moves / max(moves.shape[0] - 1, 1)


def transformed_deviations(noise, paths: torch.Tensor, dim: int) -> torch.Tensor:
    """How each draw in ``paths`` (its draws along ``dim``) moves what is measured from the draws' mean, in the noise
    model's space to first order (:data:`LINEAR`); NaN (a path that left the region) as 0."""
    centre = paths.mean(dim, keepdim=True)
    moved = (noise.transform(centre + LINEAR * (paths - centre)) - noise.transform(centre)) / LINEAR
    return torch.nan_to_num(moved, nan=0.0, posinf=0.0, neginf=0.0)


def _deviations(fit, data) -> torch.Tensor:
    """``(F, K, T_max, o)``: each draw's deviation of what is measured of every experiment at its data times (the
    padded layout; 0 past an experiment's end)."""
    nlme = fit.nlme
    names = parameter_names(fit.system, nlme.layout.vary)
    subjects = with_subject_inputs(data, nlme.thetas[:, nlme.layout.vary], names)
    values, _ = data.observed_values()
    out = values.new_zeros(DRAWS, *values.shape)
    generator = torch.Generator(device=values.device).manual_seed(SEED)
    for idx, group in subjects.by_length():
        with warnings.catch_warnings():  # the draws' own notes (support, calibration) are not the fit's to say
            warnings.simplefilter("ignore", TorchMisspecWarning)
            post = fit.corrected.posterior(
                group.initial_conditions, group.time_grid, num_samples=DRAWS, controls=group.controls,
                generator=generator, scale=1.0,
            )  # fmt: skip
        paths = group.observe(post.samples.to(values.dtype))  # (F, B, T, o)
        out[:, idx, : paths.shape[2]] = transformed_deviations(fit.noise, paths, 0)
    return out


def _problem(nlme, system, data, noise) -> tuple[_Problem, torch.Tensor]:
    """The population's last E step at its modes: the problem and its point z."""
    layout, values, modes = nlme.layout, nlme.values, nlme.modes
    priors = system.parameters
    prior = (priors.mean[layout.shared], priors.scale[layout.shared])
    typical = values.typical(nlme.covariates)
    problem = _Problem(
        layout, nlme.correction, data, nlme.free, noise, typical, values.spread, prior, modes.initial_states
    )
    z = torch.zeros(problem.p, dtype=typical.dtype, device=typical.device)
    z[: problem.ks] = (modes.shared - prior[0]) / prior[1]
    z[problem.ks : problem.ks + problem.K * problem.kv] = ((modes.eta - typical) / values.spread).reshape(-1)
    return problem, z


def _local_moves(nlme, system, data, noise, deviations: torch.Tensor) -> torch.Tensor:
    """``(F, K, k_v)``: every experiment's mode moved by each of ``deviations (F, K, T_max, o)`` (what is measured,
    moved in the noise model's space) at fixed population values (the notes)."""
    problem, z = _problem(nlme, system, data, noise)
    r = problem.residuals(z[None])[0]
    w = component_weights(problem.comp, problem.num_components)(r)
    J, full = inverse_hessian(problem, z, r, w, problem.active(), problem.penalty(z))
    dz = deviations[:, problem.seen]  # (F, n)
    step = (w * dz) @ J @ full  # (F, p): A^-1 J^T w dz, A symmetric
    ks, K, kv = problem.ks, problem.K, problem.kv
    return step[:, ks : ks + K * kv].reshape(-1, K, kv) * nlme.values.spread


def population_moves(nlme, system, data, noise, deviations: torch.Tensor) -> Shifts:
    """:class:`Shifts`: how the population ``nlme``'s values (fitted to ``data`` with its initial states, for
    ``system`` and ``noise``) move, to first order, when what is measured moves by each of ``deviations (F, K,
    T_max, o)`` (the noise model's space, the padded layout): EM's fixed point (the module's notes). Raises
    :class:`~torch.linalg.LinAlgError` where the fit's Hessian is not positive definite."""
    local = _local_moves(nlme, system, data, noise, deviations)
    values, modes, X = nlme.values, nlme.modes, nlme.covariates
    fixed = []
    for j in range(modes.eta.shape[1]):
        D = fixed_effects(values, X, j)
        pull = modes.covariance[:, j, j] / values.spread[j] ** 2  # c_ij (the notes)
        DtD_inv = torch.linalg.pinv(D.T @ D)
        eye = torch.eye(D.shape[-1], dtype=D.dtype, device=D.device)
        system_j = eye - DtD_inv @ D.T @ (pull[:, None] * D)
        least = float(torch.linalg.eigvals(system_j).real.min())  # real: similar to a symmetric matrix
        system_j = system_j + max(LEAST_LEFT - least, 0.0) * eye
        rhs = local[:, :, j] @ D @ DtD_inv.T  # (F, p): (D^T D)^-1 D^T a_j for each draw
        fixed.append(torch.linalg.solve(system_j, rhs.T).T)
    return Shifts(fixed)


def correction_shifts(fit) -> Shifts | None:
    """:class:`Shifts` of the population ``fit``'s values over F's posterior draws (the module's notes); ``None``
    without a correction, without the data, or where the fit's Hessian is not positive definite."""
    if fit.known_model or fit.data is None:
        return None
    data = fit.data.with_initial_states(fit.nlme.modes.initial_states)
    try:
        return population_moves(fit.nlme, fit.system, data, fit.noise, _deviations(fit, data))
    except torch.linalg.LinAlgError:
        return None
