"""The design criterion: information gain of noisy correction samples, and how well the proxy approximates it.

Convention. F has d_out independent outputs sharing the kernel k; the samples F~ = F + eps, eps ~ N(0, sigma^2 I),
taken at M points P carry

    I(F; F~(P)) = (d_out / 2) * logdet(I_M + K(P, P) / sigma^2)      nats (real Gaussian).

The paper (§4, footnote of Theorem 1) writes the entropy of a Gaussian vector as log((pi e)^k det Sigma), the
complex-Gaussian convention, which makes the same quantity d_out * logdet(I + K / sigma^2): exactly twice ours.
The factor is constant, so every design (every argmax) is the same in both conventions; all numbers this
package reports are in the real-Gaussian nats above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .._errors import InputError, ShapeError
from .._validation import as_tensor, check_finite, check_indices, check_ndim, check_positive_int
from ..data import simulate
from ..gp import CorrectionGP
from ..systems import MisspecifiedSystem
from ._common import (
    DesignResult,
    GPKernel,
    check_candidates,
    check_proxies,
    check_system,
    check_times,
    logdet_identity_plus,
)
from ._proxy import corrected_proxies, proxy_trajectories

__all__ = [
    "information_gain",
    "true_information_gain",
    "proxy_gap_bound",
    "proxy_check",
    "ProxyCheck",
]


def _d_out(d_out, gp: CorrectionGP) -> int:
    if d_out is None:
        if gp.output_dim is None:
            raise InputError(
                "d_out: expected the number of correction outputs (e.g. system.output_dim), got None with an "
                "unfitted gp, from which it cannot be read"
            )
        return int(gp.output_dim)
    return check_positive_int(d_out, "d_out")


def information_gain(points, gp: CorrectionGP, *, d_out: int | None = None, condition: bool | None = None) -> float:
    """Information gain (nats) about F of noisy correction samples at ``points``.

    ``(d_out / 2) * logdet(I + K / sigma^2)`` with ``K = k(points, points)`` the GP's prior covariance and
    ``sigma^2 = gp.noise_variance``. Repeated points are fine (``I + K / sigma^2`` stays positive definite); the
    log-determinant comes from one Cholesky factorization. The paper's complex-Gaussian convention gives twice
    this value (see the module docstring); designs are identical.

    Args:
        points: ``(M, d_in)`` sample locations, already restricted to the correction inputs.
        gp: a :class:`CorrectionGP` with a shared kernel whose hyperparameters are set (given or fitted).
        d_out: number of outputs of F (``system.output_dim``); defaults to the fitted GP's output dimension.
        condition: the information *given the GP's training samples* (K its posterior covariance, as
            :func:`greedy` uses); default: when the GP is fitted. ``False``: the prior's.
    """
    kern = GPKernel(gp, condition=condition)
    d_out = _d_out(d_out, gp)
    x = as_tensor(points, "points", dtype=kern.dtype, device=kern.device)
    check_ndim(x, 2, "points", "(M, d_in)")
    check_finite(x, "points")
    if gp.input_dim is not None and x.shape[1] != gp.input_dim:
        raise ShapeError(f"points: expected {gp.input_dim} input columns (as the fitted gp), got {tuple(x.shape)}")
    if x.shape[0] == 0:
        return 0.0
    logdet, _ = logdet_identity_plus(kern(kern.expand(x)), kern.noise, "I + K / noise_variance")
    return 0.5 * kern.multiplicity(d_out) * float(logdet)


# ------------------------------------------------------------------------------------------- proxy vs truth
@dataclass(frozen=True)
class ProxyCheck:
    """How good the proxy criterion is for one design (all in nats, real-Gaussian convention).

    Attributes:
        proxy_gain: information gain of the proxy samples (what the design maximised).
        exact_gain: information gain of the samples along the true trajectories.
        bound: Theorem 1 bound on ``|proxy_gain - exact_gain|`` (``inf`` when the theorem gives no bound).
        delta: largest kernel discrepancy ``max |k(true) - k(proxy)|`` over all pairs of sample points.
    """

    proxy_gain: float
    exact_gain: float
    bound: float
    delta: float

    @property
    def gap(self) -> float:
        return abs(self.proxy_gain - self.exact_gain)


def _design_points(indices, candidates, system, times, gp, proxies, states, proxy="known", condition=False):
    """Chosen indices, proxy inputs and true inputs ``(K T, d_in)`` of a design, and the kernel view."""
    system = check_system(system)
    if proxy not in ("known", "corrected"):
        raise InputError(f"proxy: expected 'known' or 'corrected', got {proxy!r}")
    if proxy == "corrected" and not gp.is_fitted:
        raise InputError("proxy='corrected': an unfitted gp has no correction to add to G; fit it or pass 'known'")
    # Theorem 1 holds for any kernel: the prior's (the paper's criterion) or the one conditioned on the GP's data
    kern = GPKernel(gp, input_dim=system.input_dim, condition=condition, system=system)
    cand = check_candidates(candidates, system, dtype=kern.dtype, device=kern.device)
    if isinstance(indices, DesignResult):
        indices = indices.indices
    if isinstance(indices, torch.Tensor):
        indices = indices.reshape(-1).tolist()
    idx = list(check_indices(indices, cand.shape[0], "indices"))
    t = check_times(times, dtype=kern.dtype, device=kern.device)
    chosen = cand[idx]
    if proxies is None and proxy == "corrected":
        prox = corrected_proxies(system, gp, chosen, t)
    elif proxies is None:
        prox = proxy_trajectories(system, chosen, t)
    else:
        prox = check_proxies(proxies, cand.shape[0], system, t, dtype=kern.dtype, device=kern.device)[idx]
    if states is None:
        if not system.has_correction:
            raise InputError(
                f"system '{system.name}' has no true correction F, so the true trajectories cannot be "
                "simulated; pass the observed states=(K, T, d) of the experiments"
            )
        true = simulate(system, chosen, t).states
    else:
        true = as_tensor(states, "states", dtype=kern.dtype, device=kern.device)
        if tuple(true.shape) != tuple(prox.shape):
            raise ShapeError(
                f"states: expected shape {tuple(prox.shape)} (one trajectory per chosen index at the "
                f"given times), got {tuple(true.shape)}"
            )
        check_finite(true, "states")
    d_in = system.input_dim
    prox_x, true_x = (kern.expand(system.select_inputs(p).reshape(-1, d_in)) for p in (prox, true))
    return kern, prox_x, true_x, system


def true_information_gain(
    indices, candidates, *, system: MisspecifiedSystem, times, gp: CorrectionGP, states=None
) -> float:
    """Information gain (nats) of samples along the true trajectories (G + F) of the chosen experiments.

    The design maximises the gain along the *proxy* trajectories (G alone); this is the quantity they stand in for.

    This is the quantity G(Y_0) the proxy stands in for (paper eq. accurate_cost_function). The true trajectories
    are simulated from ``candidates[indices]`` (the system must carry its true correction), or given as
    ``states (K, T, d)`` (e.g. the experiments actually run).

    Args:
        indices: the chosen candidate indices (or a :class:`DesignResult`).
        candidates: ``(N, d)`` the candidate set the indices refer to.
        system: as for :func:`greedy`.
        times: as for :func:`greedy`.
        gp: as for :func:`greedy`.
        states: optional ``(K, T, d)`` observed states of the chosen experiments (simulated when omitted).
    """
    kern, _, true_x, system = _design_points(indices, candidates, system, times, gp, None, states)
    logdet, _ = logdet_identity_plus(kern(true_x), kern.noise, "I + K(true) / noise_variance")
    return 0.5 * kern.multiplicity(system.output_dim) * float(logdet)


def _bound(delta: float, n: int, noise: float, blocks: int) -> float:
    ratio = delta * n**1.5 / noise
    if ratio >= 1.0:
        return math.inf
    return -0.5 * blocks * n * math.log1p(-ratio)


def proxy_check(
    indices,
    candidates,
    *,
    system: MisspecifiedSystem,
    times,
    gp: CorrectionGP,
    proxies=None,
    states=None,
    blockwise: bool = False,
    proxy: str = "known",
    condition: bool = False,
) -> ProxyCheck:
    """Proxy gain, exact gain, their largest kernel discrepancy and the Theorem 1 bound, for one design.

    See :func:`proxy_gap_bound` for the bound and :func:`true_information_gain` for the arguments. ``proxy``:
    the proxies checked, ``"known"`` (G alone, the paper's) or ``"corrected"`` (G + the fitted GP's posterior
    mean, as :func:`greedy` uses with data); ``condition=True`` measures both gains with the kernel conditioned on
    the GP's data (the criterion a conditioned design maximises; Theorem 1 holds for any kernel).
    """
    kern, prox_x, true_x, system = _design_points(
        indices, candidates, system, times, gp, proxies, states, proxy, condition
    )
    Kp, Kt = kern(prox_x), kern(true_x)
    delta = float((Kt - Kp).abs().max())
    d_out = kern.multiplicity(system.output_dim)
    ld_p, _ = logdet_identity_plus(Kp, kern.noise, "I + K(proxy) / noise_variance")
    ld_t, _ = logdet_identity_plus(Kt, kern.noise, "I + K(true) / noise_variance")
    m = prox_x.shape[0]
    bound = _bound(delta, m, kern.noise, d_out) if blockwise else _bound(delta, d_out * m, kern.noise, 1)
    return ProxyCheck(
        proxy_gain=0.5 * d_out * float(ld_p), exact_gain=0.5 * d_out * float(ld_t), bound=bound, delta=delta
    )


def proxy_gap_bound(
    indices,
    candidates,
    *,
    system: MisspecifiedSystem,
    times,
    gp: CorrectionGP,
    proxies=None,
    states=None,
    blockwise: bool = False,
) -> float:
    """Theorem 1 bound (nats) on ``|proxy information gain - true information gain|`` of a design.

    The paper bounds, in its complex-Gaussian convention (information = logdet, twice our nats),

        |G~ - G| <= -n log(1 - delta n^{3/2} / sigma_min(Sigma_eps)),    n = d_out K T,

    with ``delta = max |k(y(t_i), y(t_j)) - k(y_G(t_i), y_G(t_j))|`` over all pairs of sample points (computed here
    from both kernel matrices) and ``Sigma_eps = sigma^2 I`` (so sigma_min = noise_variance). Converted to the
    real-Gaussian nats this package reports, the bound returned is

        -(n / 2) log(1 - delta n^{3/2} / sigma^2),

    i.e. the paper's number divided by 2. The bound is ``inf`` when the log argument is <= 0 (the theorem then says
    nothing; this happens quickly, as n^{3/2} grows with the design size).

    ``blockwise=True`` gives a tighter bound that uses the shared kernel: the covariance is block diagonal with
    d_out identical K T x K T blocks, so the theorem can be applied per block and summed:
    ``-(d_out m / 2) log(1 - delta m^{3/2} / sigma^2)`` with m = K T.

    Args:
        indices: the chosen candidate indices (or a :class:`DesignResult`).
        candidates: ``(N, d)``.
        system: as for :func:`greedy`; the true trajectories are simulated from the system's true correction
            unless ``states (K, T, d)`` are given.
        times: as for :func:`greedy`.
        gp: as for :func:`greedy`.
        states: optional ``(K, T, d)`` observed states of the chosen experiments.
        blockwise: apply the theorem per output block (tighter, see above).
        proxies: optional ``(N, T, d)`` proxy trajectories of all candidates (computed when omitted).
    """
    return proxy_check(
        indices, candidates, system=system, times=times, gp=gp, proxies=proxies, states=states, blockwise=blockwise
    ).bound
