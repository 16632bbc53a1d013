"""The known model alone (F = 0) fitted through the ODE to what was measured: the classical answer.

A scientist's first fit of a model that is almost right: G's uncertain parameters and the initial states the data
do not give, chosen so that G's paths match the measured values (states and readings) in the space where the
measurement errors are alike (a :class:`~torchmisspec.noise.NoiseModel`: logs for relative errors, ``log(1 + y)``
for counts). It is what a correction must beat to be worth keeping (do no harm):
:mod:`torchmisspec.learning.refinement.partial` compares the two on held-out later times (:func:`time_split`,
:func:`forecast_score`).

The fit is Levenberg-Marquardt on

    sum_j sum_i r_ij^2 / s_j^2 + |v|^2,      theta = m + s_theta v,

r the residuals of component (or reading) j, s_j^2 their mean square at the current point (each component's noise
estimated with the fit, as a maximum-likelihood fit with unknown variances does), v the parameters in units of their
prior standard deviations (the prior as a weak penalty: it keeps a parameter the data do not see where the scientist
put it). The Jacobian is by forward differences, every column in one batched solve (an experiment's initial state
moves only its own path, so one copy per state component serves every experiment). A trial step whose solve fails or
does not lower the misfit is rejected and the damping raised: never the end of the fit. theta's covariance is the
Laplace one at the end, the initial states marginalised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..._errors import FittingError, IntegrationError
from ..._ode import EVALS_PER_STEP, FITTING_TOLERANCES, trial_budget
from ...data import Trajectories
from ...gp import CorrectionGP
from ...gp._exact import median_distance
from ..samples._gp_in_time import observed_rms
from .trajectory_fit import _solve_rhs

__all__ = [
    "KNOWN_MODEL_OUTPUTSCALE",
    "KnownFit",
    "fit_known_model",
    "forecast_score",
    "known_model_template",
    "time_split",
]

#: most Levenberg-Marquardt iterations (each: one batched solve of 1 + k + d copies, and one of the trial step)
ITERATIONS = 30
#: forward-difference step, in units of a parameter's prior sd or of a component's size
STEP = 1e-4
#: most solver steps of one batched solve (a trial step that needs more is rejected)
MAX_STEPS = 4000
#: the fit stops once an accepted step lowers the misfit by less than this fraction
TOLERANCE = 1e-7
#: of each experiment, this fraction of its times (rounded up) is kept by :func:`time_split`, the rest held out ...
KEEP = 2 / 3
#: ... when it has at least this many times (shorter ones are kept whole)
MIN_SPLIT = 6


@dataclass(frozen=True)
class KnownFit:
    """The known model's fit (:func:`fit_known_model`).

    Attributes:
        theta: G's uncertain parameters ``(k,)`` (``None`` without them).
        covariance: their Laplace covariance ``(k, k)``, the initial states marginalised (``None`` without them).
        fixed: their covariance with the initial states held at the estimate (``None`` without them).
        initial_states: every experiment's initial state ``(K, d)``.
        scale: each measured component's (and reading's) root mean square residual ``(d + m,)``, in the noise
            model's space (NaN where nothing is measured).
    """

    theta: torch.Tensor | None
    covariance: torch.Tensor | None
    fixed: torch.Tensor | None
    initial_states: torch.Tensor
    scale: torch.Tensor
    #: the fit's unknowns in the order of :attr:`unknowns_covariance`: ``("theta", i)`` or ``("state", k, j)``
    unknowns: tuple = ()
    #: their units (a parameter's prior sd, a component's size) ``(p,)``
    units: torch.Tensor | None = None
    #: their Laplace covariance in those units ``(p, p)`` (``None`` where it could not be formed)
    unknowns_covariance: torch.Tensor | None = None
    #: the number of residuals the fit matched (each component's measured values, its given first values left out)
    num_residuals: int = 0


def _predictor(system, trajectories: Trajectories, cost: dict | None = None, floor=None):
    """``predict(thetas (V, k) or None, y0 (V, K, d), max_steps) -> (V, K, T, d + m)``: the paths of G at each of V
    parameter values from each copy's initial states, read as the data are (:meth:`Trajectories.observe`), in one
    solve of at most ``max_steps`` steps; ``cost["steps"]`` (where given) is set to the solver steps it took;
    ``floor`` the noise model's :meth:`~torchmisspec.noise.NoiseModel.resolution`, the solve's."""
    times, _, _ = trajectories.padded()
    K = trajectories.num_experiments
    times = times if times.dim() == 2 else times.expand(K, -1)
    controls = trajectories.controls

    def predict(thetas, y0, max_steps=MAX_STEPS):
        V = y0.shape[0]
        rhs = system.known_rhs if thetas is None else system.copies_rhs(thetas)

        repeated = None if controls is None else controls.repeat(V)
        rtol, atol = FITTING_TOLERANCES
        solver = dict(rtol=rtol, atol=atol, max_steps=max_steps, what="the known model's fit", floor=floor)
        pred, nfe = _solve_rhs(system, rhs, y0.reshape(V * K, -1), times.repeat(V, 1), repeated, **solver)
        if cost is not None:
            cost["steps"] = nfe / EVALS_PER_STEP
        return trajectories.observe(pred.reshape(V, K, *pred.shape[1:]))

    return predict


def _observed(trajectories: Trajectories):
    """``(values (K, T, d + m), seen (K, T, d + m))``: the measured values and where they are (each experiment's
    first row included: where its initial state is estimated, the first values are data like any other)."""
    values, mask = trajectories.observed_values()
    return values, torch.isfinite(values) & mask.unsqueeze(-1)


def fit_known_model(
    system, trajectories: Trajectories, free: torch.Tensor, noise, *, start=None, theta_start=None
) -> KnownFit:
    """The known model alone fitted to ``trajectories`` (the module's notes): G's uncertain parameters (from
    ``theta_start``, default their prior mean) and the ``free (K, d)`` entries of the initial states (from ``start
    (K, d)``, default
    ``trajectories.initial_conditions``; the others are kept), the residuals those of the
    :class:`~torchmisspec.noise.NoiseModel` ``noise``. Raises :class:`FittingError` when G cannot be integrated from
    the start."""
    priors = system.parameters
    y_start = trajectories.initial_conditions if start is None else start
    kd = dict(dtype=y_start.dtype, device=y_start.device)
    k = 0 if priors is None else len(priors)
    m_theta = None if not k else priors.mean.to(**kd)
    s_theta = None if not k else priors.scale.to(**kd)
    values, seen = _observed(trajectories)
    d = y_start.shape[-1]
    seen[:, 0, :d] &= free  # a given first value is where the path starts, not a residual
    target = noise.transform(values)[seen]  # elementwise per component (a count's unit is per component)
    comp = torch.arange(values.shape[-1], device=values.device).expand_as(values)[seen]
    exp = torch.arange(values.shape[0], device=values.device).view(-1, 1, 1).expand_as(values)[seen]
    cols = free.any(0).nonzero().flatten().tolist()  # state components with a free entry somewhere
    size = observed_rms(torch.where(torch.isfinite(y_start), y_start, torch.zeros_like(y_start)))
    size = torch.where(size > 0, size, torch.ones_like(size))
    solved = {"steps": 0.0}
    predict = _predictor(system, trajectories, solved, noise.resolution(trajectories))
    K, d = y_start.shape

    def unpack(z):  # (V, p) -> thetas (V, k) or None, y0 (V, K, d)
        thetas = None if not k else m_theta + s_theta * z[:, :k]
        y0 = y_start.expand(z.shape[0], K, d).clone()
        if cols:
            off = z[:, k:].reshape(z.shape[0], K, len(cols))
            for c, j in enumerate(cols):
                y0[:, :, j] = y0[:, :, j] + free[:, j].to(off) * off[:, :, c] * size[j]
        return thetas, y0

    def residuals(z, max_steps=MAX_STEPS):  # (V, p) -> (V, n): prediction - observation in the noise model's space
        pred = noise.transform(predict(*unpack(z), max_steps))[:, seen]  # (inf where not finite)
        r = pred - target
        return torch.where(torch.isfinite(r), r, torch.full_like(r, math.inf))

    p = k + K * len(cols)
    unknowns = tuple(("theta", i) for i in range(k)) + tuple(("state", e, j) for e in range(K) for j in cols)
    z = torch.zeros(p, **kd)
    if k and theta_start is not None:
        z[:k] = (theta_start.to(**kd) - m_theta) / s_theta
    active = torch.ones(p, dtype=torch.bool, device=kd["device"])
    if cols:  # an entry that is not free is not a parameter (its column stays 0)
        active[k:] = free[:, cols].reshape(-1)
    try:
        r = residuals(z[None])[0]
    except IntegrationError as exc:
        why = str(exc)[:160]
        raise FittingError(f"the known model cannot be integrated from the start of its fit ({why})") from exc
    if not bool(torch.isfinite(r).all()):
        raise FittingError("the known model's paths from the start of its fit are not finite where measured")

    weights = component_weights(comp, values.shape[-1])

    def jacobian(z, r):
        zs = z.expand(k + len(cols), p).clone()
        for i in range(k):
            zs[i, i] += STEP
        for c in range(len(cols)):  # one copy moves component cols[c] of every experiment's initial state
            zs[k + c, k + c :: len(cols)] += STEP
        R = residuals(zs)
        J = torch.zeros(r.shape[0], p, **kd)
        J[:, :k] = ((R[:k] - r) / STEP).T
        for c in range(len(cols)):
            diff = (R[k + c] - r) / STEP
            J[torch.arange(r.shape[0]), k + exp * len(cols) + c] = diff
        J = torch.where(torch.isfinite(J), J, torch.zeros_like(J))
        return J * active.to(J)

    if p == 0:  # nothing to fit: the known model as declared, from the given initial states
        return _result(z, r, weights(r), k, m_theta, s_theta, unpack, None, active, None, comp, values.shape[-1])

    penalty = torch.cat([torch.ones(k, **kd), torch.zeros(p - k, **kd)])
    z, r, w = _damped_steps(z, r, residuals, jacobian, weights, active, penalty, solved)
    described = (unknowns, torch.cat([s_theta if k else z.new_zeros(0), size[cols].repeat(K)]))
    return _result(z, r, w, k, m_theta, s_theta, unpack, jacobian, active, penalty, comp, values.shape[-1], described)


def component_weights(comp: torch.Tensor, num_components: int):
    """``weights(r) -> 1 / s_j^2`` for each residual ``r`` of component ``comp``: each component's mean square at
    the current point (its noise variance estimated with the fit, as maximum likelihood with unknown variances)."""

    def weights(r):
        ms = torch.zeros(num_components, dtype=r.dtype, device=r.device).index_add_(0, comp, r.pow(2))
        count = torch.zeros(num_components, dtype=r.dtype, device=r.device).index_add_(0, comp, torch.ones_like(r))
        ms = ms / count.clamp_min(1)
        floor = 1e-12 * float(ms.max()) + torch.finfo(r.dtype).tiny
        return 1 / ms.clamp_min(floor)[comp]

    return weights


def component_scale(r: torch.Tensor, comp: torch.Tensor, num_components: int) -> torch.Tensor:
    """``(num_components,)`` each component's root mean square residual (NaN where it has none)."""
    ms = torch.zeros(num_components, dtype=r.dtype, device=r.device).index_add_(0, comp, r.pow(2))
    count = torch.zeros(num_components, dtype=r.dtype, device=r.device).index_add_(0, comp, torch.ones_like(r))
    return torch.where(count > 0, (ms / count.clamp_min(1)).sqrt(), torch.full_like(ms, math.nan))


def _damped_steps(z, r, residuals, jacobian, weights, active, penalty, solved):
    """Levenberg-Marquardt from ``z`` (residuals ``r``) on ``sum w r^2 + sum penalty z^2``, ``w = weights(r)``
    refreshed after each accepted step: ``(z, r, w)`` at the end. A trial step that cannot be integrated within its
    step budget (:func:`~torchmisspec._ode.trial_budget` of ``solved["steps"]``, the current point's solver steps),
    or does not lower the misfit, is rejected and the damping raised; a Jacobian that cannot be formed ends the fit
    there."""

    def misfit(r, w, z):
        return float((w * r.pow(2)).sum()) + float((penalty * z.pow(2)).sum())

    lam, w, steps = 1e-3, weights(r), solved["steps"]
    for _ in range(ITERATIONS):
        try:
            J = jacobian(z, r)
        except IntegrationError:  # a column's solve failed: stop at the current point
            break
        A = J.T @ (w[:, None] * J) + torch.diag(penalty)
        g = J.T @ (w * r) + penalty * z
        A = A + torch.diag((~active).to(A))  # entries that are not parameters: identity rows, no step
        base, cost = misfit(r, w, z), math.inf
        for _ in range(8):
            trial = z - torch.linalg.solve(A + lam * torch.diag(A.diagonal() + 1e-12), g) * active.to(g)
            try:
                rt = residuals(trial[None], trial_budget(steps, MAX_STEPS))[0]
                cost = misfit(rt, w, trial) if bool(torch.isfinite(rt).all()) else math.inf
            except IntegrationError:  # a trial step that cannot be integrated is rejected
                cost = math.inf
            if cost < base:
                break
            lam = min(lam * 10.0, 1e10)
        if not cost < base:
            break
        z, r, lam, steps = trial, rt, max(lam * 0.3, 1e-9), solved["steps"]
        settled = (base - cost) <= TOLERANCE * base
        w_new = weights(r)
        settled, w = settled and bool(torch.allclose(w_new, w, rtol=1e-3)), w_new
        if settled:
            break
    return z, r, w


def _result(z, r, w, k, m_theta, s_theta, unpack, jacobian, active, penalty, comp, e, described=None) -> KnownFit:
    """The fit's :class:`KnownFit` at ``z``: theta's Laplace covariance (the initial states marginalised, and held
    fixed), the initial states, each component's residual scale, and the unknowns' covariance (``described``:
    ``(unknowns, units)``)."""
    thetas, y0 = unpack(z[None])
    cov = fixed = full = None
    if z.numel():
        try:
            J = jacobian(z, r)
        except IntegrationError:
            J = None
        if J is not None:
            A = J.T @ (w[:, None] * J) + torch.diag(penalty) + torch.diag((~active).to(J))
            try:
                full = torch.cholesky_inverse(torch.linalg.cholesky(A)) * active.to(A)[:, None] * active.to(A)
            except torch.linalg.LinAlgError:
                full = None
    if k:
        scale = s_theta[:, None] * s_theta[None, :]
        cov = fixed = torch.diag(s_theta**2)
        if full is not None:
            cov = full[:k, :k] * scale
            fixed = torch.cholesky_inverse(torch.linalg.cholesky(A[:k, :k])) * scale
    scale = component_scale(r, comp, e)
    theta = None if thetas is None else thetas[0]
    unknowns, units = described if described is not None else ((), None)
    return KnownFit(
        theta=theta,
        covariance=cov,
        fixed=fixed,
        initial_states=y0[0],
        scale=scale,
        unknowns=unknowns,
        units=units,
        unknowns_covariance=full,
        num_residuals=int(r.numel()),
    )


#: The known model's stand-in as a correction: a GP whose prior variance is this fraction of the samples' variance
#: (its posterior mean and variance are F = 0 to this relative precision), so that F = 0 is a fitted model like any
#: other (predicted, drawn, saved and loaded as one).
KNOWN_MODEL_OUTPUTSCALE = 1e-12


def known_model_template(samples) -> CorrectionGP:
    """The known model alone (F = 0) as a :class:`CorrectionGP` template: an RBF of the samples' median distance whose
    output scale is :data:`KNOWN_MODEL_OUTPUTSCALE` times the samples' variance, its noise that variance (nothing
    learned: fitting it conditions on the samples, and its mean and draws are 0 to that precision)."""
    var = float(samples.targets.detach().double().pow(2).mean())
    var = var if math.isfinite(var) and var > 0 else 1.0
    return CorrectionGP(
        lengthscale=median_distance(samples.inputs),
        outputscale=KNOWN_MODEL_OUTPUTSCALE * var,
        noise_variance=var,
        device=samples.inputs.device,
    )


# ---- held-out later times ----------------------------------------------------------------------------------------
def time_split(trajectories: Trajectories) -> tuple[Trajectories, torch.Tensor] | None:
    """``(the earlier times, keep)``: every experiment of at least :data:`MIN_SPLIT` times cut after the first
    :data:`KEEP` of them (rounded up), shorter ones kept whole, and the ``(K,)`` number of times each keeps; ``None``
    when no experiment is long enough (nothing to hold out)."""
    lengths = torch.tensor(trajectories.lengths)
    keep = torch.where(lengths >= MIN_SPLIT, torch.ceil(lengths * KEEP).long(), lengths)
    if bool((keep == lengths).all()):
        return None
    times = [t[:n] for (t, _), n in zip(trajectories.experiments(), keep.tolist(), strict=True)]
    states = [y[:n] for (_, y), n in zip(trajectories.experiments(), keep.tolist(), strict=True)]
    readings = None
    if trajectories.readings is not None:
        listed = trajectories.readings if trajectories.is_ragged else list(trajectories.readings)
        readings = [r[:n] for r, n in zip(listed, keep.tolist(), strict=True)]
    early = Trajectories(
        times,
        states,
        state_names=trajectories.state_names,
        controls=trajectories.controls,
        initial_states=trajectories.initial_states,
        readout=trajectories.readout,
        readings=readings,
    )
    return early, keep


def held_out(trajectories: Trajectories, keep: torch.Tensor) -> torch.Tensor:
    """``(K, T, d + m)`` where the held-out values are: measured, and past each experiment's first ``keep``
    times (:func:`time_split`)."""
    values, seen = _observed(trajectories)
    late = torch.arange(values.shape[1], device=values.device).view(1, -1) >= keep.to(values.device).view(-1, 1)
    return seen & late.unsqueeze(-1)


def forecast_score(system, field, trajectories: Trajectories, initial_states, keep, noise, scale) -> torch.Tensor:
    """``(K,)`` the misfit of a model's forecast of each experiment's held-out later times (those past its first
    ``keep``): the path of ``field(y, t, u)`` (``system``'s solver conventions) from ``initial_states (K, d)`` over
    every time, its residuals in ``noise``'s space at the held-out measured values, each divided by ``scale``
    (``(d + m,)``, the same for the models compared), summed in squares per experiment; ``inf`` everywhere when the
    forecast cannot be integrated."""
    times, _, _ = trajectories.padded()
    K = trajectories.num_experiments
    times = times if times.dim() == 2 else times.expand(K, -1)
    rtol, atol = FITTING_TOLERANCES
    try:
        pred, _ = _solve_rhs(
            system, field, initial_states, times, trajectories.controls, rtol=rtol, atol=atol,
            max_steps=MAX_STEPS, what="the held-out forecast", floor=noise.resolution(trajectories),
        )  # fmt: skip
    except IntegrationError:
        return torch.full((K,), math.inf, dtype=torch.float64)
    values, held = _observed(trajectories)[0], held_out(trajectories, keep)
    pred = trajectories.observe(pred)
    r = (noise.transform(pred) - noise.transform(values)) / scale.to(values)
    per = torch.where(held, r, torch.zeros((), dtype=r.dtype, device=r.device)).pow(2).sum((1, 2))
    per = torch.where(torch.isfinite(per), per, torch.full_like(per, math.inf))
    return per.detach().cpu().to(torch.float64)


#: the known model fails its own forecast check (:func:`forecast_check`) below this p-value
CHECK_LEVEL = 0.05


def forecast_check(system, fit: KnownFit, trajectories: Trajectories, keep, noise) -> tuple[float, float]:
    """The p-value of the known model's forecast of the held-out later times (those past each experiment's first
    ``keep``) under its own predictive distribution: ``fit`` (:func:`fit_known_model` on the earlier times) predicts
    them with errors of covariance ``C = D + J Sigma J^T``, D each component's residual variance of the fit (its
    mean square times n / (n - p), the unknowns' share), J the forecast's Jacobian in the unknowns and Sigma their
    Laplace covariance (an unknown the earlier times hardly determine widens the forecast it drives). Returns
    ``(p, Q / n)``: under the model, ``Q / n = r^T C^-1 r / n`` over the n held-out values is F-distributed with
    (n, residuals - unknowns) degrees of freedom (D is estimated), and a small p-value says the known model cannot
    forecast these data, so that a correction may; ``Q / n`` is how much wider than predicted its forecast errors
    were (1 when its bands are right). ``(nan, nan)`` with nothing held out; ``(0, inf)`` when the forecast cannot be
    integrated."""
    values, held = _observed(trajectories)[0], held_out(trajectories, keep)
    n_held = int(held.sum())
    if n_held == 0:
        return math.nan, math.nan
    p = len(fit.unknowns)
    thetas = None if fit.theta is None else fit.theta.expand(1 + p, -1).clone()
    y0 = fit.initial_states.expand(1 + p, *fit.initial_states.shape).clone()
    for i, what in enumerate(fit.unknowns):  # copy 1 + i: unknown i moved by STEP of its unit
        if what[0] == "theta":
            thetas[1 + i, what[1]] += STEP * fit.units[i]
        else:
            y0[1 + i, what[1], what[2]] += STEP * fit.units[i]
    try:
        predict = _predictor(system, trajectories, floor=noise.resolution(trajectories))
        pred = noise.transform(predict(thetas, y0))[:, held]  # (1 + p, n_held)
    except IntegrationError:
        return 0.0, math.inf
    r = pred[0] - noise.transform(values)[held]
    comp = torch.arange(values.shape[-1], device=values.device).expand_as(values)[held]
    dof = fit.num_residuals / max(fit.num_residuals - p, 1)
    variance = torch.nan_to_num(fit.scale.pow(2) * dof, nan=math.inf)[comp]
    C = torch.diag(variance)
    if p and fit.unknowns_covariance is not None:
        J = (pred[1:] - pred[0]) / STEP  # (p, n_held)
        C = C + J.T @ fit.unknowns_covariance.to(J) @ J
    if not bool(torch.isfinite(r).all() and torch.isfinite(C).all()):
        return 0.0, math.inf
    try:
        L = torch.linalg.cholesky(C)
    except torch.linalg.LinAlgError:
        return 0.0, math.inf
    ratio = float(torch.cholesky_solve(r[:, None], L).squeeze(-1) @ r) / n_held
    return f_survival(ratio, n_held, max(fit.num_residuals - p, 1)), ratio


def f_survival(x: float, d1: float, d2: float) -> float:
    """P(X > x) for X ~ F(d1, d2): the regularized incomplete beta function I_{d2 / (d2 + d1 x)}(d2 / 2, d1 / 2)."""
    if not x > 0:
        return 1.0
    return betainc(d2 / 2, d1 / 2, d2 / (d2 + d1 * x))


def betainc(a: float, b: float, x: float) -> float:
    """The regularized incomplete beta function I_x(a, b), by its continued fraction (modified Lentz), on the side
    where it converges fast (Numerical Recipes, 3rd ed., section 6.4)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    if x > (a + 1) / (a + b + 2):  # the symmetric side converges faster
        return 1.0 - betainc(b, a, 1.0 - x)
    tiny, c, d = 1e-300, 1.0, 1.0 - (a + b) * x / (a + 1)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        for numerator in (
            m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
            -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1)),
        ):
            d = 1.0 + numerator * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + numerator / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-14:
            break
    return math.exp(log_front) * h / a
