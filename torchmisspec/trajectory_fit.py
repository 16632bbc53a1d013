"""Fitting the correction through the ODE: match the observed states, no derivative estimates needed.

A correction learned from estimated derivatives inherits the estimator's bias (sparse or noisy samples).
:func:`fit_trajectories` refines it by *single shooting* (each experiment integrated from an estimated initial
state over its whole grid, compared with every observation) or *multiple shooting* (from every observed state over
the next interval). What is adjusted are the GP's pseudo-targets at its training inputs, under the GP prior, so the
result is again a :class:`CorrectionGP` that :class:`~torchmisspec.CorrectedODE` uses as before.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

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
from ._validation import as_tensor, check_positive_int, check_real
from .data import Trajectories
from .gp import CorrectionGP
from .gp._optim import OptimResult, maximise
from .observations import GP_MIN_SAMPLES, _check_trajectories_and_system, _gp_time
from .systems import MisspecifiedSystem

__all__ = ["SHOOTING", "fit_trajectories", "shooting_misfit"]


def _intervals(trajectories: Trajectories) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Start states ``(B, d)``, interval grids ``(B, 2)`` and end states ``(B, d)`` of all sum_k (T_k - 1)
    intervals (experiment after experiment; ragged data too)."""
    if min(trajectories.lengths) < 2:
        raise InputError(
            f"trajectories: expected at least 2 times per experiment to shoot between, got T = "
            f"{min(trajectories.lengths)}"
        )
    if trajectories.is_ragged:
        parts = [(y[:-1], torch.stack([t[:-1], t[1:]], dim=-1), y[1:]) for t, y in trajectories.experiments()]
        return tuple(torch.cat(p) for p in zip(*parts, strict=True))
    states, grid = trajectories.states, trajectories.time_grid  # (K, T, d), (K, T)
    d = states.shape[-1]
    starts = states[:, :-1].reshape(-1, d)
    ends = states[:, 1:].reshape(-1, d)
    times = torch.stack([grid[:, :-1], grid[:, 1:]], dim=-1).reshape(-1, 2)
    return starts, times, ends


def _mean_field(gp: CorrectionGP, system: MisspecifiedSystem, alpha: torch.Tensor):
    """G(y) + k(x(y), X) alpha: the corrected right-hand side for pseudo-targets whose solve is ``alpha``."""
    cache = SimpleNamespace(fac=SimpleNamespace(alpha=alpha))

    def field(y: torch.Tensor) -> torch.Tensor:
        x = system.select_inputs(y)
        shape = x.shape[:-1]
        mu = gp._mean_from(cache, x.reshape(-1, x.shape[-1]))
        return system.known_rhs(y) + system.embed(mu.reshape(*shape, -1))

    return field


