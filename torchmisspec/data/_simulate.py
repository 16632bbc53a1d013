"""Trajectories of a system's dynamics: :func:`simulate` (see :mod:`torchmisspec.data`)."""

from __future__ import annotations

import torch

from .._errors import InputError, IntegrationError, ShapeError
from .._ode import SIMULATION_TOLERANCES, initial_conditions_and_times, solve
from .._validation import as_tensor, check_flag
from ..parallel import adaptive_threads
from ..systems import MisspecifiedSystem
from ._input import _is_number
from ._trajectories import Trajectories


@adaptive_threads()
def simulate(
    system: MisspecifiedSystem,
    y0,
    times,
    *,
    known_only: bool = False,
    controls=None,
    method: str = "dopri5",
    rtol: float = SIMULATION_TOLERANCES[0],
    atol: float = SIMULATION_TOLERANCES[1],
    max_steps: int | None = None,
) -> Trajectories:
    """Integrate the true dynamics G + F from every initial condition in one batched solve.

    Args:
        system: the system; for one without a true correction the known model G alone is integrated.
        y0: initial conditions ``(K, d)`` (or ``(d,)`` for one), the states at ``times[..., 0]``.
        times: ``(T,)`` shared, ``(K, T)`` per experiment, or a list of K ``(T_k,)`` arrays of different lengths
            (ragged: one batched solve per distinct length); strictly increasing.
        known_only: integrate the misspecified model G alone (the proxy / baseline trajectories).
        controls: for a system with controls, the K experiments' input profiles
            (:class:`~torchmisspec.signals.Controls`); they are kept on the result.
        method: torchdiffeq method (dopri5 by default).
        rtol: relative tolerance (the package's simulation tolerance by default, see :mod:`torchmisspec._ode`:
            this is the ground truth).
        atol: absolute tolerance (likewise).
        max_steps: most solver steps (default 10,000); beyond it :class:`IntegrationError` names the initial
            conditions that stalled the solve.

    Returns:
        :class:`Trajectories` with ``states (K, T, d)`` (ragged for ragged times), named as the system's states.
    """
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
    known_only = check_flag(known_only, "known_only")
    if isinstance(times, (list, tuple)) and len(times) > 0 and not _is_number(times[0]):
        y0 = as_tensor(y0, "y0")
        y0 = y0.unsqueeze(0) if y0.dim() == 1 else y0
        if y0.dim() != 2 or y0.shape[0] != len(times):
            raise ShapeError(
                f"y0: expected ({len(times)}, {system.state_dim}) initial conditions, one per time array, got shape "
                f"{tuple(y0.shape)}"
            )
        grids = [as_tensor(t, f"times[{k}]", dtype=y0.dtype, device=y0.device) for k, t in enumerate(times)]
        if any(t.dim() != 1 for t in grids):
            shapes = [tuple(t.shape) for t in grids]
            raise ShapeError(f"times: expected a list of 1-D (T_k,) arrays, got shapes {shapes}")
        if len({len(t) for t in grids}) == 1:
            times = torch.stack(grids)
        else:
            controls = system.check_controls(controls, len(grids))
            options = dict(known_only=known_only, method=method, rtol=rtol, atol=atol, max_steps=max_steps)
            groups: dict[int, list[int]] = {}
            for k, t in enumerate(grids):
                groups.setdefault(len(t), []).append(k)
            states: list = [None] * len(grids)
            for idx in groups.values():
                part_controls = None if controls is None else controls[idx]
                part = simulate(
                    system, y0[idx], torch.stack([grids[k] for k in idx]), controls=part_controls, **options
                )
                for i, k in enumerate(idx):
                    states[k] = part.states[i]
            return Trajectories(grids, states, controls=controls, state_names=system.state_names)
    y0, times = initial_conditions_and_times(y0, times, system.state_dim, system.check_states)
    controls = system.check_controls(controls, y0.shape[0])
    if controls is not None:
        controls = controls.to(dtype=y0.dtype, device=y0.device)
    rhs = system.known_rhs if known_only else system.true_rhs
    field, timed, jumps = system.solver_field(rhs, controls)
    with torch.no_grad():
        states, _ = solve(
            field,
            y0,
            times,
            method=method,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
            what=f"simulate({system.name})",
            timed=timed,
            jumps=jumps,
        )
    return Trajectories(times, states, controls=controls, state_names=system.state_names)


def simulate_known_each(system: MisspecifiedSystem, trajectories: Trajectories, **options) -> list[torch.Tensor | None]:
    """The known model G alone from each experiment's first observed state over its own times, one experiment at a
    time: ``(T_k, d)`` states, or ``None`` where G cannot be integrated (:class:`IntegrationError`). For when a
    batched ``simulate(..., known_only=True)`` failed: G may diverge where the true system does not, which is what a
    correction may exist to fix. ``options``: as for :func:`simulate`."""
    if not isinstance(trajectories, Trajectories):
        raise InputError(f"trajectories: expected a torchmisspec.Trajectories, got {type(trajectories).__name__}")
    out: list[torch.Tensor | None] = []
    first = trajectories.initial_conditions  # missing entries estimated
    controls = trajectories.controls
    for k, (times, _) in enumerate(trajectories.experiments()):
        own = None if controls is None else controls[[k]]
        try:
            out.append(simulate(system, first[k : k + 1], times, known_only=True, controls=own, **options).states[0])
        except IntegrationError:
            out.append(None)
    return out
