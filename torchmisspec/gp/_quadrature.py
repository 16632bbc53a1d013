"""Deterministic quadrature Fourier features for the RBF kernel, with a certified bound (``gp._paths`` uses them).

The RBF's spectral density is Gaussian, so its Fourier integral is a Gauss-Hermite quadrature per dimension; the
tensor grid is pruned of its lightest nodes within the error budget. :func:`quadrature_rule` returns the nodes,
weights and the uniform bound reached over a box of half-widths ``rho`` (in lengthscales), or ``None`` when no grid
within :data:`MAX_NODES_PER_DIM` nodes per dimension meets it; :func:`frequencies_for` is the random features'
count for a root-mean-square bound. The derivation is in :mod:`torchmisspec.gp._paths`' docstring.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
from numpy.polynomial.hermite_e import hermegauss

from .._errors import InputError
from .._validation import check_real

__all__ = [
    "MAX_FREQUENCIES",
    "MAX_NODES_PER_DIM",
    "QUADRATURE_FEATURE_ERROR",
    "frequencies_for",
    "gauss_hermite_error",
    "hermite_remainder",
    "quadrature_rule",
]

#: Largest number of frequency pairs chosen automatically (a bound asking for more is refused).
MAX_FREQUENCIES = 65_536
#: Most Gauss-Hermite nodes per input dimension (more: random features).
MAX_NODES_PER_DIM = 128
#: Most nodes of a tensor grid before pruning (more: random features).
_MAX_GRID = 2**20
#: Default certified *uniform* bound of the quadrature features' prior-covariance error over the widened box of the
#: training inputs, relative to the prior variance (module docstring).
QUADRATURE_FEATURE_ERROR = 1e-2


def _check_error(error: float) -> float:
    error = check_real(error, "feature_error", positive=True)
    if error >= 1.0:
        raise InputError(f"feature_error: expected a relative error in (0, 1), got {error!r}")
    return error


def frequencies_for(error: float) -> int:
    """Frequency pairs D for a root-mean-square prior-covariance error of at most ``error`` x the prior variance."""
    error = _check_error(error)
    D = math.ceil(1.0 / error**2)
    if D > MAX_FREQUENCIES:
        raise InputError(
            f"feature_error: {error!r} needs {D} frequency pairs, more than {MAX_FREQUENCIES}; ask for a larger error "
            "or pass num_features"
        )
    return D


@functools.lru_cache(maxsize=MAX_NODES_PER_DIM)
def _gauss_hermite(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (exactly symmetric about 0) and weights (summing to 1) of the m-node Gauss-Hermite rule for N(0, 1)."""
    z, a = hermegauss(m)
    z, a = (z - z[::-1]) / 2, (a + a[::-1]) / 2
    return z, a / a.sum()


def hermite_remainder(m: int, rho: float) -> float:
    """The closed-form bound ``m! rho^2m / (2m)!`` on ``max_{|t| <= rho} |Q_m(t) - exp(-t^2 / 2)|`` (the
    Gauss-Hermite remainder, module docstring), capped at 2 (both terms lie in [-1, 1])."""
    if rho <= 0.0:
        return 0.0
    return min(2.0, math.exp(math.lgamma(m + 1) - math.lgamma(2 * m + 1) + 2 * m * math.log(rho)))


@functools.lru_cache(maxsize=8192)
def _grid_error(m: int, rho: float, k: int) -> float:
    """Certified ``max_{0 <= t <= rho} |Q_m(t) - exp(-t^2 / 2)|`` from a grid of spacing ``h = 2^-k`` on
    [0, rho] (even in t): the largest grid value plus ``max|g''| h^2 / 8``, ``|g''| <= sum a z^2 + 1`` (rounding is
    added by the caller)."""
    z, a = _gauss_hermite(m)
    h = 2.0**-k
    t = np.arange(math.ceil(rho / h) + 1) * h
    pos = z > 0  # the rule is even in t: the nodes +-z share the weight, the origin (odd m) contributes a_0
    q = np.cos(np.outer(t, z[pos])) @ (2.0 * a[pos]) + a[z == 0].sum()
    curvature = float(a @ z**2) + 1.0
    return float(np.abs(q - np.exp(-0.5 * t**2)).max()) + curvature * h**2 / 8