def shooting_misfit(
    gp: CorrectionGP, system: MisspecifiedSystem, trajectories: Trajectories, *, max_steps: int | None = None
) -> float:
    """Root mean squared one-interval prediction error of the corrected model on the observed states.

    From every observed state y(t_i) the model G + mu (mu the GP's posterior mean) is integrated to t_{i+1} and
    compared with the observed y(t_{i+1}); all K (T - 1) intervals in one batched solve.
    """
    _check(gp, system, trajectories)
    starts, times, ends = _intervals(trajectories.to(dtype=gp.dtype, device=gp.device))
    cache = gp._posterior_cache()
    with torch.no_grad():
        pred, _ = solve(
            _mean_field(gp, system, cache.fac.alpha), starts, times, max_steps=max_steps, what="shooting_misfit"
        )
    return float((pred[:, -1] - ends).pow(2).mean().sqrt())


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
    if gp.per_output:
        raise InputError("gp: fit_trajectories supports the shared kernel only (per_output=False)")


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

    ``s_j^2``: ``state_noise`` (a number or one per component) if given; otherwise the measurement-noise variance
    the GP in time (:func:`~torchmisspec.observations.gp_derivative`) finds in the data (floored at 1e-10 of each
    component's variance; with fewer than 4 samples per experiment, the mean squared misfit of the starting fit).
    The optimisation starts from the GP's own targets (e.g. a derivative-based fit).

    Args:
        gp: a fitted shared-kernel :class:`CorrectionGP` (its training inputs should be the observed states'
            correction inputs, as from :func:`~torchmisspec.correction_samples`).
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

    Returns:
        a new fitted :class:`CorrectionGP` (hyperparameters fixed at ``gp``'s values) whose training targets are the
        optimised Y_hat. ``gp`` itself is not modified. ``result.n_iterations_``/``n_evaluations_`` count the
        L-BFGS iterations and objective evaluations (one batched solve each); ``result.state_noise_`` is the
        ``(d,)`` state-noise variance used; with single shooting ``result.initial_states_`` holds the estimated
        ``(K, d)`` initial states.
    """
    _check(gp, system, trajectories)
    if not isinstance(shooting, str) or shooting not in SHOOTING:
        raise InputError(f"shooting: expected one of {list(SHOOTING)}, got {shooting!r}")
    max_iter = check_positive_int(max_iter, "max_iter")
    trajectories = trajectories.to(dtype=gp.dtype, device=gp.device)
    d = trajectories.state_dim
    if min(trajectories.lengths) < 2:
        raise InputError(
            f"trajectories: expected at least 2 times per experiment to shoot between, got T = "
            f"{min(trajectories.lengths)}"
        )
    L = gp._posterior_cache().fac.chol  # (B, N, N), C = K + diag(known noise + floor), fixed
    X = gp.train_inputs_
    Y0 = gp.train_targets_.detach()
    scale = Y0.pow(2).mean().sqrt().clamp_min(torch.finfo(Y0.dtype).tiny)
    z = (Y0 / scale).contiguous().requires_grad_(True)  # optimised in units of the targets' RMS
    noise = gp.train_noise_  # known per-sample noise, part of C (None when there is none)
    kd = dict(dtype=gp.dtype, device=gp.device)

    def field_and_prior(zv: torch.Tensor):
        Yhat = gp._targets_batched(zv * scale, noise)  # (1, N, d_out), or (d_out, N, 1) with per-output noise
        alpha = torch.cholesky_solve(Yhat, L)
        return _mean_field(gp, system, alpha), 0.5 * (Yhat * alpha).sum()

    solver = dict(rtol=rtol, atol=atol, max_steps=max_steps, what="fit_trajectories")
    if shooting == "multiple":
        starts, times, ends = _intervals(trajectories)
        n_obs = ends.numel()

        def squares(zv, off, sd):  # noqa: ARG001 - the same signature as single shooting's
            field, prior = field_and_prior(zv)
            pred, _ = solve(field, starts, times, **solver)
            return (pred[:, -1] - ends).pow(2), prior

        params: list[torch.Tensor] = [z]
        offsets = None
    else:
        groups = trajectories.by_length()
        first = trajectories.initial_conditions  # (K, d)
        n_obs = trajectories.num_samples * d
        offsets = torch.zeros_like(first, requires_grad=True)  # (y0_hat - y0) / s, per component

        def squares(zv, off, sd):
            field, prior = field_and_prior(zv)
            parts = []
            for idx, group in groups:
                y0 = first[idx] if off is None else first[idx] + off[idx] * sd
                pred, _ = solve(field, y0, group.times, **solver)
                parts.append((pred - group.states).pow(2).reshape(-1, d))
            return torch.cat(parts), prior

        params = [z, offsets]

    s2 = _state_noise(state_noise, trajectories, d, kd)
    if s2 is None:  # too few samples for the GP in time: balance the terms at the start
        with torch.no_grad():
            sq0, _ = squares(z.detach(), None, None)  # the start: the observed initial states
        s2 = (sq0.reshape(-1, d).mean(0)).clamp_min(1e-12 * float(trajectories.flat_states().pow(2).mean()))
    sd = s2.sqrt()

    best = {"value": -math.inf, "params": None, "evaluations": 0}

    def evaluate():
        try:
            sq, prior = squares(z, offsets, sd)
        except IntegrationError:
            if best["params"] is None:  # the starting correction itself blows up: nothing to fall back on
                raise
            raise _TrialDiverged from None
        objective = -((sq.reshape(-1, d) / s2).sum() / 2 + prior)  # the log posterior, up to a constant
        value = float(objective.detach())
        best["evaluations"] += 1
        if math.isfinite(value) and value > best["value"]:
            best["value"], best["params"] = value, [p.detach().clone() for p in params]
        return objective.detach(), objective

    try:
        result = maximise(
            params,
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
            for p, value in zip(params, best["params"], strict=True):
                p.copy_(value)
        result = OptimResult(0, best["evaluations"], best["value"])
        warn(
            "fit_trajectories: a trial step of the optimiser made the corrected ODE blow up (or stall); the fit "
            f"stopped there and returns the best correction found ({best['evaluations']} evaluations). Give "
            "state_noise=... (a larger noise weakens the pull of the data) or fewer max_iter",
            TorchMisspecWarning,
        )
    if not all(bool(torch.isfinite(p).all()) for p in params):
        raise FittingError("fit_trajectories diverged: the pseudo-targets became non-finite; give state_noise=...")
    refined = gp.fixed_copy().fit(X, z.detach() * scale, noise=noise)
    refined.n_iterations_, refined.n_evaluations_ = result.iterations, result.evaluations
    refined.state_noise_ = s2
    if offsets is not None:
        refined.initial_states_ = trajectories.initial_conditions + offsets.detach() * sd
    return refined


class _TrialDiverged(Exception):
    """A line-search trial of the trajectory fit made the ODE blow up (caught inside fit_trajectories)."""


def _state_noise(state_noise, trajectories: Trajectories, d: int, kd: dict) -> torch.Tensor | None:
    """The ``(d,)`` state-noise variances: given, or the GP in time's estimate (None with fewer than 4 samples)."""
    if state_noise is not None:
        if isinstance(state_noise, (int, float)) and not isinstance(state_noise, bool):
            return torch.full((d,), check_real(state_noise, "state_noise", positive=True), **kd)
        value = as_tensor(state_noise, "state_noise", **kd).reshape(-1)
        if value.shape != (d,) or not bool(torch.isfinite(value).all() and (value > 0).all()):
            raise InputError(
                f"state_noise: expected a positive number or {d} positive variances (one per state component), got "
                f"{state_noise!r:.80}"
            )
        return value
    if min(trajectories.lengths) < GP_MIN_SAMPLES:
        return None
    times, states, mask = trajectories.padded()
    try:
        noise = _gp_time(states, times, mask if trajectories.is_ragged else None, 50).noise
    except InputError:  # a constant component: nothing to estimate from
        return None
    floor = 1e-10 * trajectories.flat_states().var(0).clamp_min(torch.finfo(noise.dtype).tiny)
    return torch.maximum(noise.to(**kd), floor)
