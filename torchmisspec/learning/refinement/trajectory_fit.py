"""Fitting the correction through the ODE: match the observed states, no derivative estimates needed.

A correction learned from estimated derivatives inherits the estimator's bias (sparse or noisy samples).
:func:`fit_trajectories` refines it by *single shooting* (each experiment integrated from an estimated initial
state over its whole grid, compared with every observation) or *multiple shooting* (from every observed state over
the next interval). What is adjusted are the GP's pseudo-targets at its training inputs, under the GP prior, so the
result is again a :class:`CorrectionGP` that :class:`~torchmisspec.CorrectedODE` uses as before.
"""

from __future__ import annotations

import torch

from ..._errors import FittingError, InputError, IntegrationError, LinearAlgebraError, NotFittedError, ShapeError
from ..._ode import DEFAULT_MAX_STEPS, FITTING_TOLERANCES, solve
from ..._validation import as_tensor, check_flag, check_positive_int, check_real
from ...data import Trajectories
from ...gp import CorrectionGP, Posterior
from ...parallel import adaptive_threads
from ...systems import MisspecifiedSystem
from .._units import refine_in_units
from ..samples._gp_in_time import estimate_observed_noise, observed_rms
from ..samples.observations import _check_trajectories_and_system
from ._term_price import bic, term_price
from ._trajectory_map import _balanced_noise, _fit_relevance, _maximise_posterior

__all__ = ["SHOOTING", "fit_trajectories", "shooting_misfit"]


def _intervals(trajectories: Trajectories):
    """Start states ``(B, d)``, interval grids ``(B, 2)``, end values ``(B, d + m)`` (the states and any readings,
    :meth:`Trajectories.observed_values`) and the experiment of each ``(B,)`` of all sum_k (T_k - 1) intervals
    (experiment after experiment; ragged data too). Missing entries of the start states are estimated
    (:meth:`Trajectories.filled`); those of the end values stay NaN (the residuals skip them)."""
    if min(trajectories.lengths) < 2:
        raise InputError(
            f"trajectories: expected at least 2 times per experiment to shoot between, got T = "
            f"{min(trajectories.lengths)}"
        )
    rows = torch.arange(trajectories.num_experiments, device=trajectories.device).repeat_interleave(
        torch.tensor(trajectories.lengths, device=trajectories.device) - 1
    )
    grid, filled, _ = trajectories.filled().padded()
    values, mask = trajectories.observed_values()
    inner = mask[:, 1:] & mask[:, :-1]  # intervals inside each experiment
    starts, ends = filled[:, :-1][inner], values[:, 1:][inner]
    times = torch.stack([grid[:, :-1], grid[:, 1:]], dim=-1)[inner]
    return starts, times, ends, rows


def _solve_rhs(system, rhs, y0, times, controls, **solver):
    """``solve`` of a right-hand side ``rhs(y, t, u)`` under ``controls`` (one profile per row, or None)."""
    field, timed, jumps = system.solver_field(rhs, controls)
    return solve(field, y0, times, timed=timed, jumps=jumps, **solver)


def _mean_field(system: MisspecifiedSystem, posterior: Posterior):
    """G(y) + the posterior mean of F: the corrected right-hand side (differentiable through ``posterior``'s solve
    when it was built from pseudo-targets, :meth:`Posterior.with_targets`)."""

    def field(y: torch.Tensor, t=None, u=None) -> torch.Tensor:
        x = system.select_inputs(y, u)
        shape = x.shape[:-1]
        mu = posterior.mean(x.reshape(-1, x.shape[-1]), check=False)
        return system.known_rhs(y, t, u) + system.embed(mu.reshape(*shape, -1))

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
    trajectories = trajectories.to(dtype=gp.dtype, device=gp.device)
    starts, times, ends, rows = _intervals(trajectories)
    controls = None if trajectories.controls is None else trajectories.controls[rows.tolist()]
    with torch.no_grad():
        pred, _ = _solve_rhs(
            system,
            _mean_field(system, gp.posterior()),
            starts,
            times,
            controls,
            max_steps=max_steps,
            what="shooting_misfit",
        )
    seen = torch.isfinite(ends)
    return float((trajectories.observe(pred[:, -1]) - ends)[seen].pow(2).mean().sqrt())


