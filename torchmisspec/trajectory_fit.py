"""Fitting the correction through the ODE: match the observed states, no derivative estimates needed.

A correction learned from estimated derivatives inherits the estimator's bias (sparse or noisy samples).
:func:`fit_trajectories` refines it by *multiple shooting*: from every observed state y(t_i) the corrected model is
integrated over the next interval and compared with the observed y(t_{i+1}). What is adjusted are the GP's
pseudo-targets at its training inputs, under the GP prior, so the result is again a :class:`CorrectionGP` that
:class:`~torchmisspec.CorrectedODE` uses as before.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch

from ._errors import FittingError, InputError, LinearAlgebraError, NotFittedError, ShapeError
from ._ode import PREDICTION_TOLERANCES, solve
from ._threads import adaptive_threads
from ._validation import check_positive_int, check_real
from .data import Trajectories
from .gp import CorrectionGP
from .gp._optim import maximise
from .observations import _check_trajectories_and_system
from .systems import MisspecifiedSystem

__all__ = ["fit_trajectories", "shooting_misfit"]


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


@adaptive_threads()
def fit_trajectories(
    gp: CorrectionGP,
    system: MisspecifiedSystem,
    trajectories: Trajectories,
    *,
    state_noise: float | None = None,
    max_iter: int = 30,
    rtol: float = PREDICTION_TOLERANCES[0],
    atol: float = PREDICTION_TOLERANCES[1],
    max_steps: int | None = None,
    progress: bool = False,
) -> CorrectionGP:
    """Refine a fitted correction so that the corrected ODE reproduces the observed states (multiple shooting, MAP).

    **What is optimised**: the GP's pseudo-targets Y_hat ``(N, d_out)`` at its training inputs X. The corrected
    right-hand side is G(y) + k(x, X) C^-1 Y_hat with C = K(X, X) + diag(s), s the GP's noise (its floor
    ``noise_variance`` plus any known per-sample noise), so Y_hat plays the role of the correction samples.
    **What stays fixed**: the kernel hyperparameters (lengthscale, output scale, noise variance, known per-sample
    noise), the training inputs X, and the known model G. **Objective** (a MAP estimate, minimised with L-BFGS,
    gradients through torchdiffeq's solver):

        sum over intervals ||y_hat(t_{i+1}) - y(t_{i+1})||^2 / (2 s^2)  +  1/2 sum_j Y_hat_j^T C^-1 Y_hat_j

    where y_hat(t_{i+1}) integrates the corrected model from the observed y(t_i) over one interval (all K (T - 1)
    intervals in one batched solve) and the second term is the GP prior on the pseudo-targets (the marginal of
    noisy samples of F). ``s^2`` is the state noise variance: ``state_noise`` if given, otherwise the mean squared
    one-interval misfit of the starting fit, which balances the two terms at the start. The optimisation starts from
    the GP's own targets (e.g. a derivative-based fit).

    Args:
        gp: a fitted shared-kernel :class:`CorrectionGP` (its training inputs should be the observed states'
            correction inputs, as from :func:`~torchmisspec.correction_samples`).
        system: the misspecified system.
        trajectories: the observed states ``(K, T, d)``, or ragged (experiments of different lengths).
        state_noise: variance of the state measurement noise (None: estimated as above).
        max_iter: most L-BFGS iterations.
        rtol: relative tolerance of the shooting solves.
        atol: absolute tolerance of the shooting solves.
        max_steps: step limit of each solve (an :class:`IntegrationError` stops a fit whose ODE blows up).
        progress: show a progress bar over the likelihood evaluations.

    Returns:
        a new fitted :class:`CorrectionGP` (hyperparameters fixed at ``gp``'s values) whose training targets are the
        optimised Y_hat. ``gp`` itself is not modified. ``result.n_iterations_``/``n_evaluations_`` count the
        L-BFGS iterations and solves; ``result.state_noise_`` is the state noise variance s^2 used.
    """
    _check(gp, system, trajectories)
    max_iter = check_positive_int(max_iter, "max_iter")
    trajectories = trajectories.to(dtype=gp.dtype, device=gp.device)
    starts, times, ends = _intervals(trajectories)
    X = gp.train_inputs_
    L = gp._posterior_cache().fac.chol  # (B, N, N), C = K + diag(known noise + floor), fixed
    Y0 = gp.train_targets_.detach()
    scale = Y0.pow(2).mean().sqrt().clamp_min(torch.finfo(Y0.dtype).tiny)
    z = (Y0 / scale).contiguous().requires_grad_(True)  # optimised in units of the targets' RMS

    noise = gp.train_noise_  # known per-sample noise, part of C (None when there is none)

    def misfit_and_prior(zv: torch.Tensor):
        Yhat = gp._targets_batched(zv * scale, noise)  # (1, N, d_out), or (d_out, N, 1) with per-output noise
        alpha = torch.cholesky_solve(Yhat, L)
        pred, nfe = solve(
            _mean_field(gp, system, alpha),
            starts,
            times,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
            what="fit_trajectories",
        )
        sq = (pred[:, -1] - ends).pow(2).sum()
        prior = 0.5 * (Yhat * alpha).sum()
        return sq, prior

    with torch.no_grad():
        sq0, _ = misfit_and_prior(z.detach())
    n_obs = ends.numel()
    if state_noise is None:
        s2 = float(sq0) / n_obs
        s2 = max(s2, 1e-12 * float(ends.pow(2).mean()))
    else:
        s2 = check_real(state_noise, "state_noise", positive=True)

    def evaluate():
        sq, prior = misfit_and_prior(z)
        objective = -(sq / (2 * s2) + prior)  # the log posterior, up to a constant
        return objective.detach(), objective

    try:
        result = maximise(
            [z],
            evaluate,
            max_iter=max_iter,
            normaliser=float(n_obs),
            progress=progress,
            desc=f"fit_trajectories ({starts.shape[0]} intervals)",
        )
    except LinearAlgebraError as exc:
        raise FittingError(f"fit_trajectories failed: {exc}") from exc
    if not bool(torch.isfinite(z).all()):
        raise FittingError("fit_trajectories diverged: the pseudo-targets became non-finite; give state_noise=...")
    refined = gp.fixed_copy().fit(X, z.detach() * scale, noise=noise)
    refined.n_iterations_, refined.n_evaluations_ = result.iterations, result.evaluations
    refined.state_noise_ = s2
    return refined
