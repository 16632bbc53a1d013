"""Every experiment's parameters given the population: the conditional modes and their Laplace covariances.

For fixed population values (mu, beta, omega) and a fixed correction F (0 for the classical answer, its posterior
mean otherwise), experiment i's varying parameters are estimated by their posterior mode: Levenberg-Marquardt on

    sum_j sum_t r_ijt^2 / s_j^2 + |z_i|^2 + |v|^2,     eta_i = typical_i + omega * z_i,   theta_s = m_s + s_s v,

r the residuals in the noise model's space (:mod:`torchmisspec.noise`), s_j^2 each component's mean square (its
noise estimated with the fit), z_i the experiment's deviation from its typical value in units of the population's
spread (the population prior), theta_s the shared parameters in units of their prior scales (a weak prior, as in the
classical fit), and the initial states the data do not give. Every experiment, and every column of the Jacobian, is
one batched solve: a column moves one coordinate of every experiment at once (experiments are independent). The
Laplace covariance of z_i is the block of the inverse Gauss-Newton Hessian (the shared parameters and the initial
states marginalised): first-order conditional estimation (Lindstrom & Bates 1990) per experiment.

**The noise scale reported** (``Modes.scale``, what a new subject's measurement band and fit take) is each
component's residual sum of squares over its degrees of freedom left: its residual count less the leverage of its
residuals, the trace of the fit's hat matrix ``w J A^-1 J^T`` (A the Gauss-Newton Hessian with the prior): the
parameters fitted to them, each counted as the fraction of it the data determine (a parameter the prior holds counts
little, a free initial state one). The mean square at the modes (what the fit weighs by, maximum likelihood) is too
small by that fraction: fitted with F = 0 on all their subjects, the parameters take 8.1 of the 30 residuals' freedom
on R's Orange (5 trees, 2 varying parameters), 29 of 120 on theophylline and 11 of 70 on Loblolly; with the mean
square, a new tree's 90 % band held 64 % of its later measurements (72 % with this scale,
``scripts/study_population_data.py``). The fit's own weights stay the mean square's: the modes, their covariances
and the population's values are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .._errors import FittingError, IntegrationError
from .._ode import EVALS_PER_STEP, FITTING_TOLERANCES
from ..learning.refinement._known_fit import (
    MAX_STEPS,
    STEP,
    _damped_steps,
    _observed,
    component_scale,
    component_weights,
)
from ..learning.refinement.trajectory_fit import _solve_rhs
from ..learning.samples._gp_in_time import observed_rms
from ._subjects import subject_controls

__all__ = ["Layout", "Modes", "conditional_modes", "mean_correction", "held_prior"]

#: the shared parameters' prior scale, relative to their value, where they are held at a fit's values
HELD = 1e-9


@dataclass(frozen=True)
class Layout:
    """Where things are: ``vary`` / ``shared`` the positions of the varying and shared parameters in G's theta, their
    ``distributions`` (one per varying parameter), the system ``inner`` whose controls are the system's own ``m``
    followed by every parameter (varying first, then shared), and their control ``names``."""

    vary: list
    shared: list
    distributions: list
    inner: object
    m: int
    names: list

    def theta(self, eta: torch.Tensor, shared: torch.Tensor) -> torch.Tensor:
        """``(..., k)`` G's theta from the varying parameters' eta ``(..., k_v)`` and the shared values
        ``(..., k_s)`` (broadcast)."""
        cols = [d.from_eta(eta[..., j]) for j, d in enumerate(self.distributions)]
        varying = torch.stack(cols, -1)
        shared = shared.expand(*varying.shape[:-1], -1)
        out = varying.new_empty(*varying.shape[:-1], len(self.vary) + len(self.shared))
        out[..., self.vary], out[..., self.shared] = varying, shared
        return out


@dataclass(frozen=True)
class Modes:
    """The conditional modes: ``eta (K, k_v)`` and their Laplace covariance ``covariance (K, k_v, k_v)`` (eta's
    units), the shared parameters ``shared (k_s,)``, every experiment's ``initial_states (K, d)``, each measured
    component's residual root mean square ``scale`` (the noise model's space), and the optimiser's point ``z``."""

    eta: torch.Tensor
    covariance: torch.Tensor
    shared: torch.Tensor
    initial_states: torch.Tensor
    scale: torch.Tensor
    z: torch.Tensor
    num_residuals: int


