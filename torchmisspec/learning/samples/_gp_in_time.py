"""The Gaussian process in time (:mod:`torchmisspec.learning.samples.observations`): dy/dt by :func:`gp_derivative`, and
the state-noise level it finds in the data (:func:`estimate_state_noise`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..._errors import InputError
from ..._linalg import cholesky, cholesky_or_fail, logdet_from_cholesky
from ..._optim import maximise
from ..._validation import check_positive_int
from ...data import Trajectories
from ...parallel import adaptive_threads
from ._stencils import _finite_derivative, _states_and_times


class GPDerivative(NamedTuple):
    """What :func:`gp_derivative` returns.

    Attributes:
        mean: ``(K, T, d)`` posterior mean of dy/dt at the sample times.
        variance: ``(K, T, d)`` posterior variance of dy/dt at the sample times.
        lengthscale: ``(d,)`` time lengthscale of each component (in the units of the times).
        outputscale: ``(d,)`` prior variance of each (mean-subtracted) component, in state units squared.
        noise: ``(d,)`` measurement-noise variance of each component, in state units squared.
    """

    mean: torch.Tensor
    variance: torch.Tensor
    lengthscale: torch.Tensor
    outputscale: torch.Tensor
    noise: torch.Tensor


#: Fewest samples per trajectory :func:`gp_derivative` accepts.
GP_MIN_SAMPLES = 4
#: Noise-variance floor of the GP in time, relative to each component's variance (keeps K + s I well conditioned
#: on noise-free data; a state noise of 1e-5 relative std is below what any recording resolves).
_GP_NOISE_FLOOR = 1e-10


def _rbf_parts(times: torch.Tensor, log_params: torch.Tensor, pair: torch.Tensor | None = None):
    """Kernel pieces for times ``(K, T)`` and log-parameters ``(d, 3)`` [lengthscale, outputscale, noise].

    Returns ``(Kn, dK, ell2, os)``: ``Kn (d, K, T, T)`` = k(t, t') + s I, ``dK (d, K, T, T)`` = d/dt k(t, t').
    ``pair (K, T, T)``, when given, marks the pairs of observed samples of padded (ragged) experiments: the padded
    samples are decoupled (identity rows of ``Kn``, zero rows and columns of ``dK``), so with zero padded targets
    they add nothing to the likelihood or the posterior.
    """
    ell2 = torch.exp(2 * log_params[:, 0]).view(-1, 1, 1, 1)
    os = torch.exp(log_params[:, 1]).view(-1, 1, 1, 1)
    noise = (_GP_NOISE_FLOOR + torch.exp(log_params[:, 2])).view(-1, 1, 1, 1)
    diff = (times.unsqueeze(-1) - times.unsqueeze(-2)).unsqueeze(0)  # (1, K, T, T): t_i - t_j
    k = os * torch.exp(-0.5 * diff**2 / ell2)
    eye = torch.eye(times.shape[-1], dtype=times.dtype, device=times.device)
    Kn, dK = k + noise * eye, -diff / ell2 * k
    if pair is not None:
        Kn = torch.where(pair, Kn, eye)
        dK = torch.where(pair, dK, torch.zeros((), dtype=dK.dtype, device=dK.device))
    return Kn, dK, ell2, os


def _gp_neg_mll(
    times: torch.Tensor, z: torch.Tensor, log_params: torch.Tensor, pair: torch.Tensor | None = None
) -> torch.Tensor:
    """Negative log marginal likelihood per component ``(d,)``, summed over the K experiments; ``z (d, K, T)``.

    A component whose factorization fails gets ``inf``."""
    Kn, _, _, _ = _rbf_parts(times, log_params, pair)
    L, failed = cholesky_or_fail(Kn)  # failed: (d, K)
    failed = failed.any(-1)  # (d,)
    a = torch.cholesky_solve(z.unsqueeze(-1), L).squeeze(-1)
    logdet = logdet_from_cholesky(L)  # (d, K)
    value = (0.5 * (z * a).sum(-1) + 0.5 * logdet).sum(-1)
    return torch.where(failed, torch.full_like(value, float("inf")), value)


@adaptive_threads()
def gp_derivative(states, times, *, max_iter: int = 50) -> GPDerivative:
    """dy/dt by a Gaussian process in time fitted to each state component.

    Model: for component j of experiment k, ``y_kj(t) = m_kj + f_kj(t) + e``, with ``m_kj`` the trajectory's mean
    (subtracted: a constant mean per trajectory, so that experiments at different levels share one prior),
    ``f_kj ~ GP(0, s_j^2 exp(-(t - t')^2 / (2 l_j^2)))`` and i.i.d. measurement noise ``e ~ N(0, n_j)``. The
    squared-exponential (RBF) kernel is used because ODE solutions of smooth fields are infinitely differentiable,
    which is exactly the RBF prior's smoothness; a Matern 5/2 prior would put mass on rough paths and, with a
    shared lengthscale, mostly trade bias for variance at the sample points. The three hyperparameters of
    component j are shared by all its experiments and maximise one exact marginal likelihood summed over the
    experiments (experiments may have different grids ``(K, T)``); they are optimised in log space by L-BFGS from
    the best point of a small grid of lengthscales and noise levels (ML-II can still oversmooth: check with
    :func:`~torchmisspec.learning.samples.observations.estimator_error`). The estimate is the posterior mean of dy/dt at
    the sample times,
    ``d/dt k(t*, t) @ (K + n I)^-1 (y - m)``, with posterior variance
    ``s^2 / l^2 - dk^T (K + n I)^-1 dk``. All K x d Cholesky factorizations are batched; the computation runs in
    float64 and the results come back in the states' dtype. NaN states are missing entries: they are left out of
    the likelihood and the conditioning (each component's posterior uses its own observed entries), and the posterior
    of dy/dt is returned at every time, observed or not.

    Args:
        states: ``(K, T, d)`` (NaN: missing; at least :data:`GP_MIN_SAMPLES` observed per experiment and component).
        times: ``(T,)`` or ``(K, T)``, strictly increasing.
        max_iter: most L-BFGS iterations.

    Returns:
        :class:`GPDerivative` (mean, variance, and the hyperparameters per component).

    Raises:
        InputError: infinite values, non-increasing times, fewer than :data:`GP_MIN_SAMPLES` samples, or a state
            component that is constant in every experiment (the GP in time has nothing to fit).
    """
    max_iter = check_positive_int(max_iter, "max_iter")
    states, times = _states_and_times(states, times)
    observed = torch.isfinite(states)
    mask = None if bool(observed.all()) else observed
    return _gp_time(states, times.expand(states.shape[0], -1), mask, max_iter)


#: entries of the covariance matrices evaluated at once by the start grid of :func:`_gp_time` (its memory: many
#: experiments of many times would otherwise hold every grid point's K T x T matrices together)
GRID_BATCH_ENTRIES = 2**24


@dataclass(frozen=True)
class _Standardised:
    """The states the GP in time is fitted to: the times ``t (K, T)`` in float64, each trajectory's mean ``level
    (K, 1, d)`` subtracted and each component divided by its ``scale (d,)`` (``z (d, K, T)``, unit variance,
    unobserved entries 0); the observed entries per component ``m (d, K, T)`` and their pairs ``pair (d, K, T, T)``
    (``None`` when all are observed), the samples with an observed component ``rows (K, T)``, and the states' dtype."""

    t: torch.Tensor
    z: torch.Tensor
    level: torch.Tensor
    scale: torch.Tensor
    m: torch.Tensor | None
    pair: torch.Tensor | None
    rows: torch.Tensor
    dtype: torch.dtype


def _gp_time(
    states: torch.Tensor,
    times: torch.Tensor,
    mask: torch.Tensor | None,
    max_iter: int,
    *,
    values: bool = False,
):
    """:func:`gp_derivative` on ``states (K, T, d)``, ``times (K, T)``; ``mask`` marks the observed entries: ``(K, T)``
    the samples of padded ragged experiments, ``(K, T, d)`` per component (missing entries, padding); ``None``: all
    observed. Unobserved entries are decoupled from the likelihood; the result holds the posterior at every entry
    (padded ones are meaningless). With ``values``, returns ``(GPDerivative, posterior mean of the states (K, T, d))``.
    """
    K, T, d = states.shape
    if mask is not None and mask.dim() == 2:
        mask = mask.unsqueeze(-1).expand(K, T, d)
    _check_counts(mask, K, T, d, states.device)
    data = _standardised(states, times, mask)
    dt_min, span = _time_range(data)
    start = _grid_start(data, dt_min, span)
    log_params = start.clone().requires_grad_(True)
    lo = torch.tensor([math.log(dt_min / 4), -12.0, -30.0], dtype=torch.float64, device=states.device)
    hi = torch.tensor([math.log(20 * span), 8.0, 2.0], dtype=torch.float64, device=states.device)

    def evaluate() -> tuple[torch.Tensor, torch.Tensor]:
        value = -_gp_neg_mll(data.t, data.z, torch.maximum(torch.minimum(log_params, hi), lo), data.pair).sum()
        # a failed factorization is -inf: no step is taken towards it (and no gradient is formed through it)
        return value, (value if bool(torch.isfinite(value)) else 0.0 * log_params.sum())

    maximise(
        [log_params],
        evaluate,
        max_iter=max_iter,
        normaliser=float(data.rows.sum()),
        tolerance_grad=1e-6,
        tolerance_change=1e-9,
        history_size=10,
        desc="GP in time",
    )
    with torch.no_grad():
        p = torch.maximum(torch.minimum(log_params, hi), lo)
        if not bool(torch.isfinite(_gp_neg_mll(data.t, data.z, p, data.pair)).all()):
            p = start  # the optimiser wandered into a singular corner: keep the grid's best point
        result, fitted = _time_posterior(data, p, values)
    _finite_derivative(result.mean)
    return (result, fitted) if values else result


def _check_counts(mask: torch.Tensor | None, K: int, T: int, d: int, device) -> None:
    """Refuse fewer than :data:`GP_MIN_SAMPLES` observed samples in an experiment (or a component of one)."""
    counts = torch.full((K, d), T, device=device) if mask is None else mask.sum(1)  # (K, d)
    if int(counts.min()) < GP_MIN_SAMPLES:
        k, j = (int(i) for i in (counts == counts.min()).nonzero()[0])
        where = "" if mask is None else f" (experiment {k}" + (f", component {j})" if int(counts[k].min()) < T else ")")
        raise InputError(
            f"derivative='gp': expected at least {GP_MIN_SAMPLES} samples per trajectory, got T={int(counts.min())}"
            + where
        )


def _standardised(states: torch.Tensor, times: torch.Tensor, mask: torch.Tensor | None) -> _Standardised:
    """The states centred per trajectory and scaled per component (:class:`_Standardised`), after refusing a
    component constant in every experiment (the GP in time has nothing to fit)."""
    K, T, d = states.shape
    dtype, device = states.dtype, states.device
    t = times.to(torch.float64)
    if mask is None:
        y = states.to(torch.float64)
        w = torch.ones(K, T, 1, dtype=torch.float64, device=device)
        m = pair = None
        rows = torch.ones(K, T, dtype=torch.bool, device=device)
    else:
        y = torch.where(mask, states, torch.zeros((), dtype=dtype, device=device)).to(torch.float64)
        w = mask.to(torch.float64)
        m = mask.permute(2, 0, 1)  # (d, K, T)
        pair = m.unsqueeze(-1) & m.unsqueeze(-2)  # (d, K, T, T)
        rows = mask.any(-1)  # (K, T): samples with an observed component
    level = (w * y).sum(dim=1, keepdim=True) / w.sum(dim=1, keepdim=True)  # (K, 1, d): each trajectory's mean
    centred = (y - level) * w  # unobserved entries: 0
    scale = (centred.pow(2).sum(dim=(0, 1)) / w.sum(dim=(0, 1)).expand(d)).sqrt()  # (d,)
    constant = (scale <= 1e-12 * (w * y).abs().amax(dim=(0, 1)).clamp_min(1.0)).nonzero().flatten().tolist()
    if constant:
        raise InputError(
            f"states: derivative='gp' needs state components that vary in time, got component(s) {constant} "
            "constant in every experiment; use derivative='central' for them or drop them"
        )
    z = (centred / scale).permute(2, 0, 1).contiguous()  # (d, K, T), unit variance
    return _Standardised(t, z, level, scale, m, pair, rows, dtype)


def _time_range(data: _Standardised) -> tuple[float, float]:
    """``(the shortest step between observed samples, the mean time span of the experiments)``: the bounds of the
    lengthscale's search."""
    t, rows = data.t, data.rows
    big = torch.tensor(math.inf, dtype=torch.float64, device=t.device)
    first = torch.where(rows, t, big).amin(-1)
    last = torch.where(rows, t, -big).amax(-1)
    span = float((last - first).mean())
    dt_min = min(float(t[k][rows[k]].diff().min()) for k in range(t.shape[0]) if int(rows[k].sum()) >= 2)
    return dt_min, span


def _grid_start(data: _Standardised, dt_min: float, span: float) -> torch.Tensor:
    """``(d, 3)``: where L-BFGS starts, the best of a grid of lengthscales x noise levels per component (all in one
    batch, in batches of about :data:`GRID_BATCH_ENTRIES` matrix entries)."""
    t, z, pair = data.t, data.z, data.pair
    d, K, T = z.shape
    device = t.device
    ells = torch.logspace(math.log10(dt_min), math.log10(2 * span), 10, dtype=torch.float64, device=device)
    noises = torch.tensor([1e-8, 1e-5, 1e-3, 1e-1], dtype=torch.float64, device=device)
    grid = torch.cartesian_prod(ells.log(), noises.log())  # (G, 2)
    with torch.no_grad():  # the G grid points x d components
        G = grid.shape[0]
        p = torch.cat([grid[:, :1], torch.zeros_like(grid[:, :1]), grid[:, 1:]], -1).repeat_interleave(d, 0)
        step = max(1, GRID_BATCH_ENTRIES // (d * K * T * T))
        values_ = torch.cat(
            [
                _gp_neg_mll(
                    t,
                    z.repeat(min(step, G - g0), 1, 1),
                    p[g0 * d : (g0 + step) * d],
                    None if pair is None else pair.repeat(min(step, G - g0), 1, 1, 1),
                )
                for g0 in range(0, G, step)
            ]
        ).view(G, d)  # inf where a factorization failed
        return p.view(G, d, 3)[values_.argmin(0), torch.arange(d, device=device)]  # (d, 3)


def _time_posterior(data: _Standardised, p: torch.Tensor, values: bool):
    """``(GPDerivative, posterior mean of the states (K, T, d) or None)``: the posterior of dy/dt (and, with
    ``values``, of the states) at every time given the observed entries, at the log-parameters ``p (d, 3)``, in the
    states' units and dtype."""
    t, z, pair, scale, dtype = data.t, data.z, data.pair, data.scale, data.dtype
    Kn, dK, ell2, os = _rbf_parts(t, p, pair)
    L = cholesky(Kn, what="GP in time: K + noise I")
    a = torch.cholesky_solve(z.unsqueeze(-1), L)  # (d, K, T, 1)
    if pair is not None:  # the posterior at every time, from the observed entries only (unobserved: a = 0)
        diff = (t.unsqueeze(-1) - t.unsqueeze(-2)).unsqueeze(0)
        k = os * torch.exp(-0.5 * diff**2 / ell2)
        col = data.m.unsqueeze(-2)  # (d, K, 1, T)
        zero = torch.zeros((), dtype=k.dtype, device=k.device)
        dK = torch.where(col, -diff / ell2 * k, zero)
        k = torch.where(col, k, zero)
    mean = (dK @ a).squeeze(-1)  # (d, K, T)
    V = torch.linalg.solve_triangular(L, dK.transpose(-1, -2), upper=False)  # L^-1 dk_i in column i
    var = (os.squeeze(-1) / ell2.squeeze(-1) - V.pow(2).sum(-2)).clamp_min(0.0)
    s2 = scale.view(-1, 1, 1) ** 2
    result = GPDerivative(
        mean=(mean * scale.view(-1, 1, 1)).permute(1, 2, 0).to(dtype),
        variance=(var * s2).permute(1, 2, 0).to(dtype),
        lengthscale=torch.exp(p[:, 0]).to(dtype),
        outputscale=(torch.exp(p[:, 1]) * scale**2).to(dtype),
        noise=((_GP_NOISE_FLOOR + torch.exp(p[:, 2])) * scale**2).to(dtype),
    )
    if not values:
        return result, None
    if pair is None:
        diff = (t.unsqueeze(-1) - t.unsqueeze(-2)).unsqueeze(0)
        k = os * torch.exp(-0.5 * diff**2 / ell2)
    return result, ((k @ a).squeeze(-1).permute(1, 2, 0) * scale + data.level).to(dtype)  # (K, T, d)


def estimate_state_noise(trajectories: Trajectories) -> torch.Tensor | None:
    """``(d,)`` the standard deviation of the measurement noise on each state component, as the GP in time
    (:func:`gp_derivative`) finds it in the data (floored at 1e-5 of each component's standard deviation), or
    ``None`` when an experiment has fewer than :data:`GP_MIN_SAMPLES` observations or a component is constant.

    What :meth:`CorrectedODE.calibrate <torchmisspec.CorrectedODE.calibrate>` assumes by default, so that noisy
    observations are compared with bands of noisy observations (the bands it calibrates are for the states)."""
    if min(trajectories.lengths) < GP_MIN_SAMPLES:
        return None
    if trajectories.is_partial:  # each component from the experiments that measure it; 0 where none does
        measured = trajectories.measured
        parts = []
        for j in range(trajectories.state_dim):
            ks = measured[:, j].nonzero().flatten().tolist()
            if not ks:
                parts.append(torch.zeros(1, dtype=trajectories.dtype, device=trajectories.device))
                continue
            sub = trajectories[ks]
            one = Trajectories(
                list(sub.times) if sub.is_ragged else sub.times,
                [y[:, j : j + 1] for y in sub.states] if sub.is_ragged else sub.states[..., j : j + 1],
            )
            std = estimate_state_noise(one)
            if std is None:
                return None
            parts.append(std)
        return torch.cat(parts)
    times, states, mask = trajectories.padded()
    if trajectories.has_missing:
        mask = torch.isfinite(states) & mask.unsqueeze(-1)
    try:
        var = _gp_time(states, times, mask if trajectories.is_ragged or trajectories.has_missing else None, 50).noise
    except InputError:  # a constant component or too few observations: nothing to estimate from
        return None
    floor = 1e-10 * observed_variance(trajectories.flat_states()).clamp_min(torch.finfo(var.dtype).tiny)
    return torch.maximum(var.to(states), floor.to(states)).sqrt()


def estimate_observed_noise(trajectories: Trajectories) -> torch.Tensor | None:
    """``(d + m,)`` :func:`estimate_state_noise` of the states, then the same estimate for the readings of
    :attr:`Trajectories.readout <torchmisspec.Trajectories.readout>` from the experiments that read them (a reading
    read too rarely for the GP in time: its values taken as 1 % accurate); ``None`` when either estimate is."""
    states = estimate_state_noise(trajectories)
    if trajectories.readout is None or states is None:
        return states
    values = trajectories.readings
    per = list(values) if isinstance(values, tuple) else list(values.unbind(0))
    times = [t for t, _ in trajectories.experiments()]
    kept = [k for k, r in enumerate(per) if bool(torch.isfinite(r).any())]
    read = Trajectories([times[k] for k in kept], [per[k] for k in kept], state_names=trajectories.readout.names)
    std = estimate_state_noise(read)
    if std is None:
        return None
    return torch.cat([states, torch.where(std > 0, std, 1e-2 * observed_rms(read.flat_states())).to(states)])


def observed_variance(flat: torch.Tensor) -> torch.Tensor:
    """``(d,)`` the unbiased variance of each column of ``flat (N, d)`` over its observed (non-NaN) entries."""
    seen = torch.isfinite(flat)
    n = seen.sum(0).clamp_min(2)
    zero = torch.zeros((), dtype=flat.dtype, device=flat.device)
    mean = torch.where(seen, flat, zero).sum(0) / n
    return torch.where(seen, flat - mean, zero).pow(2).sum(0) / (n - 1)


def observed_rms(flat: torch.Tensor) -> torch.Tensor:
    """``(d,)`` the root mean square of each column of ``flat (N, d)`` over its observed (non-NaN) entries; a column
    whose values are all 0 (an empty compartment at the start) gets the largest column's, as a size for steps and
    weights."""
    seen = torch.isfinite(flat)
    zero = torch.zeros((), dtype=flat.dtype, device=flat.device)
    rms = (torch.where(seen, flat, zero).pow(2).sum(0) / seen.sum(0).clamp_min(1)).sqrt()
    return torch.where(rms > 0, rms, rms.max()).clamp_min(torch.finfo(flat.dtype).tiny)
