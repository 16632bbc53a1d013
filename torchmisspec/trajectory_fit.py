"""Fitting the correction through the ODE: match the observed states, no derivative estimates needed.

A correction learned from estimated derivatives inherits the estimator's bias (sparse or noisy samples).
:func:`fit_trajectories` refines it by *single shooting* (each experiment integrated from an estimated initial
state over its whole grid, compared with every observation) or *multiple shooting* (from every observed state over
the next interval). What is adjusted are the GP's pseudo-targets at its training inputs, under the GP prior, so the
result is again a :class:`CorrectionGP` that :class:`~torchmisspec.CorrectedODE` uses as before.
"""

from __future__ import annotations

import math

import torch

from ._errors import (
    FittingError,
    InputError,
    IntegrationError,
    LinearAlgebraError,
    NotFittedError,
    ShapeError,
    TorchMisspecWarning,
    warn,
)
from ._ode import FITTING_TOLERANCES, solve
from ._threads import adaptive_threads
from ._validation import as_tensor, check_positive_int, check_real, progress_bar
from .data import Trajectories
from .gp import CorrectionGP, Posterior
from .gp._optim import OptimResult, maximise
from .observations import _check_trajectories_and_system, estimate_state_noise
from .systems import MisspecifiedSystem

__all__ = ["SHOOTING", "fit_trajectories", "shooting_misfit"]