def held_prior(shared: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The shared parameters' prior ``(mean, scale)`` that holds them at ``shared`` in :func:`conditional_modes` (a
    new subject's fit, a held-out experiment's): a fit of one or a few experiments cannot estimate them."""
    return shared, shared.abs().clamp_min(1e-300) * HELD


def mean_correction(system, gp):
    """``F(y, u) -> (..., d)``: the posterior mean of ``gp`` placed on the states of ``system`` (the system whose
    controls are its own and the varying parameters), from one posterior cache: what every step of a fit's solves
    evaluates (``CorrectedODE.correction`` checks its cache at every call: 3 ms a call, 358 of a fit's 557 s)."""
    posterior = gp.posterior()

    def correction(y, u):
        x = system.select_inputs(y, u)
        shape = x.shape[:-1]
        mu = posterior.mean(x.reshape(-1, x.shape[-1]).to(gp.dtype), check=False)
        return system.embed(mu.reshape(*shape, -1).to(y))

    return correction


def _paths(layout: Layout, correction, trajectories, floor=None):
    """``predict(theta (V, K, k), y0 (V, K, d), max_steps) -> (V, K, T, d + m)``: every copy's paths under
    ``G(y; theta_i) + F``, read as the data are, in one solve (``floor``: the noise model's
    :meth:`~torchmisspec.noise.NoiseModel.resolution`, the solve's)."""
    times, _, _ = trajectories.padded()
    K = trajectories.num_experiments
    times = times if times.dim() == 2 else times.expand(K, -1)
    inner, m, kv = layout.inner, layout.m, len(layout.vary)

    def rhs(y, t, u):
        g = inner.known_rhs(y, t, u)
        return g if correction is None else g + correction(y, u[..., : m + kv])

    def predict(theta, y0, max_steps=MAX_STEPS):
        V = theta.shape[0]
        order = layout.vary + layout.shared
        rows = theta.reshape(V * K, -1)[:, order]
        controls = subject_controls(trajectories.controls, rows, layout.names, times[:, 0].repeat(V))
        rtol, atol = FITTING_TOLERANCES
        solver = dict(rtol=rtol, atol=atol, max_steps=max_steps, what="the population fit", floor=floor)
        with torch.no_grad():  # the fit differences its solves: no graph to F's hyperparameters
            pred, nfe = _solve_rhs(inner, rhs, y0.reshape(V * K, -1), times.repeat(V, 1), controls, **solver)
        predict.steps = nfe / EVALS_PER_STEP
        return trajectories.observe(pred.reshape(V, K, *pred.shape[1:]))

    predict.steps = 0.0
    return predict


class _Problem:
    """The unknowns ``z = [v (k_s), z_1 .. z_K (k_v each), the free initial-state offsets (K x c)]``, their
    residuals and Jacobian (the module's notes)."""

    def __init__(self, layout, correction, trajectories, free, noise, typical, spread, prior, y_start):
        self.layout, self.noise, self.free, self.y_start = layout, noise, free, y_start
        self.typical, self.spread, self.prior = typical, spread, prior
        values, seen = _observed(trajectories)
        d = y_start.shape[-1]
        seen[:, 0, :d] &= free  # a given first value is where the path starts, not a residual
        self.seen, self.target = seen, noise.transform(values)[seen]
        self.num_components = values.shape[-1]
        self.comp = torch.arange(values.shape[-1], device=values.device).expand_as(values)[seen]
        self.exp = torch.arange(values.shape[0], device=values.device).view(-1, 1, 1).expand_as(values)[seen]
        self.cols = free.any(0).nonzero().flatten().tolist()
        size = observed_rms(torch.where(torch.isfinite(y_start), y_start, torch.zeros_like(y_start)))
        self.size = torch.where(size > 0, size, torch.ones_like(size))
        self.predict = _paths(layout, correction, trajectories, noise.resolution(trajectories))
        self.K, self.d = y_start.shape
        self.ks, self.kv = len(layout.shared), len(layout.vary)
        self.p = self.ks + self.K * (self.kv + len(self.cols))

    def unpack(self, z):  # (V, p) -> theta (V, K, k), y0 (V, K, d)
        V, ks, kv, K = z.shape[0], self.ks, self.kv, self.K
        shared = (self.prior[0] + self.prior[1] * z[:, :ks])[:, None, :]
        eta = self.typical + self.spread * z[:, ks : ks + K * kv].reshape(V, K, kv)
        y0 = self.y_start.expand(V, K, self.d).clone()
        if self.cols:
            off = z[:, ks + K * kv :].reshape(V, K, len(self.cols))
            for c, j in enumerate(self.cols):
                y0[:, :, j] = y0[:, :, j] + self.free[:, j].to(off) * off[:, :, c] * self.size[j]
        return self.layout.theta(eta, shared), y0

    def residuals(self, z, max_steps=MAX_STEPS):  # (V, p) -> (V, n)
        pred = self.noise.transform(self.predict(*self.unpack(z), max_steps))[:, self.seen]
        r = pred - self.target
        return torch.where(torch.isfinite(r), r, torch.full_like(r, math.inf))

    def jacobian(self, z, r):
        ks, kv, K, c = self.ks, self.kv, self.K, len(self.cols)
        blocks = [(ks + j, kv) for j in range(kv)] + [(ks + K * kv + j, c) for j in range(c)]
        zs = z.expand(ks + len(blocks), self.p).clone()
        for i in range(ks):
            zs[i, i] += STEP
        for b, (first, stride) in enumerate(blocks):  # one copy moves that coordinate of every experiment
            zs[ks + b, first : first + K * stride : stride] += STEP
        R = self.residuals(zs)
        J = torch.zeros(r.shape[0], self.p, dtype=r.dtype, device=r.device)
        J[:, :ks] = ((R[:ks] - r) / STEP).T
        rows = torch.arange(r.shape[0], device=r.device)
        for b, (first, stride) in enumerate(blocks):
            J[rows, first + self.exp * stride] = (R[ks + b] - r) / STEP
        J = torch.where(torch.isfinite(J), J, torch.zeros_like(J))
        return J * self.active().to(J)

    def active(self) -> torch.Tensor:
        out = torch.ones(self.p, dtype=torch.bool, device=self.y_start.device)
        if self.cols:  # an entry that is not free is not a parameter
            out[self.ks + self.K * self.kv :] = self.free[:, self.cols].reshape(-1)
        return out

    def penalty(self, like) -> torch.Tensor:
        tail = self.p - self.ks - self.K * self.kv
        return torch.cat([like.new_ones(self.ks + self.K * self.kv), like.new_zeros(tail)])


def conditional_modes(
    layout, correction, trajectories, free, noise, typical, spread, prior, start=None, scale=None
) -> Modes:
    """The experiments' conditional modes (the module's notes) under the population's ``typical (K, k_v)`` eta and
    ``spread (k_v,)`` omega, the shared parameters' prior ``(mean, scale)`` and the correction ``correction`` (F's
    mean ``(y, u) -> (..., d)``, :func:`mean_correction`, or ``None`` for F = 0), from ``start`` (a
    previous :class:`Modes`, whose eta and shared values are kept; default: every experiment at its typical value,
    the shared parameters at their prior mean). ``scale`` ``(d + m,)``: each component's noise scale, held fixed
    (a new subject's few measurements cannot estimate it), or ``(K, T, d + m)`` one per measurement (laid out as
    the data, :func:`~torchmisspec.population._misfit.misfit_scale`); default: estimated with the fit. Raises
    :class:`FittingError` when G cannot be integrated from the start."""
    y_start = trajectories.initial_conditions if start is None else start.initial_states
    problem = _Problem(layout, correction, trajectories, free, noise, typical, spread, prior, y_start)
    z = torch.zeros(problem.p, dtype=y_start.dtype, device=y_start.device)
    if start is not None:
        K, kv, ks = problem.K, problem.kv, problem.ks
        z[:ks] = (start.shared - prior[0]) / prior[1]
        z[ks : ks + K * kv] = ((start.eta - typical) / spread).reshape(-1)
    try:
        r = problem.residuals(z[None])[0]
    except IntegrationError as exc:
        raise FittingError(f"the population's model cannot be integrated from the start of its fit ({exc})") from exc
    if not bool(torch.isfinite(r).all()):
        raise FittingError("the population's model paths from the start of its fit are not finite where measured")
    weights, active = component_weights(problem.comp, problem.num_components), problem.active()
    if scale is not None:  # held: the weights of the population's fit (one per component, or per measurement)
        held = scale.to(z).nan_to_num(nan=1.0).pow(2)
        fixed = 1 / (held[problem.comp] if held.dim() == 1 else held[problem.seen])
        weights = lambda r: fixed  # noqa: E731
    solved = {"steps": problem.predict.steps}
    penalty = problem.penalty(z)
    z, r, w = _damped_steps(z, r, problem.residuals, problem.jacobian, weights, active, penalty, solved)
    return _laplace(problem, z, r, w, active, penalty)


def unbiased_scale(r: torch.Tensor, comp: torch.Tensor, num_components: int, leverage=None) -> torch.Tensor:
    """``(num_components,)`` each component's noise scale: the sum of its residuals' squares ``r (n,)`` over its
    degrees of freedom left, its residual count less the sum of their ``leverage (n,)`` (the module's notes; at
    least one left); ``leverage`` ``None``: the root mean square. NaN where a component has no residual."""
    scale = component_scale(r, comp, num_components)  # the root mean square: squares over the count
    if leverage is None:
        return scale
    zeros = torch.zeros(num_components, dtype=r.dtype, device=r.device)
    count = zeros.index_add(0, comp, torch.ones_like(r))
    left = (count - zeros.index_add(0, comp, leverage.clamp(0.0, 1.0))).clamp_min(1.0)
    return scale * (count / left).sqrt()  # NaN (no residual) stays NaN


def inverse_hessian(problem: _Problem, z, r, w, active, penalty) -> tuple[torch.Tensor, torch.Tensor]:
    """``(J (n, p), A^-1 (p, p))``: the residuals' Jacobian at ``z`` and the inverse of the Gauss-Newton Hessian with
    the prior, ``A = J^T w J + diag(penalty)`` (an inactive coordinate held by a unit diagonal). Raises
    :class:`~torch.linalg.LinAlgError` where A is not positive definite."""
    J = problem.jacobian(z, r)
    A = J.T @ (w[:, None] * J) + torch.diag(penalty) + torch.diag((~active).to(J))
    return J, torch.cholesky_inverse(torch.linalg.cholesky(A))


def _laplace(problem: _Problem, z, r, w, active, penalty) -> Modes:
    """The :class:`Modes` at ``z``: the blocks of the inverse Gauss-Newton Hessian of every experiment's z_i."""
    K, kv, ks = problem.K, problem.kv, problem.ks
    eye = torch.eye(kv, dtype=z.dtype, device=z.device).expand(K, kv, kv)
    cov_z, leverage = eye, None
    try:
        J, full = inverse_hessian(problem, z, r, w, active, penalty)
        block = full[ks : ks + K * kv, ks : ks + K * kv].reshape(K, kv, K, kv)
        cov_z = block[torch.arange(K), :, torch.arange(K), :]
        leverage = w * ((J @ full) * J).sum(1)  # the hat matrix's diagonal
    except (IntegrationError, torch.linalg.LinAlgError):
        pass  # the prior's covariance: nothing learned about the spread from this fit
    theta, y0 = problem.unpack(z[None])
    eta = problem.typical + problem.spread * z[ks : ks + K * kv].reshape(K, kv)
    scale = unbiased_scale(r, problem.comp, problem.num_components, leverage)
    s = problem.spread
    return Modes(
        eta=eta,
        covariance=cov_z * s[:, None] * s[None, :],
        shared=problem.prior[0] + problem.prior[1] * z[:ks],
        initial_states=y0[0],
        scale=scale,
        z=z,
        num_residuals=int(r.numel()),
    )