def _check(gp, system, trajectories) -> None:
    if not isinstance(gp, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP, got {type(gp).__name__}")
    if not gp.is_fitted:
        raise NotFittedError("gp: expected a fitted CorrectionGP (fit it on derivative-based samples first)")
    _check_trajectories_and_system(trajectories, system)
    if system.parameters is not None:
        raise InputError(
            f"system: '{system.name}' has uncertain parameters {list(system.parameters.names)}, which the fit through "
            "the ODE does not learn; fix them, e.g. at the fit's posterior mean: system.at(gp.parameters_.mean) (or "
            "fit_correction(..., refine=True), which does so)"
        )
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
    the GP in time (:func:`~torchmisspec.learning.samples.observations.gp_derivative`) finds in the data (floored at
    1e-10 of each component's variance; with fewer than 4 samples per experiment, the mean squared misfit of the
    starting fit). The optimisation starts from the GP's own targets (e.g. a derivative-based fit).

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
        atol: absolute tolerance of the shooting solves, in units of each state's scale: the fit runs on the states
            divided by a power of ten near each component's size (data near 1 as they are), and returns the model in
            the user's units (:mod:`torchmisspec.learning._units`), so states of any size are integrated alike.
        max_steps: step limit of each solve (an :class:`IntegrationError` stops a fit whose ODE blows up).
        progress: show a progress bar over the likelihood evaluations.
        relevance: for the feature kernel (default ``True`` there): also re-estimate its term weights from the
            trajectories (sparse Bayesian learning through the ODE: MAP coefficients, a Laplace posterior,
            MacKay's update, repeated): the terms the observed states do not support are removed. What is then
            optimised are the coefficients of the terms (and the initial states); the result's pseudo-targets
            reproduce the fitted coefficients exactly. Where the rounds end, a sparse set of terms proposed by
            BIC in the linearised misfit is refitted the same way and kept when its BIC through the ODE is lower
            (:mod:`torchmisspec.learning.refinement._term_price`; ``result.relevance_record_`` holds the misfit and the
            terms kept).

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
    max_iter, relevance = _checked_options(gp, shooting, max_iter, relevance)
    options = dict(shooting=shooting, max_iter=max_iter, rtol=rtol, atol=atol, max_steps=max_steps, progress=progress)
    if state_noise is not None:  # refused here, before it is recorded (a bad value raised inside _recorded)
        _state_noise(state_noise, trajectories, dict(dtype=torch.float64, device=trajectories.device))
    scaled = refine_in_units(
        fit_trajectories, gp, system, trajectories, state_noise=state_noise, recorded=_recorded(state_noise),
        relevance=relevance, **options,
    )  # fmt: skip
    if scaled is not None:  # refined in the data's own units, returned in the user's (torchmisspec.learning._units)
        return scaled
    trajectories = trajectories.to(dtype=gp.dtype, device=gp.device)
    if min(trajectories.lengths) < 2:
        raise InputError(
            f"trajectories: expected at least 2 times per experiment to shoot between, got T = "
            f"{min(trajectories.lengths)}"
        )
    solver = dict(rtol=rtol, atol=atol, max_steps=max_steps, what="fit_trajectories")
    residuals, n_obs, offsets = _shooting(trajectories, shooting, solver, system)
    kd = dict(dtype=gp.dtype, device=gp.device)
    s2 = _state_noise(state_noise, trajectories, kd)
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
        options = dict(max_iter=max_iter, progress=progress)
        refined = _fit_relevance(gp, system, trajectories, residuals, n_obs, offsets, s2, propose=True, **options)
        refined = _sparser(refined, gp, system, trajectories, residuals, n_obs, offsets, options)
    else:
        refined = _refined_targets(
            gp, system, trajectories, residuals, n_obs, offsets, s2, max_iter, progress, shooting
        )
    refined.refinement_ = recipe
    return refined


def _checked_options(gp, shooting, max_iter, relevance) -> tuple[int, bool]:
    """``(max_iter, relevance)``: relevance by default for a feature kernel (term weights learned in feature space),
    after refusing an unknown ``shooting``, a bad ``max_iter`` and relevance for another kernel."""
    if not isinstance(shooting, str) or shooting not in SHOOTING:
        raise InputError(f"shooting: expected one of {list(SHOOTING)}, got {shooting!r}")
    max_iter = check_positive_int(max_iter, "max_iter")
    relevance = check_flag(relevance, "relevance", none=True)
    relevance_kernel = gp.kernel_spec.terms and gp.kernel_spec.feature_space  # term weights learned in feature space
    relevance = relevance_kernel if relevance is None else relevance
    if relevance and not relevance_kernel:
        raise InputError(
            f"relevance: expected a feature kernel (its term weights are re-estimated), got kernel {gp.kernel!r}"
        )
    return max_iter, relevance


def _refined_targets(gp, system, trajectories, residuals, n_obs, offsets, s2, max_iter, progress, shooting):
    """The MAP of the pseudo-targets (and initial-state offsets) given the observed states, by L-BFGS
    (:func:`_maximise_posterior`), as a new :class:`CorrectionGP` with ``gp``'s hyperparameters and its records
    (iterations, evaluations, right-hand-side evaluations, state noise, initial states)."""
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
        s2 = _balanced_noise(residuals, field_and_prior(z.detach())[0], trajectories)
    result = _maximise_posterior(
        [z], offsets, field_and_prior, residuals, s2, n_obs, max_iter=max_iter, progress=progress, shooting=shooting
    )
    refined = gp.condition(X, z.detach() * scale, noise=noise)
    refined.n_iterations_, refined.n_evaluations_ = result.iterations, result.evaluations
    refined.n_rhs_evaluations_ = residuals.nfe
    refined.state_noise_ = s2
    if offsets is not None:
        d = trajectories.state_dim
        refined.initial_states_ = trajectories.initial_conditions + offsets.detach() * s2[:d].sqrt()
    return refined


def _sparser(refined, gp, system, trajectories, residuals, n_obs, offsets, options) -> CorrectionGP:
    """``refined`` or the refit through the ODE of the sparse terms proposed where its rounds ended
    (:mod:`torchmisspec.learning.refinement._term_price`), whichever has the lower BIC through the ODE (the scaled
    misfit of the observed states, plus the price of each kept term)."""
    record = refined.relevance_record_
    proposal = record["proposal"]
    if proposal is None or not bool(proposal.any()) or torch.equal(proposal, record["active"]):
        return refined
    price = term_price(gp, n_obs)
    start = None if offsets is None else offsets.detach().clone()
    try:
        rival = _fit_relevance(gp, system, trajectories, residuals, n_obs, offsets, refined.state_noise_,
                               only=proposal, **options)  # fmt: skip
    except (FittingError, IntegrationError, LinearAlgebraError):
        rival = None
    if rival is not None:
        ours, theirs = rival.relevance_record_, record
        if bic(ours["misfit"], ours["terms"], price) < bic(theirs["misfit"], theirs["terms"], price):
            return rival
    if start is not None:  # the offsets as the kept fit left them
        offsets.data.copy_(start)
    return refined


def _shooting(trajectories: Trajectories, shooting: str, solver: dict, system: MisspecifiedSystem):
    """``residuals(field, off, sd, max_steps=None)``: the errors (prediction - observation) ``(n, d + m)`` of a
    right-hand side ``field`` in the states and any readings (:meth:`Trajectories.observe`; single shooting: from the
    observed first states moved by ``off * sd[:d]``, its rows experiment after experiment, ``residuals.experiment
    (n,)`` naming each row's experiment; ``max_steps`` lowers the solve's step limit, ``residuals.last`` is the last
    solve's right-hand-side evaluations); the number of observations compared; the initial-state offsets to optimise
    (single shooting) or ``None``."""
    d = trajectories.state_dim
    observe = trajectories.observe
    if shooting == "multiple":
        starts, times, ends, rows = _intervals(trajectories)
        _check_starts(starts, "multiple shooting starts every interval at the observed states: ", "use single shooting")
        controls = None if trajectories.controls is None else trajectories.controls[rows.tolist()]
        seen = torch.isfinite(ends)
        zero = torch.zeros((), dtype=ends.dtype, device=ends.device)

        def residuals(field, off, sd, max_steps=None):  # noqa: ARG001 - the same signature as single shooting's
            pred, nfe = _solve_rhs(system, field, starts, times, controls, **_limited(solver, max_steps))
            residuals.nfe, residuals.last = residuals.nfe + nfe, nfe
            return torch.where(seen, observe(pred[:, -1]) - ends, zero)  # missing entries: 0

        residuals.experiment = None
        residuals.nfe = residuals.last = 0
        residuals.seen = seen
        return residuals, int(seen.sum()), None
    # every experiment in one batched solve, ragged ones too: each row on its own times (padded at its end by
    # repeating its last time, which the solver's shared grid absorbs); only the observed entries are compared
    times, _, mask = trajectories.padded()
    states, _ = trajectories.observed_values()  # (K, T, d + m): the states and any readings
    if times.dim() == 1:
        times = times.expand(states.shape[0], -1)
    first = trajectories.initial_conditions  # (K, d), missing entries estimated (Trajectories.filled)
    _check_starts(first)
    controls = trajectories.controls
    offsets = torch.zeros_like(first, requires_grad=True)  # (y0_hat - y0) / s, per component
    zero = torch.zeros((), dtype=first.dtype, device=first.device)
    seen = torch.isfinite(states)  # missing entries (NaN) are compared as 0

    def residuals(field, off, sd, max_steps=None):
        y0 = first if off is None else first + off * sd[:d]
        pred, nfe = _solve_rhs(system, field, y0, times, controls, **_limited(solver, max_steps))
        residuals.nfe, residuals.last = residuals.nfe + nfe, nfe
        return torch.where(seen, observe(pred) - states, zero)[mask]  # (n, d + m), experiment after experiment

    residuals.nfe = residuals.last = 0  # right-hand-side evaluations of every solve, and of the last one
    residuals.experiment = torch.arange(states.shape[0], device=first.device).unsqueeze(-1).expand_as(mask)[mask]

    def many(field, copies: int, off, sd):
        """``(copies, n, d + m)``: the residuals of ``copies`` models at once, ``field`` taking the states of copy c's
        experiments in rows c K ... c K + K - 1 (one batched solve instead of ``copies``)."""
        y0 = first if off is None else first + off * sd[:d]  # off (K, d), or (copies, K, d): one per copy
        y0 = y0.reshape(-1, d) if y0.dim() == 3 else y0.repeat(copies, 1)
        repeated = None if controls is None else controls.repeat(copies)
        pred, nfe = _solve_rhs(system, field, y0, times.repeat(copies, 1), repeated, **solver)
        residuals.nfe += nfe
        pred = observe(pred.reshape(copies, *first.shape[:1], -1, d))
        return torch.where(seen, pred - states, zero)[:, mask]

    residuals.many = many
    residuals.seen = seen[mask]
    return residuals, int(residuals.seen.sum()), offsets


def _limited(solver: dict, max_steps: int | None) -> dict:
    """``solver`` with its step limit lowered to ``max_steps`` (where given: a trial step's budget)."""
    if max_steps is None:
        return solver
    cap = solver.get("max_steps") or DEFAULT_MAX_STEPS
    return {**solver, "max_steps": min(cap, max_steps)}


def _check_starts(first: torch.Tensor, why: str = "", fix: str | None = None) -> None:
    """Refuse start states with a component that was never observed (partly measured data without initial states)."""
    if bool(torch.isfinite(first).all()):
        return
    k, j = (int(i) for i in (~torch.isfinite(first)).nonzero()[0])
    fix = fix or (
        "set the initial states (trajectories.with_initial_states(model.initial_states(trajectories))), or let "
        "fit_correction estimate them (it learns partly measured data through the ODE)"
    )
    raise InputError(
        f"trajectories: {why}component {j} of experiment {k} is never observed there, so its path has no start; {fix}"
    )


def _recorded(state_noise):
    """``state_noise`` as a model records it (None, a float or a list of floats: saved with the model)."""
    if state_noise is None or isinstance(state_noise, (int, float)):
        return None if state_noise is None else float(state_noise)
    return [float(v) for v in torch.as_tensor(state_noise).reshape(-1).tolist()]


def _state_noise(state_noise, trajectories: Trajectories, kd: dict) -> torch.Tensor | None:
    """The ``(d + m,)`` noise variances of the states and any readings: given (a number for all, or one per state
    and reading), or the GP in time's estimate (None with fewer than 4 samples)."""
    d = trajectories.state_dim
    e = trajectories.observed_dim
    if state_noise is not None:
        if isinstance(state_noise, (int, float)) and not isinstance(state_noise, bool):
            return torch.full((e,), check_real(state_noise, "state_noise", positive=True), **kd)
        value = as_tensor(state_noise, "state_noise", **kd).reshape(-1)
        if value.shape != (e,) or not bool(torch.isfinite(value).all() and (value > 0).all()):
            what = "state component" if e == d else "state component and reading"
            raise InputError(
                f"state_noise: expected a positive number or {e} positive variance{'s' if e > 1 else ''} (one per "
                f"{what}), got {state_noise!r:.80}"
            )
        return value
    std = estimate_observed_noise(trajectories)  # None with fewer than 4 samples or a constant component
    if std is None:
        return None
    var = std.to(**kd).pow(2)
    if trajectories.is_partial:  # a component no experiment measures: its few values taken as 1 % accurate (of
        # its size, or of the largest component's when they are all 0)
        size = observed_rms(trajectories.flat_states().to(**kd))
        var[:d] = torch.where(trajectories.measured.any(0), var[:d], (1e-2 * size).pow(2))
    return var
