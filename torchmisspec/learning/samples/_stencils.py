"""The stencil estimators of dy/dt (:mod:`torchmisspec.learning.samples.observations`): :func:`finite_difference`
(Lagrange / Fornberg weights) and :func:`smoothed_derivative` (local polynomial least squares), on possibly non-uniform
grids, with missing entries; and the helpers they share with the GP in time
(:mod:`torchmisspec.learning.samples._gp_in_time`)."""

from __future__ import annotations

import torch

from ..._errors import InputError
from ..._validation import check_positive_int, states_and_times
from ...data._missing import check_counts, local_fit

_FD_ORDERS = (2, 4)


def _states_and_times(states, times) -> tuple[torch.Tensor, torch.Tensor]:
    """The shared states/times check (NaN states are missing entries); the times come back as ``(1, T)`` (shared
    grid) or ``(K, T)``."""
    states, times = states_and_times(states, times, missing=True)
    if states.dtype not in (torch.float32, torch.float64):  # the least-squares fits have no half-precision kernels
        raise InputError(
            f"states: expected float32 or float64 values, got {str(states.dtype).removeprefix('torch.')} (half "
            "precision is too coarse for derivative estimates); convert with .double()"
        )
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
        raise InputError(f"states: expected at least {width} samples per trajectory for order={order}, got T={T}")
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
        raise InputError(f"states: expected at least {window} samples per trajectory for window={window}, got T={T}")
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


def _check_stencil_options(name: str, options: dict, T: int) -> None:
    """The checks :func:`finite_difference` / :func:`smoothed_derivative` make on their options (for the masked path,
    which calls the stencils directly)."""
    if name == "central":
        order = check_positive_int(options.get("order", 2), "order")
        if order not in _FD_ORDERS:
            raise InputError(f"order: expected one of {list(_FD_ORDERS)}, got {order}")
        if T < order + 1:
            raise InputError(
                f"states: expected at least {order + 1} samples per trajectory for order={order}, got T={T}"
            )
        return
    window = check_positive_int(options.get("window", 7), "window")
    degree = check_positive_int(options.get("degree", 2), "degree", minimum=1)
    if window % 2 == 0 or window < 3 or window <= degree:
        raise InputError(f"window: expected an odd integer >= 3 and > degree, got window={window}, degree={degree}")
    if T < window:
        raise InputError(f"states: expected at least {window} samples per trajectory for window={window}, got T={T}")