def _intervals(trajectories: Trajectories) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Start states ``(B, d)``, interval grids ``(B, 2)`` and end states ``(B, d)`` of all sum_k (T_k - 1)
    intervals (experiment after experiment; ragged data too). Missing entries of the start states are estimated
    (:meth:`Trajectories.filled`); those of the end states stay NaN (the residuals skip them)."""
    if min(trajectories.lengths) < 2:
        raise InputError(
            f"trajectories: expected at least 2 times per experiment to shoot between, got T = "
            f"{min(trajectories.lengths)}"
        )
    filled = trajectories.filled()
    if trajectories.is_ragged:
        parts = [
            (f[:-1], torch.stack([t[:-1], t[1:]], dim=-1), y[1:])
            for (t, y), f in zip(trajectories.experiments(), filled.states, strict=True)
        ]
        return tuple(torch.cat(p) for p in zip(*parts, strict=True))
    states, grid = trajectories.states, trajectories.time_grid  # (K, T, d), (K, T)
    d = states.shape[-1]
    starts = filled.states[:, :-1].reshape(-1, d)
    ends = states[:, 1:].reshape(-1, d)
    times = torch.stack([grid[:, :-1], grid[:, 1:]], dim=-1).reshape(-1, 2)
    return starts, times, ends


def _mean_field(system: MisspecifiedSystem, posterior: Posterior):
    """G(y) + the posterior mean of F: the corrected right-hand side (differentiable through ``posterior``'s solve
    when it was built from pseudo-targets, :meth:`Posterior.with_targets`)."""

    def field(y: torch.Tensor) -> torch.Tensor:
        x = system.select_inputs(y)
        shape = x.shape[:-1]
        mu = posterior.mean(x.reshape(-1, x.shape[-1]), check=False)
        return system.known_rhs(y) + system.embed(mu.reshape(*shape, -1))

    return field


def shooting_misfit(
    gp: CorrectionGP, system: MisspecifiedSystem, trajectories: Trajectories, *, max_steps: int | None = None
) -> float:
    """Root mean squared one-interval prediction error of the corrected model on the observed states.

    From every observed state y(t_i) the model G + mu (mu the GP's posterior mean) is integrated to t_{i+1} and
    compared with the observed y(t_{i+1}); all K (T - 1) intervals in one batched solve. Missing entries are not
    compared (a missing start entry is estimated by :meth:`Trajectories.filled`).
    """
    _check(gp, system, trajectories)
    starts, times, ends = _intervals(trajectories.to(dtype=gp.dtype, device=gp.device))
    with torch.no_grad():
        pred, _ = solve(_mean_field(system, gp.posterior()), starts, times, max_steps=max_steps, what="shooting_misfit")
    seen = torch.isfinite(ends)
    return float((pred[:, -1] - ends)[seen].pow(2).mean().sqrt())


def _check(gp, system, trajectories) -> None:
    if not isinstance(gp, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP, got {type(gp).__name__}")
    if not gp.is_fitted:
        raise NotFittedError("gp: expected a fitted CorrectionGP (fit it on derivative-based samples first)")
    _check_trajectories_and_system(trajectories, system)
    if gp.input_dim != system.input_dim or gp.output_dim != system.output_dim:
        raise ShapeError(
            f"gp: expected {system.input_dim} inputs and {system.output_dim} outputs (the system's correction), got "
            f"{gp.input_dim} and {gp.output_dim}"
        )


#: Names accepted by ``fit_trajectories(shooting=...)``.
SHOOTING = ("single", "multiple")


@adaptive_threads()
def fit_trajectories(
    gp: CorrectionGP,
    system: MisspecifiedSystem,
    trajectories: Trajectories,
    *,
    shooting: str = "single",
    state_noise=None,
    max_iter: int = 30,
    rtol: float = FITTING_TOLERANCES[0],
    atol: float = FITTING_TOLERANCES[1],
    max_steps: int | None = None,
    progress: bool = False,
    relevance: bool | None = None,
) -> CorrectionGP:
    """Refine a fitted correction so that the corrected ODE reproduces the observed states (shooting, MAP).

    **What is optimised**: the GP's pseudo-targets Y_hat ``(N, d_out)`` at its training inputs X, and with
    ``shooting="single"`` also every experiment's initial state. The corrected right-hand side is
    G(y) + k(x, X) C^-1 Y_hat with C = K(X, X) + diag(s), s the GP's noise (its floor ``noise_variance`` plus any
    known per-sample noise), so Y_hat plays the role of the correction samples. **What stays fixed**: the kernel
    hyperparameters (lengthscale, output scale, noise variance, known per-sample noise), the training inputs X,
    the known model G and the state-noise variances. **Objective** (a MAP estimate, minimised with L-BFGS,
    gradients through torchdiffeq's solver; ``s_j^2`` the state-noise variance of component j):

    * ``shooting="single"`` (default): every experiment is integrated from its estimated initial state
      ``y0_hat_k`` over its whole grid, and every observation is compared with the path:

          sum_k sum_i sum_j (y_hat_kj(t_i) - y_kj(t_i))^2 / (2 s_j^2)  +  1/2 sum_j Y_hat_j^T C^-1 Y_hat_j

      (the i = 0 term is the prior of y0_hat_k around the observed first state). The measurement model is exact,
      so noisy states do not bias the correction;
    * ``shooting="multiple"``: from every *observed* state y(t_i) the model is integrated over one interval and
      compared with y(t_{i+1}) (all K (T - 1) intervals in one batched solve). Robust for long or chaotic
      horizons, where a single path drifts away from the data, but the noise in the start states is ignored
      (errors in variables): with noisy states the correction learns a spurious damping.

    **Missing entries** (NaN states) are left out of every sum: the residuals compare observed entries only (a
    missing component of a first state has no i = 0 term: its y0_hat starts from the estimate of
    :meth:`Trajectories.filled` and is set by the later observations; with multiple shooting a missing start entry
    is that estimate).

    ``s_j^2``: ``state_noise`` (a number or one per component) if given; otherwise the measurement-noise variance
    the GP in time (:func:`~torchmisspec.observations.gp_derivative`) finds in the data (floored at 1e-10 of each
    component's variance; with fewer than 4 samples per experiment, the mean squared misfit of the starting fit).
    The optimisation starts from the GP's own targets (e.g. a derivative-based fit).

    Args:
        gp: a fitted :class:`CorrectionGP`, any kernel, shared or per output (its training inputs should be the
            observed states' correction inputs, as from :func:`~torchmisspec.correction_samples`).
        system: the misspecified system.
        trajectories: the observed states ``(K, T, d)``, or ragged (experiments of different lengths).
        shooting: ``"single"`` or ``"multiple"``.
        state_noise: variance of the state measurement noise, a number or ``(d,)`` (None: estimated as above).
        max_iter: most L-BFGS iterations.
        rtol: relative tolerance of the shooting solves (the package's fitting tolerance by default, see
            :mod:`torchmisspec._ode`).
        atol: absolute tolerance of the shooting solves.
        max_steps: step limit of each solve (an :class:`IntegrationError` stops a fit whose ODE blows up).
        progress: show a progress bar over the likelihood evaluations.
        relevance: for the feature kernel (default ``True`` there): also re-estimate its term weights from the
            trajectories (sparse Bayesian learning through the ODE: MAP coefficients, a Laplace posterior,
            MacKay's update, repeated): the terms the observed states do not support are removed. What is then
            optimised are the coefficients of the terms (and the initial states); the result's pseudo-targets
            reproduce the fitted coefficients exactly.

    Returns:
        a new fitted :class:`CorrectionGP` (hyperparameters fixed at ``gp``'s values) whose training targets are the
        optimised Y_hat. ``gp`` itself is not modified. ``result.n_iterations_``/``n_evaluations_`` count the
        L-BFGS iterations and objective evaluations (one batched solve each), ``result.n_rhs_evaluations_`` the
        right-hand-side evaluations of all its solves (each a batched call; gradients and finite differences
        included); ``result.state_noise_`` is the
        ``(d,)`` state-noise variance used; with single shooting ``result.initial_states_`` holds the estimated
        ``(K, d)`` initial states; ``result.refinement_`` the settings of this refinement (saved with the model:
        :meth:`CorrectedODE.calibrate <torchmisspec.CorrectedODE.calibrate>` refines each fold the same way).
    """
    _check(gp, system, trajectories)
    if not isinstance(shooting, str) or shooting not in SHOOTING:
        raise InputError(f"shooting: expected one of {list(SHOOTING)}, got {shooting!r}")
    max_iter = check_positive_int(max_iter, "max_iter")
    relevance = gp.kernel_spec.feature_space if relevance is None else bool(relevance)
    if relevance and not gp.kernel_spec.feature_space:
        raise InputError(f"relevance: re-estimating term weights needs the feature kernel, got kernel {gp.kernel!r}")
    trajectories = trajectories.to(dtype=gp.dtype, device=gp.device)
    d = trajectories.state_dim
    if min(trajectories.lengths) < 2:
        raise InputError(
            f"trajectories: expected at least 2 times per experiment to shoot between, got T = "
            f"{min(trajectories.lengths)}"
        )
    solver = dict(rtol=rtol, atol=atol, max_steps=max_steps, what="fit_trajectories")
    residuals, n_obs, offsets = _shooting(trajectories, shooting, solver)
    kd = dict(dtype=gp.dtype, device=gp.device)
    s2 = _state_noise(state_noise, trajectories, d, kd)
    # how this refinement was made: calibrate_bands repeats it on each fold (a fold fitted to the samples alone is a
    # worse model than the refined one, and its held-out errors would widen the bands too much)
    recipe = dict(
        shooting=shooting,
        state_noise=_recorded(state_noise),
        max_iter=max_iter,
        rtol=float(rtol),
        atol=float(atol),
        max_steps=max_steps,
        relevance=relevance,
    )
    if relevance:
        refined = _fit_relevance(
            gp, system, trajectories, residuals, n_obs, offsets, s2, max_iter=max_iter, progress=progress
        )
        refined.refinement_ = recipe
        return refined
    posterior = gp.posterior()  # its factor of C = K + diag(known noise + floor) is fixed; the targets are not
    X = gp.train_inputs_
    Y0 = gp.train_targets_.detach()
    scale = Y0.pow(2).mean().sqrt().clamp_min(torch.finfo(Y0.dtype).tiny)
    z = (Y0 / scale).contiguous().requires_grad_(True)  # optimised in units of the targets' RMS
    noise = gp.train_noise_  # known per-sample noise, part of C (None when there is none)

    def field_and_prior(zv: torch.Tensor):
        pseudo = posterior.with_targets(zv * scale)
        return _mean_field(system, pseudo), 0.5 * pseudo.factor.quad

    if s2 is None:  # too few samples for the GP in time: balance the terms at the start
        s2 = _balanced_noise(residuals, field_and_prior(z.detach())[0], trajectories, d)
    result = _maximise_posterior(
        [z], offsets, field_and_prior, residuals, s2, n_obs, max_iter=max_iter, progress=progress, shooting=shooting
    )
    refined = gp.condition(X, z.detach() * scale, noise=noise)
    refined.n_iterations_, refined.n_evaluations_ = result.iterations, result.evaluations
    refined.n_rhs_evaluations_ = residuals.nfe
    refined.state_noise_ = s2
    if offsets is not None:
        refined.initial_states_ = trajectories.initial_conditions + offsets.detach() * s2.sqrt()
    refined.refinement_ = recipe
    return refined


def _shooting(trajectories: Trajectories, shooting: str, solver: dict):
    """``residuals(field, off, sd)``: the state errors (prediction - observation) ``(n, d)`` of a right-hand side
    ``field`` (single shooting: from the observed first states moved by ``off * sd``, its rows experiment after
    experiment within each length group, ``residuals.experiment (n,)`` naming each row's experiment); the number of
    observations compared; the initial-state offsets to optimise (single shooting) or ``None``."""
    d = trajectories.state_dim
    if shooting == "multiple":
        starts, times, ends = _intervals(trajectories)

        seen = torch.isfinite(ends)
        zero = torch.zeros((), dtype=ends.dtype, device=ends.device)

        def residuals(field, off, sd):  # noqa: ARG001 - the same signature as single shooting's
            pred, nfe = solve(field, starts, times, **solver)
            residuals.nfe += nfe
            return torch.where(seen, pred[:, -1] - ends, zero)  # missing entries: 0

        residuals.experiment = None
        residuals.nfe = 0
        residuals.seen = seen
        return residuals, int(seen.sum()), None
    # every experiment in one batched solve, ragged ones too: each row on its own times (padded at its end by
    # repeating its last time, which the solver's shared grid absorbs); only the observed entries are compared
    times, states, mask = trajectories.padded()
    if times.dim() == 1:
        times = times.expand(states.shape[0], -1)
    first = trajectories.initial_conditions  # (K, d), missing entries estimated (Trajectories.filled)
    offsets = torch.zeros_like(first, requires_grad=True)  # (y0_hat - y0) / s, per component
    zero = torch.zeros((), dtype=first.dtype, device=first.device)
    seen = torch.isfinite(states)  # missing entries (NaN) are compared as 0

    def residuals(field, off, sd):
        y0 = first if off is None else first + off * sd
        pred, nfe = solve(field, y0, times, **solver)
        residuals.nfe += nfe
        return torch.where(seen, pred - states, zero)[mask]  # (n, d), experiment after experiment

    residuals.nfe = 0  # right-hand-side evaluations of every solve (batched: one per step stage)
    residuals.experiment = torch.arange(states.shape[0], device=first.device).unsqueeze(-1).expand_as(mask)[mask]

    def many(field, copies: int, off, sd):
        """``(copies, n, d)``: the residuals of ``copies`` models at once, ``field`` taking the states of copy c's
        experiments in rows c K ... c K + K - 1 (one batched solve instead of ``copies``)."""
        y0 = first if off is None else first + off * sd  # off (K, d), or (copies, K, d): one per copy
        y0 = y0.reshape(-1, d) if y0.dim() == 3 else y0.repeat(copies, 1)
        pred, nfe = solve(field, y0, times.repeat(copies, 1), **solver)
        residuals.nfe += nfe
        return torch.where(seen, pred.reshape(copies, *states.shape) - states, zero)[:, mask]

    residuals.many = many
    residuals.seen = seen[mask]
    return residuals, int(residuals.seen.sum()), offsets


def _balanced_noise(residuals, field, trajectories: Trajectories, d: int) -> torch.Tensor:
    """State-noise variances that balance data and prior at the start: the mean squared misfit per component."""
    with torch.no_grad():
        sq0 = residuals(field, None, None).pow(2).reshape(-1, d)  # the start: the observed initial states
    seen = residuals.seen.to(sq0.dtype)
    flat = trajectories.flat_states()
    size = float(flat[torch.isfinite(flat)].pow(2).mean())
    return (sq0.sum(0) / seen.sum(0).clamp_min(1.0)).clamp_min(1e-12 * size)


def _maximise_posterior(params, offsets, field_and_prior, residuals, s2, n_obs, *, max_iter, progress, shooting):
    """L-BFGS on the log posterior ``-(sum squares / (2 s2) + prior)`` over ``params`` (and the offsets); a trial
    step that blows up the ODE ends the fit at the best iterate, with a warning. The parameters hold the optimum."""
    d = s2.shape[0]
    sd = s2.sqrt()
    every = [*params] + ([] if offsets is None else [offsets])
    best = {"value": -math.inf, "params": None, "evaluations": 0}

    def evaluate():
        try:
            field, prior = field_and_prior(params[0])
            sq = residuals(field, offsets, sd).pow(2)
        except IntegrationError:
            if best["params"] is None:  # the starting correction itself blows up: nothing to fall back on
                raise
            raise _TrialDiverged from None
        objective = -((sq.reshape(-1, d) / s2).sum() / 2 + prior)  # the log posterior, up to a constant
        value = float(objective.detach())
        best["evaluations"] += 1
        if math.isfinite(value) and value > best["value"]:
            best["value"], best["params"] = value, [p.detach().clone() for p in every]
        return objective.detach(), objective

    try:
        result = maximise(
            every,
            evaluate,
            max_iter=max_iter,
            normaliser=float(n_obs),
            progress=progress,
            desc=f"fit_trajectories ({shooting} shooting)",
        )
    except LinearAlgebraError as exc:
        raise FittingError(f"fit_trajectories failed: {exc}") from exc
    except _TrialDiverged:
        # a line-search trial drove the corrected ODE into a blow-up or a stiff region: keep the best iterate
        with torch.no_grad():
            for p, value in zip(every, best["params"], strict=True):
                p.copy_(value)
        result = OptimResult(0, best["evaluations"], best["value"])
        warn(
            "fit_trajectories: a trial step of the optimiser made the corrected ODE blow up (or stall); the fit "
            f"stopped there and returns the best correction found ({best['evaluations']} evaluations). Give "
            "state_noise=... (a larger noise weakens the pull of the data) or fewer max_iter",
            TorchMisspecWarning,
        )
    if not all(bool(torch.isfinite(p).all()) for p in every):
        raise FittingError("fit_trajectories diverged: the parameters became non-finite; give state_noise=...")
    return result


#: Most outer iterations (MAP, then a relevance update of the weights) of the feature kernel's trajectory fit.
RELEVANCE_ROUNDS = 10
#: L-BFGS iterations of the MAP in the rounds after the first (each starts from the previous optimum).
_LATER_ITERATIONS = 10


def _fit_relevance(gp, system, trajectories, residuals, n_obs, offsets, s2, *, max_iter: int, progress: bool = False):
    """The feature kernel through the ODE: sparse Bayesian learning of its term weights from the trajectories.

    F(x) = sum_j beta_j phi_j(x) with beta_j ~ N(0, w_j). Each round (i) finds the MAP coefficients (and initial
    states) under the current weights by L-BFGS, (ii) approximates their posterior by Laplace with the Gauss-Newton
    Hessian of the state misfit (its Jacobian by central differences: every coefficient, and each state component
    of all initial states at once, since experiments are independent), and (iii) updates the weights by MacKay's
    rule w_j = sum_o beta_oj^2 / sum_o gamma_oj, gamma_oj = 1 - Sigma_oj / w_j (removing terms that fall below
    :data:`~torchmisspec.gp._features.PRUNE`), until the active terms and weights settle.
    """
    from .gp._features import PRUNE

    d = trajectories.state_dim
    base = gp.covar_module.base_kernel
    X = gp.train_inputs_
    Phi = base.features(X)  # (N, p): the monomials or a user library
    p = Phi.shape[1]
    d_out = gp.output_dim
    kd = dict(dtype=gp.dtype, device=gp.device)
    scale = gp.covar_module.outputscale.detach().reshape(-1, 1)  # (B, 1)
    W = (base.weights.detach().reshape(-1, p) * scale).T.expand(p, d_out).clone()  # (p, d_out) prior variances
    shared = W.shape[1] > 1 and not gp.per_output
    # the starting coefficients: the posterior mean of the current fit, beta = W Phi^T alpha
    alpha = gp.posterior().weights  # (N, d_out)
    beta = W * (Phi.T @ alpha)
    second = float(gp.train_targets_.pow(2).mean()) or 1.0
    phi2 = Phi.pow(2).mean(0).unsqueeze(-1).clamp_min(torch.finfo(Phi.dtype).tiny)  # (p, 1)
    # every term starts active: the derivative samples may have removed a term the trajectories support (their
    # estimator's bias is not the trajectories'); a removed term starts with an equal share of the samples' size
    W = torch.where(W > 0, W, (second / (p * phi2)).expand_as(W))

    def make_field(b):
        def field(y):
            x = system.select_inputs(y)
            return system.known_rhs(y) + system.embed(base.features(x) @ b)

        return field

    def make_fields(bs):  # bs (m, p, d_out): copy c's coefficients drive rows c K ... c K + K - 1
        def field(y):
            f = base.features(system.select_inputs(y)).reshape(bs.shape[0], -1, p)  # (m, K, p)
            return system.known_rhs(y) + system.embed(torch.einsum("mkp,mpo->mko", f, bs).reshape(y.shape[0], -1))

        return field

    if s2 is None:
        s2 = _balanced_noise(residuals, make_field(beta), trajectories, d)
    sd = s2.sqrt()
    iterations = evaluations = 0
    bar = progress_bar(progress, RELEVANCE_ROUNDS, "fit_trajectories: term weights through the ODE", "round")
    for round_ in range(RELEVANCE_ROUNDS):
        bar.update()
        active = W > 0
        if not bool(active.any()):
            beta = torch.zeros_like(W)
            break
        root = W[active].sqrt()
        u = (beta[active] / root).clone().requires_grad_(True)  # coefficients in units of their prior std

        def field_and_prior(uv, active=active, root=root):
            b = torch.zeros((p, d_out), **kd).index_put((active.nonzero(as_tuple=True)), uv * root)
            return make_field(b), 0.5 * uv.pow(2).sum()

        rounds_iter = max_iter if round_ == 0 else min(max_iter, _LATER_ITERATIONS)
        if hasattr(residuals, "many") and offsets is not None:  # single shooting: Levenberg-Marquardt
            its, evals = _levenberg_marquardt(
                u, offsets, active, root, beta, make_field, make_fields, residuals, sd, max_iter=rounds_iter
            )
        else:
            result = _maximise_posterior(
                [u], offsets, field_and_prior, residuals, s2, n_obs, max_iter=rounds_iter, progress=False,
                shooting="relevance",
            )  # fmt: skip
            its, evals = result.iterations, result.evaluations
        iterations += its
        evaluations += evals
        b_act = (u.detach() * root).clone()
        beta = torch.zeros((p, d_out), **kd)
        beta[active] = b_act
        # Laplace: Gauss-Newton Hessian of the scaled misfit in (coefficients, initial-state offsets)
        off = None if offsets is None else offsets.detach()
        with torch.no_grad():
            J_b = _coefficient_columns(residuals, make_field, beta, active, off, sd, make_fields)
            H = J_b.T @ J_b + torch.diag(1.0 / W[active])
            if off is not None:  # the offsets' block: column j moves component j of every initial state
                Jo = _offset_columns(residuals, make_field(beta), off, sd)  # (n d, K d)
                Kx, dd = off.shape
                Hbo = J_b.T @ Jo
                Hoo = Jo.T @ Jo + torch.eye(Kx * dd, **kd)  # the offsets' prior N(0, 1) in units of sd
                H = H - Hbo @ torch.linalg.solve(Hoo, Hbo.T)  # marginal over the offsets (Schur complement)
            try:
                Sigma = torch.linalg.inv(H).diagonal()
            except torch.linalg.LinAlgError:
                break
            new = torch.zeros_like(W)
            gam = (1.0 - Sigma / W[active]).clamp(1e-12, 1.0)
            num = torch.zeros_like(W)
            num[active] = b_act.pow(2)
            den = torch.zeros_like(W)
            den[active] = gam
            if shared:  # one weight per term shared by the outputs
                num = num.sum(1, keepdim=True).expand_as(W)
                den = den.sum(1, keepdim=True).expand_as(W)
            new[active] = num[active] / den[active].clamp_min(1e-12)
            new[new * phi2 < PRUNE * second] = 0.0
            both = (new > 0) & active
            change = float((new[both].log() - W[both].log()).abs().max()) if bool(both.any()) else 0.0
            settled = bool(((new > 0) == active).all()) and change < 1e-2
            beta = beta * (new > 0)
            W = new
        if settled:
            break
    bar.close()
    # back to a CorrectionGP: the new weights, and pseudo-targets whose posterior mean is exactly phi(x)^T beta
    tmp = gp.condition(X, gp.train_targets_, noise=gp.train_noise_)
    with torch.no_grad():
        wt = (W.T / scale) if gp.per_output else (W[:, :1].T / scale)
        tmp.covar_module.base_kernel.weights.copy_(wt.reshape(tmp.covar_module.base_kernel.weights.shape))
        # a term kept through the ODE is present; one the samples' fit removed too keeps the chance of being present
        # and the spread that the samples gave it (gp._features; the trajectories' own would need the linearised
        # factors); one the samples kept but the trajectories removed counts as absent (chance 0, no spread)
        base = tmp.covar_module.base_kernel
        kept = base.weights.detach() > 0
        was_kept = gp.covar_module.base_kernel.weights.detach().reshape(kept.shape) > 0
        one, zero = torch.ones_like(base.inclusion), torch.zeros_like(base.inclusion)
        base.inclusion.copy_(torch.where(kept, one, torch.where(was_kept, zero, base.inclusion)))
        base.spread.copy_(torch.where(kept | was_kept, zero, base.spread))
        Yhat = _pseudo_targets(tmp, Phi, W, beta)
    refined = tmp.condition(X, Yhat, noise=gp.train_noise_)
    refined.n_iterations_, refined.n_evaluations_ = iterations, evaluations
    refined.n_rhs_evaluations_ = residuals.nfe
    refined.state_noise_ = s2
    if offsets is not None:
        refined.initial_states_ = trajectories.initial_conditions + offsets.detach() * sd
    return refined


def _levenberg_marquardt(u, offsets, active, root, beta, make_field, make_fields, residuals, sd, *, max_iter: int):
    """Minimise ``1/2 ||r(u, o) / s||^2 + 1/2 ||u||^2`` (the MAP of the coefficients ``u``, in units of their prior
    standard deviations, and the initial-state offsets ``o``, in units of the state noise) by Levenberg-Marquardt
    steps: the Jacobian by central differences, every perturbed model in one batched solve. The problem has a few
    dozen parameters and is nearly linear in them, so a handful of steps replaces L-BFGS's dozens of evaluations,
    each of which differentiated through the solver. ``u`` and ``offsets`` are updated in place; returns
    ``(iterations, objective evaluations)``."""
    q = u.numel()
    K, d = offsets.shape
    kd = dict(dtype=u.dtype, device=u.device)

    def coefficients(uv):
        b = torch.zeros_like(beta)
        b[active] = uv * root
        return b

    def objective(uv, ov):
        try:
            r = residuals(make_field(coefficients(uv)), ov, sd) / sd
        except IntegrationError:
            return math.inf, None
        return 0.5 * float(r.pow(2).sum() + uv.pow(2).sum()), r.reshape(-1)

    with torch.no_grad():
        uv, ov = u.detach().clone(), offsets.detach().clone()
        value, r = objective(uv, ov)
        if r is None:
            raise FittingError("fit_trajectories: the starting correction cannot be integrated over the experiments")
        lam, evaluations, iterations = 1e-3, 1, 0
        while iterations < max_iter:
            iterations += 1
            b = coefficients(uv)
            J_u = _coefficient_columns(residuals, make_field, b, active, ov, sd, make_fields) * root  # (n d, q)
            J_o = _offset_columns(residuals, make_field(b), ov, sd)  # (n d, K d)
            J = torch.cat([J_u, J_o], dim=1)
            grad = J.T @ r + torch.cat([uv, torch.zeros(K * d, **kd)])
            H = J.T @ J
            H[range(q), range(q)] += 1.0
            accepted = False
            for _ in range(8):
                A = H + lam * torch.diag(H.diagonal().clamp_min(1e-12))
                try:
                    step = -torch.linalg.solve(A, grad)
                except torch.linalg.LinAlgError:
                    lam *= 10.0
                    continue
                new_u, new_o = uv + step[:q], ov + step[q:].reshape(K, d)
                new_value, new_r = objective(new_u, new_o)
                evaluations += 1
                if new_value < value:
                    accepted = True
                    break
                lam *= 10.0
            if not accepted:
                break
            gain = value - new_value
            uv, ov, value, r = new_u, new_o, new_value, new_r
            lam = max(lam / 10.0, 1e-9)
            if gain <= 1e-8 * max(value, 1.0):
                break
        u.data.copy_(uv)
        offsets.data.copy_(ov)
    return iterations, evaluations


def _step(value: float, typical: float) -> float:
    """A central-difference step for a parameter of size ``value`` among parameters of size ``typical``."""
    return 1e-5 * max(abs(value), typical, 1e-12)


def _coefficient_columns(residuals, make_field, beta, active, off, sd, make_fields=None) -> torch.Tensor:
    """``(n d, q)``: d (residual / s) / d beta over the active coefficients, by central differences; with
    ``make_fields`` (a field for a stack of coefficient sets) and single shooting, every perturbed model in one
    batched solve."""
    typical = float(beta.abs().max()) * 1e-3
    pairs = active.nonzero(as_tuple=False).tolist()
    if make_fields is not None and hasattr(residuals, "many"):
        h = torch.tensor([_step(float(beta[i, o]), typical) for i, o in pairs], dtype=beta.dtype, device=beta.device)
        q = len(pairs)
        stack = beta.unsqueeze(0).repeat(2 * q, 1, 1)
        rows = torch.arange(q, device=beta.device)
        idx_i = torch.tensor([i for i, _ in pairs], device=beta.device)
        idx_o = torch.tensor([o for _, o in pairs], device=beta.device)
        stack[rows, idx_i, idx_o] += h
        stack[q + rows, idx_i, idx_o] -= h
        res = residuals.many(make_fields(stack), 2 * q, off, sd)  # (2q, n, d)
        diff = (res[:q] - res[q:]) / (2 * h.reshape(-1, 1, 1)) / sd
        return diff.reshape(q, -1).T
    cols = []
    for i, o in pairs:
        h = _step(float(beta[i, o]), typical)
        plus, minus = beta.clone(), beta.clone()
        plus[i, o] += h
        minus[i, o] -= h
        diff = residuals(make_field(plus), off, sd) - residuals(make_field(minus), off, sd)
        cols.append((diff / (2 * h) / sd).reshape(-1))
    return torch.stack(cols, dim=-1)


def _offset_columns(residuals, field, off, sd) -> torch.Tensor:
    """``(n d, K d)``: d (residual / s) / d offsets by central differences; experiments are independent, so moving
    component j of every initial state at once gives each experiment's own column."""
    rows = residuals.experiment  # (n,)
    K, d = off.shape
    n = rows.shape[0]
    J = torch.zeros((n, d, K, d), dtype=off.dtype, device=off.device)
    h = 1e-5
    if hasattr(residuals, "many"):  # the 2 d perturbed offsets in one batched solve
        stack = off.unsqueeze(0).repeat(2 * d, 1, 1)
        j = torch.arange(d, device=off.device)
        stack[j, :, j] += h
        stack[d + j, :, j] -= h
        res = residuals.many(field, 2 * d, stack, sd)  # (2 d, n, d)
        delta = (res[:d] - res[d:]) / (2 * h) / sd  # (d, n, d)
        for jj in range(d):
            J[torch.arange(n, device=off.device), :, rows, jj] = delta[jj]
        return J.reshape(n * d, K * d)
    for j in range(d):
        plus, minus = off.clone(), off.clone()
        plus[:, j] += h
        minus[:, j] -= h
        delta = (residuals(field, plus, sd) - residuals(field, minus, sd)) / (2 * h) / sd  # (n, d)
        J[torch.arange(n, device=off.device), :, rows, j] = delta
    return J.reshape(n * d, K * d)


def _pseudo_targets(gp, Phi: torch.Tensor, W: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """Targets ``Y (N, d_out)`` whose posterior mean under ``gp`` (a feature kernel with prior variances ``W``) is
    ``phi(x)^T beta``: with C the training covariance, ``Y_o = C Phi_a (Phi_a^T Phi_a)^-1 W_a^-1 beta_a`` over the
    active terms a of output o (then ``W_a Phi_a^T C^-1 Y_o = beta_a``)."""
    X = gp.train_inputs_
    C = gp.posterior().training_covariance()  # (B, N, N)
    Y = torch.zeros((X.shape[0], beta.shape[1]), dtype=beta.dtype, device=beta.device)
    for o in range(beta.shape[1]):
        act = W[:, o] > 0
        if not bool(act.any()):
            continue
        P = Phi[:, act]
        Y[:, o] = C[o if C.shape[0] > 1 else 0] @ (P @ torch.linalg.solve(P.T @ P, beta[act, o] / W[act, o]))
    return Y


class _TrialDiverged(Exception):
    """A line-search trial of the trajectory fit made the ODE blow up (caught inside fit_trajectories)."""


def _recorded(state_noise):
    """``state_noise`` as a model records it (None, a float or a list of floats: saved with the model)."""
    if state_noise is None or isinstance(state_noise, (int, float)):
        return None if state_noise is None else float(state_noise)
    return [float(v) for v in torch.as_tensor(state_noise).reshape(-1).tolist()]


def _state_noise(state_noise, trajectories: Trajectories, d: int, kd: dict) -> torch.Tensor | None:
    """The ``(d,)`` state-noise variances: given, or the GP in time's estimate (None with fewer than 4 samples)."""
    if state_noise is not None:
        if isinstance(state_noise, (int, float)) and not isinstance(state_noise, bool):
            return torch.full((d,), check_real(state_noise, "state_noise", positive=True), **kd)
        value = as_tensor(state_noise, "state_noise", **kd).reshape(-1)
        if value.shape != (d,) or not bool(torch.isfinite(value).all() and (value > 0).all()):
            raise InputError(
                f"state_noise: expected a positive number or {d} positive variance{'s' if d > 1 else ''} (one per "
                f"state component), got "
                f"{state_noise!r:.80}"
            )
        return value
    std = estimate_state_noise(trajectories)  # None with fewer than 4 samples or a constant component
    return None if std is None else std.to(**kd).pow(2)
