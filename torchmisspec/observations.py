"""Samples of the missing term F from observed trajectories: derivative estimators and :func:`correction_samples`.

The correction is never observed directly. From states ``y`` observed at times ``t`` we estimate ``dy/dt`` and
form the samples ``F~ = dy/dt - G(y)`` at the observed states, restricted to the components F acts on and
paired with the components F depends on. Three derivative estimators are provided:

* ``"oracle"``: the paper's observation model, the exact ``dy/dt = G(y) + F(y)`` plus Gaussian noise (simulation
  and benchmark systems only, since it needs the true F);
* ``"central"``: :func:`finite_difference`, exact Lagrange (Fornberg) weights on local, possibly non-uniform
  stencils, second or fourth order everywhere, end points included;
* ``"smooth"``: :func:`smoothed_derivative`, a local polynomial least-squares fit (Savitzky-Golay generalised to
  non-uniform grids) for noisy states.

Every function is vectorised over experiments and state components, follows the dtype and device of the states,
and raises :class:`~torchmisspec._errors.InputError` / :class:`~torchmisspec._errors.ShapeError` on bad input.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._errors import InputError, ShapeError
from ._validation import check_finite, check_positive_int, check_real, states_and_times
from .data import Trajectories
from .systems import MisspecifiedSystem

__all__ = [
    "DERIVATIVE_ESTIMATORS",
    "CorrectionSamples",
    "correction_samples",
    "finite_difference",
    "smoothed_derivative",
]

#: Names accepted by ``correction_samples(derivative=...)``.
DERIVATIVE_ESTIMATORS = ("oracle", "central", "smooth")

_FD_ORDERS = (2, 4)


# ---------------------------------------------------------------------------------------------------------------
# Shared helpers
def _states_and_times(states, times) -> tuple[torch.Tensor, torch.Tensor]:
    """The shared states/times check; the times come back as ``(1, T)`` (shared grid) or ``(K, T)``."""
    states, times = states_and_times(states, times)
    return states, times.reshape(-1, states.shape[1])


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

    Args:
        states: ``(K, T, d)`` states of K trajectories at T times.
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
    for polynomials of degree <= ``degree``.

    Args:
        states: ``(K, T, d)``.
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
@dataclass(frozen=True)
class CorrectionSamples:
    """Noisy samples F~ of the correction at the observed states, flattened over experiments and times.

    Sample ``n = k * T + j`` is experiment k at its j-th time.

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


def correction_samples(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    *,
    derivative: str = "central",
    noise_std: float = 0.0,
    generator: torch.Generator | None = None,
    order: int = 2,
    window: int = 7,
    degree: int = 2,
) -> CorrectionSamples:
    """Samples F~ = dy/dt - G(y) of the missing term at every observed state.

    Args:
        trajectories: the observations, ``states (K, T, d)``.
        system: the misspecified system; its ``state_dim`` must equal d.
        derivative: how dy/dt is obtained:

            * ``"oracle"``: the paper's observation model, the exact ``G(y) + F(y)`` (``system.true_rhs``) plus
              noise; only for systems with a true correction (simulations, benchmarks);
            * ``"central"``: :func:`finite_difference` with ``order``;
            * ``"smooth"``: :func:`smoothed_derivative` with ``window`` and ``degree``.
        noise_std: standard deviation of i.i.d. Gaussian noise added to every target entry (for ``"oracle"`` this
            is the observation noise of the paper's model; for ``"central"`` / ``"smooth"`` it is extra noise
            added on top of the estimator's own error, e.g. to mimic noisy derivative observations). Must be a
            finite number >= 0; with 0 no random numbers are drawn.
        generator: optional ``torch.Generator`` for the noise (on the states' device), for reproducibility.
        order: finite-difference order for ``"central"`` (2 or 4).
        window: samples per local fit for ``"smooth"``.
        degree: polynomial degree of the local fits for ``"smooth"``.

    Returns:
        :class:`CorrectionSamples` with ``N = K * T`` samples, in the dtype and on the device of the states.

    Raises:
        InputError: ``trajectories`` / ``system`` of the wrong type, an unknown ``derivative``, a bad
            ``noise_std``, ``"oracle"`` for a system without a true correction, too few samples for the
            estimator, or non-finite samples (e.g. a state sitting on a singularity of G or F).
        ShapeError: the trajectories' state dimension differs from the system's.
    """
    if not isinstance(trajectories, Trajectories):
        raise InputError(
            f"trajectories: expected a torchmisspec Trajectories object, got {type(trajectories).__name__}; "
            "wrap arrays with Trajectories(times, states)"
        )
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
    if trajectories.state_dim != system.state_dim:
        raise ShapeError(
            f"trajectories: expected state dimension {system.state_dim} of system '{system.name}', "
            f"got trajectories.state_dim={trajectories.state_dim} (states {tuple(trajectories.states.shape)})"
        )
    if not isinstance(derivative, str) or derivative not in DERIVATIVE_ESTIMATORS:
        raise InputError(f"derivative: expected one of {list(DERIVATIVE_ESTIMATORS)}, got {derivative!r}")
    noise = check_real(noise_std, "noise_std", minimum=0.0)
    if generator is not None and not isinstance(generator, torch.Generator):
        raise InputError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")

    states = trajectories.states  # (K, T, d), finite (checked by Trajectories)
    K, T, d = states.shape
    if derivative == "oracle":
        if not system.has_correction:
            raise InputError(
                f"derivative='oracle': oracle derivatives need a system with a true correction F, and system "
                f"'{system.name}' has none; use 'central' or 'smooth' for real data"
            )
        check_finite(states, "trajectories.states")
        dydt = system.true_rhs(states)
    elif derivative == "central":
        dydt = finite_difference(states, trajectories.times, order=order)
    else:
        dydt = smoothed_derivative(states, trajectories.times, window=window, degree=degree)

    flat_states = states.reshape(K * T, d)
    targets = system.select_outputs(dydt.reshape(K * T, d) - system.known_rhs(flat_states))
    check_finite(targets, f"correction samples dy/dt - G(y) of system '{system.name}'")
    if noise > 0:
        eps = torch.randn(targets.shape, generator=generator, dtype=targets.dtype, device=targets.device)
        targets = targets + noise * eps
        check_finite(targets, f"correction samples with noise_std={noise_std!r} added")
    experiment = torch.arange(K, device=states.device).repeat_interleave(T)
    return CorrectionSamples(
        inputs=system.select_inputs(flat_states),
        targets=targets,
        states=flat_states,
        experiment=experiment,
    )
