"""G with each row's own parameters: one call for a batch whose rows differ in theta.

A fit's Jacobian solves copies of the experiments at k + 1 values of theta, a prediction's bands at a draw of theta
per path, a population at each experiment's own. Calling G once per distinct theta costs k + 1 (or S) calls of G per
right-hand side; on nlme's Remifentanil (16 parameters: 8 subjects' k and V) those calls were most of the fit's time.
:func:`per_row` finds, at the first batch whose rows differ, the fastest way that gives the row-by-row answer.
"""

from __future__ import annotations

import torch

from .._errors import InputError, ShapeError
from .._user_code import call_user, checked_output

__all__ = ["per_row", "rows_of"]


def per_row(known, autonomous: bool):
    """``call(t (B,), y (B, d), u (B, m), theta (B, k))``: the user's G with each row's own theta. Fastest first: G
    called once with theta as ``(k, B)`` columns (a G written with ``theta[0] * y[..., 0]`` broadcasts them over the
    rows), kept only where it agrees with the row-by-row answer at the first call whose rows differ in theta; else
    ``torch.func.vmap`` of G; else one call per distinct theta (a G with Python control flow on a value)."""

    def single(t, y, u, th):
        return known(y, th) if autonomous else known(t, y, u, th)

    batched = torch.func.vmap(single, in_dims=(0, 0, 0, 0))
    state = {"way": None}

    def grouped(t, y, u, theta):
        out = torch.empty_like(y)
        unique, inverse = torch.unique(theta.detach(), dim=0, return_inverse=True)
        for g in range(unique.shape[0]):
            rows = (inverse == g).nonzero().flatten()
            out[rows] = single(t[rows], y[rows], u[rows], unique[g])  # G's own convention: one theta (k,)
        return out

    def direct(t, y, u, theta):
        return single(t, y, u, theta.T)

    def vmapped(t, y, u, theta):
        return batched(t, y, u, theta)

    def call(t, y, u, theta):
        if state["way"] is None:
            if y.shape[0] < 2 or bool((theta == theta[:1]).all()):  # rows alike cannot tell a wrong way
                return grouped(t, y, u, theta)
            state["way"] = _first_that_agrees((direct, vmapped), grouped(t, y, u, theta), (t, y, u, theta), grouped)
        return state["way"](t, y, u, theta)

    return call


def _first_that_agrees(ways, reference: torch.Tensor, args, fallback):
    """The first of ``ways`` whose answer on ``args`` is ``reference`` (``fallback`` when none is)."""
    for way in ways:
        try:
            out = way(*args)
        except Exception:  # noqa: BLE001 - a way G does not support: the next
            continue
        if isinstance(out, torch.Tensor) and out.shape == reference.shape and torch.allclose(out, reference):
            return way
    return fallback


def rows_of(system, y: torch.Tensor, t, u, theta: torch.Tensor) -> torch.Tensor:
    """:meth:`MisspecifiedSystem.rows_rhs <torchmisspec.MisspecifiedSystem.rows_rhs>`: G of ``system`` for states
    ``(B, d)`` with each row's parameters ``theta (B, k)``, its output checked (the per-row caller kept on it)."""
    if system.theta is None:
        raise InputError(f"system '{system.name}': rows_rhs expected a system with uncertain parameters, got none")
    y = system.check_states(y, "y")
    if y.dim() != 2 or theta.shape != (y.shape[0], system.theta.shape[0]):
        raise ShapeError(
            f"rows_rhs: expected states (B, {system.state_dim}) and parameters (B, {system.theta.shape[0]}), got "
            f"{tuple(y.shape)} and {tuple(theta.shape)}"
        )
    if "_rows" not in system.__dict__:
        system._rows = per_row(system.known, system.autonomous)
    t, u = system._time_and_controls(y, t, u)
    what = f"system '{system.name}': G"
    out = call_user(lambda z: system._rows(t.expand(y.shape[0]), z, u, theta.to(y)), y, what)
    return checked_output(out, y.shape, what, y)