def gauss_hermite_error(m: int, rho: float, error: float = QUADRATURE_FEATURE_ERROR) -> float:
    """Certified ``e_m(rho) = max_{|t| <= rho} |Q_m(t) - exp(-t^2 / 2)|`` for the m-node Gauss-Hermite rule: the
    smaller of :func:`hermite_remainder` and the grid bound (module docstring), the grid chosen for a target
    ``error`` of the whole rule (its interpolation slack at most ``error / 64``, grid spacing at most 2^-7)."""
    rho = float(rho)
    if rho <= 0.0:
        return 0.0  # Q_m(0) = sum a_j = 1 = c(0)
    k = next((k for k in range(7, 13) if 2.0 ** (-2 * k) / 4 <= error / 64), 12)
    key = math.ceil(rho * 64) / 64  # rounded up (a bound on a wider interval holds on a narrower one): cached
    # plus the rounding of the computed rule and of its evaluation (a few ulps per node)
    return min(hermite_remainder(m, rho), _grid_error(m, key, k)) + 64 * m * float(np.finfo(float).eps)


def _half_grid(ms: Sequence[int], budget: float) -> tuple[np.ndarray, np.ndarray, float]:
    """One node of every pair +-z of the tensor grid with ``ms`` nodes per dimension (and the origin, if a node),
    their masses (2 x product weight; the origin's own weight), the pairs of least mass up to a total ``budget``
    dropped, the rest renormalized to sum 1: ``(Z (D, d), c (D,), dropped mass)``."""
    rules = [_gauss_hermite(m) for m in ms]
    P = math.prod(ms)
    A = functools.reduce(np.multiply.outer, [a for _, a in rules]).reshape(-1)  # C order: the mirror of f is P-1-f
    flat = np.arange(P // 2 + P % 2)
    mass = np.where(flat < P // 2, 2.0 * A[flat], A[flat])  # the last one is the origin when P is odd
    order = np.argsort(mass, kind="stable")
    cum = np.cumsum(mass[order])
    n_drop = int(np.searchsorted(cum, budget, side="right"))
    n_drop = min(n_drop, len(order) - 1)
    dropped = float(cum[n_drop - 1]) if n_drop else 0.0
    keep = np.sort(order[n_drop:])
    index = np.unravel_index(flat[keep], tuple(ms))
    Z = np.stack([rules[i][0][index[i]] for i in range(len(ms))], -1)
    c = mass[keep]
    return Z, c / c.sum(), dropped


def quadrature_rule(rho: Sequence[float], error: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The pruned tensor Gauss-Hermite rule with the fewest frequency pairs whose certified bound (module docstring)
    on ``|k_hat - k| / s^2`` is at most ``error`` for all ``|r_i| / l <= rho_i``.

    Returns:
        ``(Z (D, d), c (D,), bound)``: frequencies in units of 1 / l (``w_j = Z_j / l``), their weights (summing to
        1: feature pair ``sqrt(s^2 c_j) [cos(w_j^T x), sin(w_j^T x)]``) and the bound reached; ``None`` when no rule
        with at most :data:`MAX_NODES_PER_DIM` nodes per dimension and ``2^20`` grid nodes meets ``error``.

    The per-dimension node counts come from a scan of per-dimension targets ``t`` (``m_i`` the fewest nodes with
    ``e_{m_i}(rho_i) <= t``, from ``error / d`` down); what the tensor error leaves of ``error`` is the pruning
    budget (half of it: renormalizing doubles the dropped mass). ``rho`` is rounded up to a multiple of 1/64.
    """
    error = _check_error(error)
    # rounded up (a bound over wider intervals holds on narrower ones), so that repeated calls hit the cache
    key = tuple(math.ceil(max(float(r), 0.0) * 64) / 64 for r in rho)
    rule = _quadrature_rule(key, error)
    return None if rule is None else (rule[0].copy(), rule[1].copy(), rule[2])


@functools.lru_cache(maxsize=64)
def _quadrature_rule(rho: tuple[float, ...], error: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    d = len(rho)

    def fewest(r: float, t: float) -> int | None:
        start = max(1, int(r * r / 4))  # fewer nodes cannot resolve rho (measured: e_m > 0.98 for m < rho^2 / 4)
        return next((m for m in range(start, MAX_NODES_PER_DIM + 1) if gauss_hermite_error(m, r, error) <= t), None)

    best, previous, worse, t = None, None, 0, error / d
    while worse < 4 and t > error * 1e-12:
        ms = [fewest(r, t) for r in rho]
        t /= math.sqrt(2.0)
        if None in ms or math.prod(ms) > _MAX_GRID:
            break
        if ms == previous:
            continue
        previous = ms
        # |prod_i Q_i - prod_i c_i| <= sum_i |Q_i - c_i| (all factors in [-1, 1]) <= sum_i e_{m_i}(rho_i); dropping
        # pairs of total weight delta and renormalizing adds at most 2 delta (module docstring)
        tensor = sum(gauss_hermite_error(m, r, error) for m, r in zip(ms, rho, strict=True))
        Z, c, dropped = _half_grid(ms, (error - tensor) / 2)
        if best is None or len(c) < len(best[1]):
            best, worse = (Z, c, tensor + 2 * dropped), 0
        else:
            worse += 1
    return best
