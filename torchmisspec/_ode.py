"""Private batched ODE solve shared by :func:`simulate` and :class:`CorrectedODE`.

Many initial conditions are integrated in one torchdiffeq call. Per-experiment time grids ``(B, T)`` are handled
by integrating on the sorted union of all times and gathering each experiment's own times, so the batch still
costs one solve. Non-finite states or a solver that gives up raise :class:`IntegrationError`.

**Tolerance policy** (one rule for every solve in the package, dopri5 by default):

* :data:`SIMULATION_TOLERANCES` ``rtol=1e-10, atol=1e-12`` for simulations of a *given* model - the true system
  (:func:`~torchmisspec.simulate`), the known model's proxy trajectories (:mod:`torchmisspec.design`) and the true
  trajectories of a design - so that solver error never limits an accuracy check or a comparison of designs;
* :data:`PREDICTION_TOLERANCES` ``rtol=1e-7, atol=1e-9`` for the corrected model
  (:meth:`~torchmisspec.CorrectedODE.predict`), whose own error (F_hat - F) is orders of magnitude larger: tighter
  tolerances would cost steps without changing what is predicted.

Every public function that solves takes ``rtol``/``atol`` keywords to override its default.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchdiffeq import odeint

from ._errors import IntegrationError, ShapeError
from ._validation import as_tensor, check_finite, check_ndim, check_times

#: (rtol, atol) of simulations of a given model: the truth, the proxies (see the module docstring)
SIMULATION_TOLERANCES = (1e-10, 1e-12)
#: (rtol, atol) of the corrected model's predictions (see the module docstring)
PREDICTION_TOLERANCES = (1e-7, 1e-9)


def initial_conditions_and_times(
    y0, times, state_dim: int, check_states, *, dtype=None, device=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate ``y0 (B, d)`` (or ``(d,)``) and ``times (T,)`` or ``(B, T)`` for a batched solve."""
    y0 = as_tensor(y0, "y0", dtype=dtype, device=device)
    if y0.dim() == 1:
        y0 = y0.unsqueeze(0)
    check_ndim(y0, 2, "y0", f"(B, {state_dim})")
    check_states(y0, "y0")
    check_finite(y0, "y0")
    times = check_times(times, "times", per_row=True, dtype=y0.dtype, device=y0.device)
    if times.dim() == 2 and times.shape[0] != y0.shape[0]:
        raise ShapeError(f"times: expected ({y0.shape[0]}, T) to match y0 {tuple(y0.shape)}, got {tuple(times.shape)}")
    return y0, times


class _Autonomous(torch.nn.Module):
    """Wrap an autonomous field f(y) as torchdiffeq's func(t, y), counting evaluations."""

    def __init__(self, field: Callable[[torch.Tensor], torch.Tensor]) -> None:
        super().__init__()
        self.field = field
        self.nfe = 0

    def forward(self, t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        self.nfe += 1
        return self.field(y)


def solve(
    field: Callable[[torch.Tensor], torch.Tensor],
    y0: torch.Tensor,
    times: torch.Tensor,
    *,
    method: str = "dopri5",
    rtol: float = PREDICTION_TOLERANCES[0],
    atol: float = PREDICTION_TOLERANCES[1],
    options: dict | None = None,
    what: str = "ODE",
) -> tuple[torch.Tensor, int]:
    """Integrate dy/dt = field(y) from ``y0 (B, d)`` given at ``times[..., 0]``.

    Args:
        times: ``(T,)`` shared by all, or ``(B, T)`` one grid per initial condition; each row starts at the
            time of its initial condition. Rows may start at different times.

    Returns:
        states ``(B, T, d)`` and the number of right-hand-side evaluations.
    """
    func = _Autonomous(field)
    if times.dim() == 1:
        grid, gather = times, None
    else:
        # One solve on the union of all grids; row b starts at times[b, 0], so shift every row to start at 0
        # (autonomous system) and gather each row's own times afterwards.
        rel = times - times[:, :1]
        grid, inverse = torch.unique(rel.reshape(-1), sorted=True, return_inverse=True)
        gather = inverse.reshape(times.shape)
    try:
        sol = odeint(func, y0, grid, method=method, rtol=rtol, atol=atol, options=options)  # (T', B, d)
    except AssertionError as exc:  # torchdiffeq signals step-size underflow with an assertion
        raise IntegrationError(
            f"{what}: the solver gave up ({exc}); the trajectory probably blows up. Shorten the time span, "
            "start closer to the data, or check the model"
        ) from exc
    sol = sol.transpose(0, 1)  # (B, T', d)
    if gather is not None:
        sol = torch.gather(sol, 1, gather.unsqueeze(-1).expand(-1, -1, sol.shape[-1]))
    finite = torch.isfinite(sol).all(dim=-1).all(dim=-1)
    if not bool(finite.all()):
        bad = (~finite).nonzero().flatten().tolist()
        raise IntegrationError(
            f"{what}: the solution is not finite for {len(bad)} of {sol.shape[0]} initial condition(s) "
            f"(indices {bad[:10]}{' ...' if len(bad) > 10 else ''}); the trajectory blows up within the time span"
        )
    return sol, func.nfe
