"""Proxy trajectories (paper §4.2): what the known model G alone predicts from every candidate."""

from __future__ import annotations

import torch

from .._errors import InputError, IntegrationError, TorchMisspecWarning, warn
from .._ode import SIMULATION_TOLERANCES, widened_box
from .._validation import progress_bar
from ..data import simulate
from ..parallel import map_tasks
from ..systems import MisspecifiedSystem
from ._common import check_candidates, check_system, check_times

__all__ = ["proxy_trajectories", "corrected_proxies", "PROXY_TOLERANCES"]

#: (rtol, atol) of the corrected proxies: a proxy only stands in for the unknown true trajectory, so 1e-6 is ample
PROXY_TOLERANCES = (1e-6, 1e-8)


def corrected_proxies(
    system: MisspecifiedSystem, gp, y0: torch.Tensor, times: torch.Tensor, controls=None
) -> torch.Tensor:
    """The corrected model's trajectories (G + the fitted GP's posterior mean) from ``y0 (N, d)`` (under
    ``controls``, one profile each, for a system with inputs): the proxies a design with data uses
    (:func:`~torchmisspec.design.greedy` with ``proxy="corrected"``, :func:`proxy_check`). Where the corrected
    model blows up from a candidate (its solve fails, or its trajectory leaves :func:`escape_box`), G's proxy stands
    in, with a warning."""
    out, failed = _corrected(system, gp, y0, times, controls, escape_box(y0))
    _warn_failed(failed, y0.shape[0])
    return out


#: a corrected proxy that leaves the candidates' box widened by this many times its width on each side is taken as
#: blowing up (the solve stops it there, and G's proxy stands in): far outside every candidate the posterior mean is
#: an extrapolation, and such a row would otherwise hold back its batch's steps until the solver gives up
ESCAPE_WIDTHS = 10.0


