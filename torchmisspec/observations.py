"""Samples of the missing term F from observed trajectories: derivative estimators and :func:`correction_samples`.

The correction is never observed directly. From states ``y`` observed at times ``t`` we estimate ``dy/dt`` and
form the samples ``F~ = dy/dt - G(y)`` at the observed states, restricted to the components F acts on and
paired with the components F depends on. The derivative estimators:

* ``"oracle"``: the paper's observation model, the exact ``dy/dt = G(y) + F(y)`` plus Gaussian noise (simulation
  and benchmark systems only, since it needs the true F);
* ``"central"``: :func:`finite_difference`, exact Lagrange (Fornberg) weights on local, possibly non-uniform
  stencils, second or fourth order everywhere, end points included;
* ``"smooth"``: :func:`smoothed_derivative`, a local polynomial least-squares fit (Savitzky-Golay generalised to
  non-uniform grids) for noisy states;
* ``"gp"``: :func:`gp_derivative`, the posterior mean of dy/dt under a Gaussian process in time per state
  component (hyperparameters by marginal likelihood shared across experiments); its posterior variance becomes
  the samples' per-sample noise variance;
* ``"auto"`` (the default of :func:`correction_samples`): the estimator among ``central`` / ``smooth`` / ``gp``
  (several settings) with the smallest :func:`estimator_error`, chosen by :func:`choose_derivative`; a
  :class:`~torchmisspec.TorchMisspecWarning` is issued when even the best one is unreliable
  (ratio > :data:`ESTIMATOR_ERROR_THRESHOLD`).

:func:`estimator_error` is the self-check that needs no truth: the estimator's error on trajectories of the known
model G (where dy/dt = G(y) exactly), simulated from the observed initial states on the observed grids with the
state-noise level the GP in time finds in the data, relative to the size of the correction samples.

**Missing entries** (NaN states, see :class:`~torchmisspec.Trajectories`): every estimator fits each component
from its own observed times only (the stencil of a time is the nearest observed samples of that component; the GP in
time conditions on the observed entries), and returns a derivative at every time, observed or not.
:func:`correction_samples` explains how a sample at a time with a missing component is formed.

Every function is vectorised over experiments and state components, follows the dtype and device of the states,
and raises :class:`~torchmisspec._errors.InputError` / :class:`~torchmisspec._errors.ShapeError` on bad input.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ._errors import InputError, IntegrationError, ShapeError, TorchMisspecWarning, warn
from ._linalg import cholesky, cholesky_or_fail, logdet_from_cholesky
from ._missing import check_counts, local_fit
from ._threads import adaptive_threads
from ._validation import check_finite, check_positive_int, check_real, states_and_times
from .data import Trajectories, simulate, simulate_known_each
from .systems import MisspecifiedSystem

__all__ = [
    "AUTO_CANDIDATES",
    "DERIVATIVE_ESTIMATORS",
    "ESTIMATOR_ERROR_THRESHOLD",
    "GP_MIN_SAMPLES",
    "CorrectionSamples",
    "GPDerivative",
    "choose_derivative",
    "correction_samples",
    "estimate_state_noise",
    "estimator_error",
    "finite_difference",
    "gp_derivative",
    "smoothed_derivative",
]

#: Names accepted by ``correction_samples(derivative=...)``.
DERIVATIVE_ESTIMATORS = ("auto", "oracle", "central", "smooth", "gp")

_FD_ORDERS = (2, 4)


# ---------------------------------------------------------------------------------------------------------------
# Shared helpers
def _states_and_times(states, times) -> tuple[torch.Tensor, torch.Tensor]:
    """The shared states/times check (NaN states are missing entries); the times come back as ``(1, T)`` (shared
    grid) or ``(K, T)``."""
    states, times = states_and_times(states, times, missing=True)
    return states, times.reshape(-1, states.shape[1])


def _masked(name: str, states: torch.Tensor, times: torch.Tensor, observed: torch.Tensor, options: dict):
    """``(dy/dt, values)`` ``(K, T, d)`` of the stencil estimator ``name`` with missing entries: each component from
    its own observed samples; ``values`` is the local fit's value at every time. ``times (K, T)``."""
    K = states.shape[0]
    times = times.expand(K, -1)
    clean = torch.where(observed, states, torch.zeros((), dtype=states.dtype, device=states.device))
    if name == "central":
        order = options.get("order", 2)
        check_counts(observed, order + 1, f"derivative='central' order={order}")
        values, dydt = local_fit(clean, times, observed, kind="lagrange", width=order + 1)
    else:
        window, degree = options.get("window", 7), options.get("degree", 2)
        check_counts(observed, window, f"derivative='smooth' window={window}")
        values, dydt = local_fit(clean, times, observed, kind="poly", width=window, degree=degree)
    return _finite_derivative(dydt), values


def _finite_derivative(dydt: torch.Tensor) -> torch.Tensor:
    """Refuse derivative estimates that overflowed (times so close that the stencil weights are infinite)."""
    if not bool(torch.isfinite(dydt).all()):
        raise InputError(
            "times: the derivative estimate is not finite: some samples are too close in time for this dtype (the "
            "stencil weights overflow); drop near-duplicate times or use float64"
        )
    return dydt


