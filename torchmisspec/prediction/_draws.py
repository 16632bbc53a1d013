"""The posterior's sampled paths (:meth:`CorrectedODE.posterior <torchmisspec.CorrectedODE.posterior>`): the
region they stay in, their one batched solve that stops a diverging draw where it leaves it, and the warning that
names the draws that left (issue 41: bands in seconds, always finite)."""

from __future__ import annotations

import math

import torch

from .._errors import IntegrationError, TorchMisspecWarning, warn
from .._ode import solve, widened_box

__all__ = ["REGION_LIMIT_WIDTHS", "REGION_WIDTHS", "draws_region", "solve_draws", "warn_left"]


#: :meth:`CorrectedODE.posterior`'s region: the box of the data, the initial conditions and the mean paths widened
#: this many times its width on each side. On theoph (fold 1, 64 draws) the draws that left it were those that left
#: the box widened ten times (the design's proxies'), and the diverging draws' way out to that one cost the solve
#: 4,800 right-hand sides against 1,750 here
REGION_WIDTHS = 2.0
#: ... and never beyond the box of the data and the initial conditions widened this many times (the design's
#: proxies' box): a mean path that itself diverges (a forecast that leaves the data, where F is the prior's guess)
#: no longer carries the region with it. On the UDE Lotka-Volterra protocol (one trajectory, RBF lengthscale 0.22,
#: forecast to t = 10) the mean path's exponential growth made the region 1,600 wide, and the draws, rough prior
#: functions over all of it, took 699 s
REGION_LIMIT_WIDTHS = 10.0


def draws_region(y0: torch.Tensor, mean_path: torch.Tensor, gp) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)`` ``(d,)``: where :meth:`CorrectedODE.posterior`'s draws stay: the box of the initial conditions,
    the mean paths (where computed) and the GP's observed states (``gp.samples_.states``, when recorded) widened
    :data:`REGION_WIDTHS` times its width on each side (:func:`~torchmisspec._ode.widened_box`, as the design's
    proxies: a width of at least a tenth of the component's size), within the box of the initial conditions and the
    observed states widened :data:`REGION_LIMIT_WIDTHS` times (when the observed states are recorded)."""
    d = y0.shape[-1]

    def finite(points):
        points = torch.cat(points)
        return points[torch.isfinite(points).all(-1)]

    known = [y0.detach()]
    states = getattr(getattr(gp, "samples_", None), "states", None)
    if isinstance(states, torch.Tensor) and states.dim() == 2 and states.shape[-1] == d:
        known.append(states.detach().to(y0))
    lo, hi = widened_box(finite([*known, mean_path.detach().reshape(-1, d)]), REGION_WIDTHS)
    if len(known) == 1:
        return lo, hi
    lo_max, hi_max = widened_box(finite(known), REGION_LIMIT_WIDTHS)
    return torch.maximum(lo, lo_max), torch.minimum(hi, hi_max)


def warn_left(left: torch.Tensor, stopped: list[int]) -> None:
    """One warning naming the draws ``left (S, B)`` that did not remain in the region to the end (``stopped``: the
    rows, ``s * B + b``, of those that stalled inside it)."""
    S, B = left.shape
    per = left.sum(0).tolist()
    by = ", ".join(f"{b}: {n} of {S}" for b, n in enumerate(per) if n)
    stalled = f"; {len(stopped)} of them stalled inside it instead" if stopped else ""
    warn(
        f"CorrectedODE.posterior: {int(left.sum())} of {S * B} sampled paths left the region (the box of the data, "
        f"the initial conditions and the mean paths widened {REGION_WIDTHS:g} times its width on each side: "
        f"posterior.region) and were stopped there{stalled}; by initial condition: {by[:400]}. Under those draws of F "
        "the trajectory diverges. Their paths are NaN from the first output time outside the region, and the "
        "bands, mean and quantiles come from the draws that remain (posterior.fraction_remaining: the fraction of "
        "each initial condition's draws that stayed to the end; where too few remain for a band's level, its "
        "entries are NaN, with a warning). Shorten the time span, or collect data nearer those states",
        TorchMisspecWarning,
    )


def solve_draws(field, y0: torch.Tensor, grid: torch.Tensor, settings: dict, B: int, box):
    """All sampled paths in one batched solve that stops a path where it leaves ``box`` (its derivative 0 from
    there: a diverging draw never holds the batch's steps back to the step limit). Where the solve still fails (a
    path stalls inside the box), the rows the solver names keep what it computed up to the failure and the others
    are solved again together. Returns ``(paths (S B, T, d), NaN from the first output time outside the box or not
    reached; right-hand-side evaluations of every solve, failed ones included; the rows that stalled; escaped
    (S B, T, d) int8: from a path's first output outside the box on, +1 / -1 for each component that was above /
    below the box there, 0 elsewhere)``."""
    n_rows, T = y0.shape[0], grid.shape[-1]
    timed = settings.get("timed", False)
    paths = y0.new_full((n_rows, T, y0.shape[-1]), math.nan)
    stopped: list[int] = []
    nfe = 0
    pending = torch.arange(n_rows, device=y0.device)
    while pending.numel():
        rows = pending

        def part(*args: torch.Tensor, rows=rows) -> torch.Tensor:  # the rows' own draws: field sees the whole batch
            full = y0.new_zeros(y0.shape).index_copy(0, rows, args[-1])
            if not timed:
                return field(full)[rows]
            t = args[0].new_zeros(n_rows).index_copy(0, rows, args[0])  # the other rows' times are not read
            return field(t, full)[rows]

        try:
            out, n = solve(
                field if rows.numel() == n_rows else part,
                y0[rows],
                grid if grid.dim() == 1 else grid[rows],
                what="CorrectedODE.posterior",
                label=lambda i, rows=rows: f"draw {int(rows[i]) // B} of initial condition {int(rows[i]) % B}",
                box=box,
                partial=True,
                **settings,
            )
            nfe += n
            paths[rows] = out
            break
        except IntegrationError as exc:
            named = [i for i in getattr(exc, "suspects", []) if i < rows.numel()]
            if not named:
                raise
            nfe += exc.nfe
            if exc.states is not None:  # the others are solved again; the named keep what was computed
                paths[rows] = exc.states
            else:  # a method that keeps nothing: the named rows are their initial conditions alone
                paths[rows[named], 0] = y0[rows[named]]
            stopped.extend(rows[named].tolist())
            keep = torch.ones(rows.numel(), dtype=torch.bool, device=rows.device)
            keep[named] = False
            pending = rows[keep]
    lo, hi = (b.to(paths) for b in box)
    above, below = paths > hi, paths < lo
    outside = (above | below).any(-1).cumsum(-1) > 0  # (S B, T): from the first output outside
    first = outside.to(torch.int8).argmax(-1)  # the first output outside (0 where none: masked below)
    rows = torch.arange(paths.shape[0], device=paths.device)
    side = above[rows, first].to(torch.int8) - below[rows, first].to(torch.int8)  # (S B, d): where it crossed
    escaped = torch.where(outside.unsqueeze(-1), side.unsqueeze(1), torch.zeros((), dtype=torch.int8))
    return paths.masked_fill(outside.unsqueeze(-1), math.nan), nfe, stopped, escaped