def escape_box(y0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)`` ``(d,)``: the box of the candidates ``y0 (N, d)`` widened by :data:`ESCAPE_WIDTHS` times its
    width on each side (a width of at least a tenth of the component's size where the candidates do not vary)."""
    return widened_box(y0, ESCAPE_WIDTHS)


def _warn_failed(failed: list[int], n: int) -> None:
    if failed:
        warn(
            f"corrected proxies: the corrected model (G + the GP's posterior mean) blows up from {len(failed)} of "
            f"{n} candidates (e.g. {sorted(failed)[:5]}: its solve fails, or leaves the candidates' box widened "
            f"{ESCAPE_WIDTHS:g} times its width): far from the data the correction is an extrapolation. Their "
            "proxies are the known model's alone (the paper's proxy); the design still ranks them, by the "
            "information along G's trajectories",
            TorchMisspecWarning,
        )


def _corrected(system, gp, y0: torch.Tensor, times: torch.Tensor, controls, box) -> tuple[torch.Tensor, list[int]]:
    """The corrected proxies from ``y0`` and the rows where G's had to stand in (see :func:`corrected_proxies`): those
    whose solve fails, and those that leave ``box`` (:func:`escape_box`)."""
    from ..prediction.dynamics import CorrectedODE

    model = CorrectedODE(system, gp)
    failed: list[int] = []

    def one(rows: torch.Tensor) -> torch.Tensor:
        u = None if controls is None else controls[rows.tolist()]
        tol = dict(rtol=PROXY_TOLERANCES[0], atol=PROXY_TOLERANCES[1])
        with torch.no_grad():
            paths = model._solve(y0[rows], times, u, box=box, **tol)
        lo, hi = (b.to(paths) for b in box)
        left = ((paths < lo) | (paths > hi)).flatten(1).any(-1).nonzero().flatten()
        if left.numel():  # stopped at the box: G's proxy stands in
            gone = rows[left]
            failed.extend(gone.tolist())
            paths[left] = proxy_trajectories(system, y0[gone], times, controls=None if u is None else u[left.tolist()])
        return paths

    def alone(row: int) -> torch.Tensor:
        """One candidate's corrected proxy, or G's where the corrected model cannot be integrated from it."""
        rows = torch.tensor([row], device=y0.device)
        try:
            return one(rows)
        except IntegrationError:
            failed.append(row)
            return proxy_trajectories(system, y0[rows], times, controls=None if controls is None else controls[[row]])

    def solve(rows: torch.Tensor) -> torch.Tensor:
        """The corrected proxies of ``y0[rows]``. Where the corrected model cannot be integrated from a candidate (the
        posterior mean far from the data can grow without bound), the solver's suspects (the rows with the largest
        state or derivative where it gave up) are solved alone and the rest together again; without suspects, the
        halves are solved apart. Each failing solve runs to the step limit, so isolating the suspects first takes
        a few solves where halving took one per level and failure."""
        out: dict[int, torch.Tensor] = {}
        pending = rows
        while pending.numel():
            try:
                for row, path in zip(pending.tolist(), one(pending), strict=True):
                    out[row] = path
                break
            except IntegrationError as exc:
                suspects = sorted(set(getattr(exc, "rows", None) or []))
                if pending.numel() == 1:
                    out[int(pending[0])] = alone(int(pending[0]))[0]
                    break
                if not suspects:
                    half = pending.numel() // 2
                    for part in (pending[:half], pending[half:]):
                        for row, path in zip(part.tolist(), solve(part), strict=True):
                            out[row] = path
                    break
                keep = torch.ones(pending.numel(), dtype=torch.bool, device=pending.device)
                keep[suspects] = False
                for row in pending[~keep].tolist():
                    out[row] = alone(row)[0]
                pending = pending[keep]
        return torch.stack([out[row] for row in rows.tolist()])

    return solve(torch.arange(y0.shape[0], device=y0.device)), failed


def proxy_trajectories(
    system: MisspecifiedSystem,
    candidates,
    times,
    *,
    known_only: bool = True,
    controls=None,
    method: str = "dopri5",
    rtol: float = SIMULATION_TOLERANCES[0],
    atol: float = SIMULATION_TOLERANCES[1],
    max_steps: int | None = None,
) -> torch.Tensor:
    """The known model's trajectories y_G(t) from every candidate initial condition, in one batched computation.

    For a linear known model (``system.known_matrix`` = A) the closed form y_G(t_i) = expm(A (t_i - t_0)) y0 is used:
    one batched matrix exponential for all T times, then one einsum for all candidates (no ODE solver). Otherwise
    all candidates are integrated together in one batched torchdiffeq solve.

    Args:
        system: the misspecified system.
        candidates: ``(N, d)`` initial conditions, the states at ``times[0]``.
        times: ``(T,)`` strictly increasing observation times (the first is the time of the initial condition).
        known_only: ``True`` (the design proxy) integrates G alone; ``False`` integrates the true system G + F
            (needs a system with a true correction; used to assess the proxy).
        method: torchdiffeq method for the non-linear case (dopri5 by default).
        rtol: relative tolerance (the package's simulation tolerance by default: see :mod:`torchmisspec._ode`).
        atol: absolute tolerance (likewise).
        max_steps: most solver steps (default 10,000).
        controls: for a system with inputs, one profile per candidate (:class:`~torchmisspec.signals.Controls`).

    Returns:
        ``(N, T, d)`` states, in the candidates' dtype and on their device.
    """
    system = check_system(system, controls, with_controls=True)
    y0 = check_candidates(candidates, system)
    controls = system.check_controls(controls, y0.shape[0])
    t = check_times(times, dtype=y0.dtype, device=y0.device)
    if not known_only and not system.has_correction:
        raise InputError(
            f"known_only=False: system '{system.name}' has no true correction F to integrate; pass "
            "known_only=True for the proxy of the known model"
        )
    if known_only and system.known_matrix is not None and system.autonomous:
        A = system.known_matrix.to(dtype=y0.dtype, device=y0.device)
        E = torch.linalg.matrix_exp(A.unsqueeze(0) * (t - t[0]).reshape(-1, 1, 1))  # (T, d, d)
        out = torch.einsum("tij,nj->nti", E, y0)
        if not bool(torch.isfinite(out).all()):
            raise IntegrationError(
                f"proxy_trajectories({system.name}): the known linear model's trajectories overflow within the time "
                f"span [{float(t[0]):.4g}, {float(t[-1]):.4g}] (expm(A t) y0 is not finite); shorten the span"
            )
        return out
    return simulate(
        system,
        y0,
        t,
        known_only=known_only,
        controls=controls,
        method=method,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
    ).states


#: The proxy trajectories a design may use: G alone (the paper's), or G + the GP's posterior mean.
PROXIES = ("known", "corrected")


def choose_proxy(proxy: str | None, gp) -> str:
    """``proxy`` checked, or the default: ``"corrected"`` for a fitted GP (closer to the truth once data are in),
    ``"known"`` otherwise."""
    if proxy is None:
        return "corrected" if gp.is_fitted else "known"
    if proxy not in PROXIES:
        raise InputError(f"proxy: expected one of {PROXIES}, got {proxy!r}")
    if proxy == "corrected" and not gp.is_fitted:
        raise InputError("proxy='corrected': an unfitted gp has no correction to add to G; fit it or pass 'known'")
    return proxy


#: candidates per solve of a design's proxies: the solves of a large set are independent chunks (each its own
#: adaptive steps; a candidate that blows up holds back only its chunk), run one after another or through an executor
PROXY_CHUNK = 4096


def proxy_paths(
    proxy: str,
    system: MisspecifiedSystem,
    gp,
    y0: torch.Tensor,
    times: torch.Tensor,
    controls=None,
    executor=None,
    progress: bool = False,
):
    """The ``proxy`` trajectories (:func:`choose_proxy`) from ``y0 (N, d)``: ``(N, T, d)``. Solved in chunks of
    :data:`PROXY_CHUNK` candidates (a linear autonomous G in one closed form), through ``executor`` when one is
    given (a ``concurrent.futures.Executor``): the same numbers either way; ``progress``: a bar over the chunks."""
    if proxy == "known" and system.known_matrix is not None and system.autonomous:
        return proxy_trajectories(system, y0, times, controls=controls)  # expm: no solver
    n = y0.shape[0]
    box = escape_box(y0)  # of all the candidates: every chunk stops its rows at the same box
    starts = range(0, n, PROXY_CHUNK)
    tasks = [
        (
            proxy,
            system,
            gp,
            y0[s : s + PROXY_CHUNK],
            times,
            None if controls is None else controls[list(range(s, min(s + PROXY_CHUNK, n)))],
            box,
        )
        for s in starts
    ]
    with progress_bar(progress and len(tasks) > 1, len(tasks), f"design: {proxy} proxies (N={n})", "chunk") as bar:
        parts = map_tasks(_proxy_chunk, tasks, executor, each=lambda _: bar.update())
    _warn_failed([s + row for s, (_, failed) in zip(starts, parts, strict=True) for row in failed], n)
    return torch.cat([paths for paths, _ in parts])


def _proxy_chunk(task) -> tuple[torch.Tensor, list[int]]:
    """One chunk of :func:`proxy_paths` (a task for an executor): its paths and the rows where G's stood in."""
    proxy, system, gp, y0, times, controls, box = task
    if proxy == "known":
        return proxy_trajectories(system, y0, times, controls=controls), []
    return _corrected(system, gp, y0, times, controls, box)