def _stencil_index(T: int, width: int, device) -> torch.Tensor:
    """``(T, width)`` sample indices of the stencil of every point: centred, shifted inward at the ends."""
    start = (torch.arange(T, device=device) - width // 2).clamp(0, T - width)
    return start.unsqueeze(-1) + torch.arange(width, device=device)


def _apply_stencil(states: torch.Tensor, index: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``sum_j weights[k, i, j] * states[k, index[i, j]]``: states ``(K, T, d)``, index ``(T, m)``, weights
    ``(1 or K, T, m)`` -> ``(K, T, d)``."""
    gathered = states[:, index]  # (K, T, m, d)
    return torch.einsum("ktm,ktmd->ktd", weights.expand(states.shape[0], -1, -1), gathered)


def _lagrange_derivative_weights(dt: torch.Tensor) -> torch.Tensor:
    """Weights w_j = L_j'(t_i) of the derivative of the Lagrange interpolant at the evaluation point.

    Args:
        dt: ``(..., m)`` stencil node offsets t_j - t_i from the evaluation point t_i (one of them is 0).

    Returns:
        ``(..., m)`` weights, exact for polynomials of degree m - 1 (the same weights Fornberg's recursion gives).

    Uses L_j'(x0) = sum_{k != j} 1 / (x_j - x_k) * prod_{l != j, k} (x0 - x_l) / (x_j - x_l) with x - x0 = dt.
    """
    m = dt.shape[-1]
    cols = []
    for j in range(m):
        w = torch.zeros_like(dt[..., 0])
        for k in range(m):
            if k == j:
                continue
            term = 1.0 / (dt[..., j] - dt[..., k])
            for ell in range(m):
                if ell in (j, k):
                    continue
                term = term * (-dt[..., ell]) / (dt[..., j] - dt[..., ell])
            w = w + term
        cols.append(w)
    return torch.stack(cols, dim=-1)


# ---------------------------------------------------------------------------------------------------------------
def finite_difference(states, times, *, order: int = 2) -> torch.Tensor:
    """dy/dt at every sample of every trajectory by finite differences on a possibly non-uniform grid.

    The weights are those of the derivative of the Lagrange interpolant through the local stencil (exact for
    non-uniform spacing; identical to Fornberg's weights), computed for every grid point at once:

    * ``order=2``: 3-point stencils, centred in the interior and one-sided at the two ends (second order
      everywhere);
    * ``order=4``: 5-point stencils, centred in the interior and shifted inward at the two first and two last
      samples (fourth order everywhere).

    NaN states are missing entries: each component's stencils then use its own ``order + 1`` nearest observed
    samples, and a missing entry gets the derivative of the interpolant through them at its time.

    Args:
        states: ``(K, T, d)`` states of K trajectories at T times (NaN: missing).
        times: ``(T,)`` shared by all trajectories, or ``(K, T)`` one grid per trajectory; strictly increasing.
        order: 2 or 4.

    Returns:
        ``(K, T, d)`` derivative estimates, in the dtype and on the device of ``states``.

    Raises:
        ShapeError: ``states`` is not 3-D or ``times`` does not match it.
        InputError: NaN/inf values, non-increasing times, a bad ``order``, or fewer samples than the stencil needs.
    """
    order = check_positive_int(order, "order")
    if order not in _FD_ORDERS:
        raise InputError(f"order: expected one of {list(_FD_ORDERS)}, got {order}")
    states, times = _states_and_times(states, times)
    T = states.shape[1]
    width = order + 1
    if T < width:
        raise InputError(f"order={order} needs at least {width} samples per trajectory, got T={T}")
    observed = torch.isfinite(states)
    if not bool(observed.all()):
        return _masked("central", states, times, observed, {"order": order})[0]
    index = _stencil_index(T, width, states.device)  # (T, m)
    dt = times[:, index] - times.unsqueeze(-1)  # (1 or K, T, m)
    weights = _lagrange_derivative_weights(dt)
    return _finite_derivative(_apply_stencil(states, index, weights))


def smoothed_derivative(states, times, *, window: int = 7, degree: int = 2) -> torch.Tensor:
    """dy/dt of noisy states by local polynomial least squares (Savitzky-Golay on a non-uniform grid).

    At every sample t_i a polynomial of degree ``degree`` in (t - t_i) is fitted by ordinary least squares
    (uniform weights, as in the classic Savitzky-Golay filter) to the ``window`` consecutive samples centred on
    sample i (the window is shifted inward at the ends so that it always holds ``window`` samples); the derivative
    estimate is the fitted linear coefficient. The estimate is a fixed linear combination of the window's states,
    so it is computed as one stencil per grid point, vectorised over trajectories and state components. It is exact
    for polynomials of degree <= ``degree``. NaN states are missing entries: each component's windows then hold its
    own ``window`` nearest observed samples, and a missing entry gets the fit's derivative at its time.

    Args:
        states: ``(K, T, d)`` (NaN: missing).
        times: ``(T,)`` or ``(K, T)``, strictly increasing.
        window: odd number of samples per local fit (>= 3 and > ``degree``).
        degree: polynomial degree (>= 1).

    Returns:
        ``(K, T, d)`` derivative estimates, in the dtype and on the device of ``states``.

    Raises:
        ShapeError: ``states`` is not 3-D or ``times`` does not match it.
        InputError: NaN/inf values, non-increasing times, bad ``window`` / ``degree``, or ``T < window``.
    """
    window = check_positive_int(window, "window")
    degree = check_positive_int(degree, "degree", minimum=0)
    if degree < 1:
        raise InputError(f"degree: expected an integer >= 1 (the derivative is the linear coefficient), got {degree}")
    if window % 2 == 0 or window < 3:
        raise InputError(f"window: expected an odd integer >= 3, got {window}")
    if window <= degree:
        raise InputError(
            f"window: expected more samples than the polynomial degree (window > degree), got window={window} "
            f"and degree={degree}"
        )
    states, times = _states_and_times(states, times)
    T = states.shape[1]
    if T < window:
        raise InputError(f"window={window} needs at least {window} samples per trajectory, got T={T}")
    observed = torch.isfinite(states)
    if not bool(observed.all()):
        return _masked("smooth", states, times, observed, {"window": window, "degree": degree})[0]
    index = _stencil_index(T, window, states.device)  # (T, w)
    dt = times[:, index] - times.unsqueeze(-1)  # (1 or K, T, w)
    scale = dt.abs().amax(dim=-1, keepdim=True)  # (1 or K, T, 1), > 0 since the times are strictly increasing
    powers = torch.arange(degree + 1, device=states.device, dtype=states.dtype)
    X = (dt / scale).unsqueeze(-1) ** powers  # (.., T, w, p+1) scaled Vandermonde, well conditioned
    # Least-squares linear coefficient: beta_1 = e_1^T R^{-1} Q^T y = (Q R^{-T} e_1)^T y.
    Q, R = torch.linalg.qr(X, mode="reduced")
    e1 = torch.zeros((*R.shape[:-1], 1), dtype=states.dtype, device=states.device)
    e1[..., 1, 0] = 1.0
    z = torch.linalg.solve_triangular(R.transpose(-1, -2), e1, upper=False)  # (.., T, p+1, 1)
    weights = (Q @ z).squeeze(-1) / scale  # (.., T, w)
    return _finite_derivative(_apply_stencil(states, index, weights))


# ---------------------------------------------------------------------------------------------------------------
# Gaussian process in time
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
    :func:`estimator_error`). The estimate is the posterior mean of dy/dt at the sample times,
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
    counts = torch.full((K, d), T, device=states.device) if mask is None else mask.sum(1)  # (K, d)
    if int(counts.min()) < GP_MIN_SAMPLES:
        k, j = (int(i) for i in (counts == counts.min()).nonzero()[0])
        where = "" if mask is None else f" (experiment {k}" + (f", component {j})" if int(counts[k].min()) < T else ")")
        raise InputError(
            f"derivative='gp' needs at least {GP_MIN_SAMPLES} samples per trajectory, got T={int(counts.min())}" + where
        )
    dtype, device = states.dtype, states.device
    t = times.to(torch.float64)
    if mask is None:
        y = states.to(torch.float64)
        w = torch.ones(K, T, 1, dtype=torch.float64, device=device)
        pair = None
        rows = torch.ones(K, T, dtype=torch.bool, device=device)
    else:
        y = torch.where(mask, states, torch.zeros((), dtype=dtype, device=device)).to(torch.float64)
        w = mask.to(torch.float64)
        m = mask.permute(2, 0, 1)  # (d, K, T)
        pair = m.unsqueeze(-1) & m.unsqueeze(-2)  # (d, K, T, T)
        rows = mask.any(-1)  # (K, T): samples with an observed component
    n = rows.sum()
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
    big = torch.tensor(math.inf, dtype=torch.float64, device=device)
    first = torch.where(rows, t, big).amin(-1)
    last = torch.where(rows, t, -big).amax(-1)
    span = float((last - first).mean())
    dt_min = min(float(t[k][rows[k]].diff().min()) for k in range(K) if int(rows[k].sum()) >= 2)
    # Start: the best of a grid of lengthscales x noise levels (per component, all in one batch).
    ells = torch.logspace(math.log10(dt_min), math.log10(2 * span), 10, dtype=torch.float64, device=device)
    noises = torch.tensor([1e-8, 1e-5, 1e-3, 1e-1], dtype=torch.float64, device=device)
    grid = torch.cartesian_prod(ells.log(), noises.log())  # (G, 2)
    with torch.no_grad():  # all G grid points x d components in one batch
        G = grid.shape[0]
        p = torch.cat([grid[:, :1], torch.zeros_like(grid[:, :1]), grid[:, 1:]], -1).repeat_interleave(d, 0)
        grid_pair = None if pair is None else pair.repeat(G, 1, 1, 1)
        values_ = _gp_neg_mll(t, z.repeat(G, 1, 1), p, grid_pair).view(G, d)  # inf where a factorization failed
        start = p.view(G, d, 3)[values_.argmin(0), torch.arange(d, device=device)]  # (d, 3)
    log_params = start.clone().requires_grad_(True)
    opt = torch.optim.LBFGS(
        [log_params], lr=1.0, max_iter=max_iter, history_size=10, line_search_fn="strong_wolfe", tolerance_grad=1e-6
    )
    lo = torch.tensor([math.log(dt_min / 4), -12.0, -30.0], dtype=torch.float64, device=device)
    hi = torch.tensor([math.log(20 * span), 8.0, 2.0], dtype=torch.float64, device=device)

    def closure():
        opt.zero_grad()
        value = _gp_neg_mll(t, z, torch.maximum(torch.minimum(log_params, hi), lo), pair).sum() / n
        if torch.isfinite(value):
            value.backward()
        return value

    opt.step(closure)
    with torch.no_grad():
        p = torch.maximum(torch.minimum(log_params, hi), lo)
        if not bool(torch.isfinite(_gp_neg_mll(t, z, p, pair)).all()):
            p = start  # the optimiser wandered into a singular corner: keep the grid's best point
        Kn, dK, ell2, os = _rbf_parts(t, p, pair)
        L = cholesky(Kn, what="GP in time: K + noise I")
        a = torch.cholesky_solve(z.unsqueeze(-1), L)  # (d, K, T, 1)
        if pair is not None:  # the posterior at every time, from the observed entries only (unobserved: a = 0)
            diff = (t.unsqueeze(-1) - t.unsqueeze(-2)).unsqueeze(0)
            k = os * torch.exp(-0.5 * diff**2 / ell2)
            col = m.unsqueeze(-2)  # (d, K, 1, T)
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
        fitted = None
        if values:
            if pair is None:
                diff = (t.unsqueeze(-1) - t.unsqueeze(-2)).unsqueeze(0)
                k = os * torch.exp(-0.5 * diff**2 / ell2)
            fitted = ((k @ a).squeeze(-1).permute(1, 2, 0) * scale + level).to(dtype)  # (K, T, d)
    _finite_derivative(result.mean)
    return (result, fitted) if values else result


# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CorrectionSamples:
    """Noisy samples F~ of the correction at the observed states, flattened over experiments and times.

    Samples run experiment after experiment (sample ``n = k * T + j`` is experiment k at its j-th time when every
    experiment has T samples; ragged data concatenates its experiments likewise).

    Attributes:
        inputs: ``(N, d_in)`` the correction's inputs, ``system.select_inputs(states)``.
        targets: ``(N, d_out)`` the samples ``F~ = select_outputs(dy/dt - G(y))`` (noise included).
        states: ``(N, d)`` the full observed states.
        experiment: ``(N,)`` long tensor, the experiment index k of each sample.
        noise: known per-sample noise variances of the targets, ``(N, d_out)``, or ``None`` when unknown (the
            correction GP then learns one noise variance).
    """

    inputs: torch.Tensor
    targets: torch.Tensor
    states: torch.Tensor
    experiment: torch.Tensor
    noise: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.inputs.shape[0]

    @property
    def num_samples(self) -> int:
        return self.inputs.shape[0]

    @property
    def input_dim(self) -> int:
        return self.inputs.shape[1]

    @property
    def output_dim(self) -> int:
        return self.targets.shape[1]

    def with_shared_noise(self) -> CorrectionSamples:
        """These samples with one known noise variance per sample for every output: the largest of its outputs'
        (conservative). A design conditions one kernel shared by the outputs, so it needs the same noise for each;
        the GP in time (:func:`gp_derivative`) estimates one per output. Unchanged when the noise is unknown or
        already shared."""
        if self.noise is None or bool((self.noise == self.noise[:, :1]).all()):
            return self
        noisiest = self.noise.amax(1, keepdim=True).expand_as(self.noise).contiguous()
        return dataclasses.replace(self, noise=noisiest)


def _check_trajectories_and_system(trajectories, system) -> None:
    if not isinstance(trajectories, Trajectories):
        raise InputError(
            f"trajectories: expected a torchmisspec Trajectories object, got {type(trajectories).__name__}; "
            "wrap arrays with Trajectories(times, states)"
        )
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
    if trajectories.state_dim != system.state_dim:
        names = trajectories.state_names
        raise ShapeError(
            f"trajectories: expected state dimension {system.state_dim} of system '{system.name}', got "
            f"trajectories.state_dim={trajectories.state_dim} (state columns {list(names)}; "
            f"{_describe_states(trajectories)}); load every state component the system has "
            "(Trajectories.load(..., state_columns=[...]) with one column per component, in the system's order)"
        )


def _describe_states(trajectories: Trajectories) -> str:
    """The states' shape in words, ragged data included."""
    if trajectories.is_ragged:
        return (
            f"{trajectories.num_experiments} experiments of {min(trajectories.lengths)}..{max(trajectories.lengths)} "
            f"times x {trajectories.state_dim} components"
        )
    return f"states {tuple(trajectories.states.shape)}"


def _estimate(name: str, states: torch.Tensor, times: torch.Tensor, options: dict):
    """``(dy/dt, variance or None)`` of the estimator ``name`` (``central`` / ``smooth`` / ``gp``)."""
    if name == "central":
        return finite_difference(states, times, order=options.get("order", 2)), None
    if name == "smooth":
        return smoothed_derivative(
            states, times, window=options.get("window", 7), degree=options.get("degree", 2)
        ), None
    if name == "gp":
        out = gp_derivative(states, times, max_iter=options.get("max_iter", 50))
        return out.mean, out.variance
    raise InputError(f"derivative: expected one of {list(_SELF_CHECKED)}, got {name!r}")


def _estimate_flat(name: str, trajectories: Trajectories, options: dict):
    """``(dy/dt (N, d), variance (N, d) or None, states (N, d))`` at every sample, experiment after experiment (ragged
    data too); ``states`` are the observed states with every missing entry replaced by the estimator's own fit at
    that time (the interpolant for ``central``, the local polynomial for ``smooth``, the posterior mean for ``gp``).

    Stencil estimators run once per group of equal-length experiments; the GP in time runs on the padded batch,
    so its hyperparameters stay shared by all experiments. With missing entries every estimator runs on the padded
    batch with the mask of the observed entries."""
    d = trajectories.state_dim
    if name == "gp" and (trajectories.is_ragged or trajectories.has_missing):
        return _gp_flat(trajectories, options.get("max_iter", 50))[1]
    if trajectories.has_missing:
        if name not in _SELF_CHECKED:
            raise InputError(f"derivative: expected one of {list(_SELF_CHECKED)}, got {name!r}")
        times, states, rows = trajectories.padded()
        observed = torch.isfinite(states) & rows.unsqueeze(-1)
        _check_stencil_options(name, options, min(trajectories.lengths))
        dydt, fit = _masked(name, states, times, observed, options)
        filled = torch.where(observed, states, fit)
        return dydt[rows], None, filled[rows]
    flat = trajectories.flat_states()
    if not trajectories.is_ragged:
        dydt, var = _estimate(name, trajectories.states, trajectories.times, options)
        return dydt.reshape(-1, d), None if var is None else var.reshape(-1, d), flat
    per_experiment: list = [None] * trajectories.num_experiments
    for idx, group in trajectories.by_length():
        try:
            dydt, _ = _estimate(name, group.states, group.times, options)
        except InputError as exc:
            raise InputError(f"{exc} (experiment{'s' * (len(idx) > 1)} {idx[:5]} of the ragged data)") from None
        for i, k in enumerate(idx):
            per_experiment[k] = dydt[i]
    return torch.cat(per_experiment), None, flat


def _check_stencil_options(name: str, options: dict, T: int) -> None:
    """The checks :func:`finite_difference` / :func:`smoothed_derivative` make on their options (for the masked path,
    which calls the stencils directly)."""
    if name == "central":
        order = check_positive_int(options.get("order", 2), "order")
        if order not in _FD_ORDERS:
            raise InputError(f"order: expected one of {list(_FD_ORDERS)}, got {order}")
        if T < order + 1:
            raise InputError(f"order={order} needs at least {order + 1} samples per trajectory, got T={T}")
        return
    window = check_positive_int(options.get("window", 7), "window")
    degree = check_positive_int(options.get("degree", 2), "degree", minimum=1)
    if window % 2 == 0 or window < 3 or window <= degree:
        raise InputError(f"window: expected an odd integer >= 3 and > degree, got window={window}, degree={degree}")
    if T < window:
        raise InputError(f"window={window} needs at least {window} samples per trajectory, got T={T}")


_SELF_CHECKED = ("central", "smooth", "gp")
_OPTION_NAMES = {"central": ("order",), "smooth": ("window", "degree"), "gp": ("max_iter",)}

#: ``estimator_error`` ratio above which ``correction_samples(derivative="auto")`` warns. At 0.5 the estimator's
#: own error is half the RMS of the samples the correction GP is asked to learn. On the pendulum of issue 9
#: (T = 21, friction as F), central differences of order 2 score 0.8 and gave corrected/misspecified RMSE 0.69
#: (a correction barely worth having), while order 4 and the GP in time score 0.06-0.23 (RMSE 0.08); at T = 11
#: every estimator scores above 0.8. The threshold sits between the two groups.
ESTIMATOR_ERROR_THRESHOLD = 0.5

#: Candidates of ``derivative="auto"``, in order of preference on ties: ``(name, options, samples needed)``.
AUTO_CANDIDATES: tuple[tuple[str, dict, int], ...] = (
    ("central", {"order": 4}, 5),
    ("gp", {}, GP_MIN_SAMPLES),
    ("central", {"order": 2}, 3),
    ("smooth", {"window": 5, "degree": 2}, 5),
    ("smooth", {"window": 7, "degree": 2}, 7),
    ("smooth", {"window": 9, "degree": 3}, 9),
    ("smooth", {"window": 11, "degree": 3}, 11),
)


def _check_options(name: str, options: dict) -> dict:
    if name not in _SELF_CHECKED:
        raise InputError(f"derivative: expected one of {list(_SELF_CHECKED)}, got {name!r}")
    unknown = sorted(set(options) - set(_OPTION_NAMES[name]))
    if unknown:
        raise InputError(
            f"options: derivative={name!r} accepts {list(_OPTION_NAMES[name])}, got unknown option(s) {unknown}"
        )
    return dict(options)


def _with_flat_states(trajectories: Trajectories, flat: torch.Tensor) -> Trajectories:
    """``trajectories`` with its states replaced by ``flat (N, d)`` (same experiments, times and lengths)."""
    if not trajectories.is_ragged:
        return Trajectories(trajectories.times, flat.reshape(trajectories.states.shape))
    return Trajectories(list(trajectories.times), list(flat.split(list(trajectories.lengths))))


def _flat_observed(trajectories: Trajectories) -> torch.Tensor:
    """``(N, d)``: the observed-entry mask, experiment after experiment."""
    observed = trajectories.observed
    return torch.cat(observed) if trajectories.is_ragged else observed.reshape(-1, trajectories.state_dim)


def _known_model_copy(trajectories: Trajectories, system: MisspecifiedSystem):
    """The self-check data ``(noisy copy, noise-free flat states (N, d), the GP in time's (dy/dt, variance, filled
    states) on the real data, or None)``: G alone from the observed initial states on the observed grids, plus state
    noise of the level the GP in time finds in the real data (a fixed seed, so the check is deterministic), with the
    real data's missing entries missing too (the estimators are checked on the data's own gaps)."""
    # Tolerances 100x looser than the package's ground-truth simulations (2.5x faster): the copy's solver error
    # (~1e-8 relative) is far below any derivative estimator's error that the check has to rank.
    times = list(trajectories.times) if trajectories.is_ragged else trajectories.times
    kept = trajectories
    try:
        sim = simulate(system, trajectories.initial_conditions, times, known_only=True, rtol=1e-8, atol=1e-10)
    except IntegrationError:
        sim, kept = _known_model_where_it_integrates(trajectories, system)
    clean = sim.flat_states()
    states, real_gp = clean, None
    if min(trajectories.lengths) >= GP_MIN_SAMPLES:
        try:
            out, real_gp = _gp_flat(trajectories, 50)
            noise = out.noise
        except InputError:
            real_gp = None  # e.g. a constant component or too few observations: the check measures the bias only
        if real_gp is not None:
            gen = torch.Generator(device=states.device).manual_seed(0)
            eps = torch.randn(states.shape, generator=gen, dtype=states.dtype, device=states.device)
            states = states + noise.sqrt() * eps
    if kept.has_missing:
        states = torch.where(_flat_observed(kept), states, torch.full_like(states, math.nan))
    return _with_flat_states(sim, states), clean, real_gp


def _gp_flat(trajectories: Trajectories, max_iter: int):
    """The GP in time on the padded batch: ``(GPDerivative (padded), (dy/dt (N, d), variance (N, d), states (N, d)))``
    as :func:`_estimate_flat` returns them."""
    max_iter = check_positive_int(max_iter, "max_iter")
    times, states, rows = trajectories.padded()
    if trajectories.has_missing:
        observed = torch.isfinite(states) & rows.unsqueeze(-1)
        out, fit = _gp_time(states, times, observed, max_iter, values=True)
        filled = torch.where(observed, states, fit)[rows]
    else:
        out = _gp_time(states, times, rows if trajectories.is_ragged else None, max_iter)
        filled = trajectories.flat_states()
    return out, (out.mean[rows], out.variance[rows], filled)


def _known_model_where_it_integrates(trajectories: Trajectories, system: MisspecifiedSystem):
    """G alone from each observed initial state, keeping the experiments over which it can be integrated (the known
    model may diverge where the true system does not: what the correction exists to fix). Warns which were left out;
    raises if none is left. Returns the simulated copy and the kept experiments' observations."""
    each = simulate_known_each(system, trajectories, rtol=1e-8, atol=1e-10)
    kept = [k for k, states in enumerate(each) if states is not None]
    if not kept:
        raise IntegrationError(
            "derivative='auto': the self-check integrates the known model alone from every observed initial state, "
            f"and it diverges from all {trajectories.num_experiments} of them; choose an estimator yourself, e.g. "
            "derivative='central' or derivative='gp'"
        )
    warn(
        f"derivative='auto': the known model alone cannot be integrated from the initial states of experiments "
        f"{[k for k, states in enumerate(each) if states is None]}; the self-check ranks the estimators on the "
        f"other {len(kept)}",
        TorchMisspecWarning,
    )
    times = [t for k, (t, _) in enumerate(trajectories.experiments()) if k in kept]
    return Trajectories(times, [each[k] for k in kept]), trajectories[kept]


def _sample_rows(trajectories: Trajectories, system: MisspecifiedSystem) -> torch.Tensor:
    """``(N,)``: the rows that give a correction sample, those at which every output component is observed."""
    return system.select_outputs(_flat_observed(trajectories)).all(-1)


def _ratio(name, options, trajectories, known_copy, system) -> float:
    if name == "gp" and not options and known_copy[2] is not None:
        dydt, _, flat = known_copy[2]  # already computed for the noise level
    else:
        dydt, _, flat = _estimate_flat(name, trajectories, options)
    targets = system.select_outputs(dydt - system.known_rhs(flat))
    if trajectories.has_missing:
        targets = targets[_sample_rows(trajectories, system)]
    spread = float(targets.pow(2).mean().sqrt())
    copy = known_copy[0]
    est, _, _ = _estimate_flat(name, copy, options)
    errors = system.select_outputs(est - system.known_rhs(known_copy[1]))  # dy/dt = G(y) on the noise-free copy
    if copy.has_missing:
        errors = errors[_sample_rows(copy, system)]
    err = float(errors.pow(2).mean().sqrt())
    if not math.isfinite(err) or not math.isfinite(spread):
        return float("inf")
    if spread == 0.0:
        return 0.0 if err == 0.0 else float("inf")
    return err / spread


@adaptive_threads()
def estimator_error(trajectories: Trajectories, system: MisspecifiedSystem, *, derivative: str, **options) -> float:
    """Self-check of a derivative estimator that needs no truth: its error on the known model relative to the data.

    The known model G alone is integrated from every observed initial state on the observed time grids
    (:func:`~torchmisspec.data.simulate` with ``known_only=True``); on these trajectories ``dy/dt = G(y)`` exactly.
    State noise of the level the GP in time (:func:`gp_derivative`) estimates on the real data is added to them
    (fixed seed: the check is deterministic), so the check measures the estimator's bias *and* its noise
    amplification. The estimator is applied to them, and the RMS of its error in ``dy/dt`` on the correction's
    output components is divided by the RMS of the correction samples ``F~`` the same estimator gives on the real
    data. A ratio of 0.1 means the estimator's own error is a tenth of the size of what the correction GP is asked
    to learn; a ratio near or above 1 means the samples are mostly estimator error.

    Args:
        trajectories: the observations.
        system: the misspecified system.
        derivative: ``"central"``, ``"smooth"`` or ``"gp"``.
        **options: the estimator's options (``order``; ``window``, ``degree``; ``max_iter``).

    Returns:
        The ratio (``inf`` when the estimate is not finite).

    Raises:
        InputError: bad arguments, unknown options, or too few samples for the estimator.
        IntegrationError: the known model cannot be integrated from any observed initial state (experiments from
            which it diverges are left out of the check, with a warning).
    """
    _check_trajectories_and_system(trajectories, system)
    options = _check_options(derivative, options)
    if derivative != "gp":  # cheap: bad options or too few samples fail before the simulation
        _estimate_flat(derivative, trajectories, options)
    return _ratio(derivative, options, trajectories, _known_model_copy(trajectories, system), system)


@adaptive_threads()
def choose_derivative(
    trajectories: Trajectories, system: MisspecifiedSystem
) -> tuple[str, dict, dict[tuple[str, tuple], float]]:
    """The estimator ``derivative="auto"`` uses: the candidate with the smallest :func:`estimator_error`.

    Candidates (:data:`AUTO_CANDIDATES`): ``central`` order 4 and 2, ``gp``, and ``smooth`` with windows 5, 7
    (degree 2) and 9, 11 (degree 3); those needing more samples than the trajectories have are skipped. The
    known-model copy of the data is simulated once and shared by all candidates.

    Returns:
        ``(name, options, errors)``: the chosen estimator, its options (pass them on as
        ``correction_samples(..., derivative=name, **options)``), and every candidate's ratio keyed by
        ``(name, tuple(sorted(options.items())))``.

    Raises:
        InputError: no candidate fits the number of samples (T < 3), or bad arguments.
    """
    _check_trajectories_and_system(trajectories, system)
    T = min(trajectories.lengths)
    candidates = [(n, o) for n, o, need in AUTO_CANDIDATES if T >= need]
    if not candidates:
        raise InputError(
            f"derivative='auto': every estimator needs at least 3 samples per trajectory, got T={T}"
            + (" (the shortest experiment)" if trajectories.is_ragged else "")
        )
    known_copy = _known_model_copy(trajectories, system)
    errors: dict[tuple[str, tuple], float] = {}
    for name, options in candidates:
        try:
            errors[(name, tuple(sorted(options.items())))] = _ratio(name, options, trajectories, known_copy, system)
        except InputError:
            errors[(name, tuple(sorted(options.items())))] = float("inf")
    key = min(errors, key=errors.get)
    return key[0], dict(key[1]), errors


def correction_samples(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    *,
    derivative: str = "auto",
    noise_std: float = 0.0,
    generator: torch.Generator | None = None,
    order: int = 2,
    window: int = 7,
    degree: int = 2,
) -> CorrectionSamples:
    """Samples F~ = dy/dt - G(y) of the missing term at every observed state.

    **Missing entries** (NaN in ``trajectories``): each component's derivative comes from its own observed times
    (see the estimators). A sample at time t_i is formed only when every output component F acts on
    (``system.correction_outputs``) was observed at t_i; a missing input or other component of that state, which
    G(y) and the sample's inputs need, is replaced by the estimator's own fit at t_i (the interpolant for
    ``central``, the local polynomial for ``smooth``, the posterior mean for ``gp``; for ``oracle``,
    :meth:`Trajectories.filled`). Why: a target at a time where its output was not observed would be an interpolation
    of its neighbours' derivative estimates, no new information but counted as if it were (and a poor one for a
    rarely measured component); since one sample carries all outputs at one input, a time missing any output gives
    no sample, and the other outputs' targets lost there are covered by their neighbours'. A filled input or G
    argument has the accuracy of the estimator's fit, the same order as its derivative's, so these samples are kept
    rather than lose every time at which some other component was not measured.

    Args:
        trajectories: the observations, ``states (K, T, d)`` or ragged (experiments of different lengths); NaN
            entries are missing.
        system: the misspecified system; its ``state_dim`` must equal d.
        derivative: how dy/dt is obtained:

            * ``"auto"`` (default): the estimator :func:`choose_derivative` picks by the self-check
              :func:`estimator_error` (``order`` / ``window`` / ``degree`` are then ignored). When the chosen
              estimator's ratio exceeds :data:`ESTIMATOR_ERROR_THRESHOLD` (0.5: the estimator's own error is more
              than half the size of the samples, so the learned correction would be dominated by it) a
              :class:`~torchmisspec.TorchMisspecWarning` is issued. Explicit estimators are not self-checked
              (call :func:`estimator_error` yourself);
            * ``"oracle"``: the paper's observation model, the exact ``G(y) + F(y)`` (``system.true_rhs``) plus
              noise; only for systems with a true correction (simulations, benchmarks);
            * ``"central"``: :func:`finite_difference` with ``order``;
            * ``"smooth"``: :func:`smoothed_derivative` with ``window`` and ``degree``;
            * ``"gp"``: :func:`gp_derivative`; its posterior variance of dy/dt on the output components becomes
              ``CorrectionSamples.noise`` (the error of G(y) caused by state noise is ignored).
        noise_std: standard deviation of i.i.d. Gaussian noise added to every target entry (for ``"oracle"`` this
            is the observation noise of the paper's model; for the estimators it is extra noise added on top of
            the estimator's own error, e.g. to mimic noisy derivative observations; with ``"gp"`` its variance is
            added to ``noise``). Must be a finite number >= 0; with 0 no random numbers are drawn.
        generator: optional ``torch.Generator`` for the noise (on the states' device), for reproducibility.
        order: finite-difference order for ``"central"`` (2 or 4).
        window: samples per local fit for ``"smooth"``.
        degree: polynomial degree of the local fits for ``"smooth"``.

    Returns:
        :class:`CorrectionSamples` with one sample per observed state (``N = K * T``, or the sum of the lengths;
        fewer with missing outputs), in the dtype and on the device of the states; its ``states`` are the observed
        states with missing entries filled as above.

    Raises:
        InputError: ``trajectories`` / ``system`` of the wrong type, an unknown ``derivative``, a bad
            ``noise_std``, ``"oracle"`` for a system without a true correction, too few samples for the
            estimator, or non-finite samples (e.g. a state sitting on a singularity of G or F).
        ShapeError: the trajectories' state dimension differs from the system's.
    """
    _check_trajectories_and_system(trajectories, system)
    if not isinstance(derivative, str) or derivative not in DERIVATIVE_ESTIMATORS:
        raise InputError(f"derivative: expected one of {list(DERIVATIVE_ESTIMATORS)}, got {derivative!r}")
    noise = check_real(noise_std, "noise_std", minimum=0.0)
    if generator is not None and not isinstance(generator, torch.Generator):
        raise InputError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")

    variance = None
    if derivative == "oracle":
        if not system.has_correction:
            raise InputError(
                f"derivative='oracle': oracle derivatives need a system with a true correction F, and system "
                f"'{system.name}' has none; use 'auto', 'central', 'smooth' or 'gp' for real data"
            )
        flat_states = trajectories.filled().flat_states()
        check_finite(flat_states, "trajectories.states")
        dydt = system.true_rhs(flat_states)
    elif derivative == "auto":
        name, options, errors = choose_derivative(trajectories, system)
        ratio = errors[(name, tuple(sorted(options.items())))]
        if not ratio <= ESTIMATOR_ERROR_THRESHOLD:
            warn(
                f"correction_samples: the best derivative estimator ({name} {options}) has an error on the known "
                f"model of {ratio:.3g} times the size of the correction samples (threshold "
                f"{ESTIMATOR_ERROR_THRESHOLD}): the learned correction would mostly fit estimator error. Fixes: "
                "sample the states more densely in time, try another estimator (estimator_error tells which is "
                "best), or fit the correction through the ODE with tms.fit_trajectories",
                TorchMisspecWarning,
            )
        dydt, variance, flat_states = _estimate_flat(name, trajectories, options)
    elif derivative == "central":
        dydt, _, flat_states = _estimate_flat("central", trajectories, {"order": order})
    elif derivative == "smooth":
        dydt, _, flat_states = _estimate_flat("smooth", trajectories, {"window": window, "degree": degree})
    else:
        dydt, variance, flat_states = _estimate_flat("gp", trajectories, {})

    lengths = torch.tensor(trajectories.lengths, device=flat_states.device)
    experiment = torch.arange(trajectories.num_experiments, device=flat_states.device).repeat_interleave(lengths)
    if trajectories.has_missing:
        keep = _sample_rows(trajectories, system)
        if not bool(keep.any()):
            raise InputError(
                f"trajectories: expected some time at which every output component {list(system.correction_outputs)} "
                "of the correction is observed (a sample needs them all), got none"
            )
        dydt, flat_states, experiment = dydt[keep], flat_states[keep], experiment[keep]
        variance = None if variance is None else variance[keep]
    targets = system.select_outputs(dydt - system.known_rhs(flat_states))
    check_finite(targets, f"correction samples dy/dt - G(y) of system '{system.name}'")
    sample_noise = None if variance is None else system.select_outputs(variance)
    if noise > 0:
        eps = torch.randn(targets.shape, generator=generator, dtype=targets.dtype, device=targets.device)
        targets = targets + noise * eps
        check_finite(targets, f"correction samples with noise_std={noise_std!r} added")
        if sample_noise is not None:
            sample_noise = sample_noise + noise**2
    return CorrectionSamples(
        inputs=system.select_inputs(flat_states),
        targets=targets,
        states=flat_states,
        experiment=experiment,
        noise=sample_noise,
    )


def estimate_state_noise(trajectories: Trajectories) -> torch.Tensor | None:
    """``(d,)`` the standard deviation of the measurement noise on each state component, as the GP in time
    (:func:`gp_derivative`) finds it in the data (floored at 1e-5 of each component's standard deviation), or
    ``None`` when an experiment has fewer than :data:`GP_MIN_SAMPLES` observations or a component is constant.

    What :meth:`CorrectedODE.calibrate <torchmisspec.CorrectedODE.calibrate>` assumes by default, so that noisy
    observations are compared with bands of noisy observations (the bands it calibrates are for the states)."""
    if min(trajectories.lengths) < GP_MIN_SAMPLES:
        return None
    times, states, mask = trajectories.padded()
    if trajectories.has_missing:
        mask = torch.isfinite(states) & mask.unsqueeze(-1)
    try:
        var = _gp_time(states, times, mask if trajectories.is_ragged or trajectories.has_missing else None, 50).noise
    except InputError:  # a constant component or too few observations: nothing to estimate from
        return None
    floor = 1e-10 * observed_variance(trajectories.flat_states()).clamp_min(torch.finfo(var.dtype).tiny)
    return torch.maximum(var.to(states), floor.to(states)).sqrt()


def observed_variance(flat: torch.Tensor) -> torch.Tensor:
    """``(d,)`` the unbiased variance of each column of ``flat (N, d)`` over its observed (non-NaN) entries."""
    seen = torch.isfinite(flat)
    n = seen.sum(0).clamp_min(2)
    zero = torch.zeros((), dtype=flat.dtype, device=flat.device)
    mean = torch.where(seen, flat, zero).sum(0) / n
    return torch.where(seen, flat - mean, zero).pow(2).sum(0) / (n - 1)
