"""Baseline designs: random initial conditions, and the agnostic design that ignores the known model."""

from __future__ import annotations

import dataclasses
import math
import time

import torch

from .._errors import ShapeError
from .._validation import as_tensor, check_finite, check_indices, check_ndim
from ..gp import CorrectionGP
from ..systems import MisspecifiedSystem
from ._common import (
    DesignResult,
    check_budget,
    check_candidates,
    check_partition,
    check_proxies,
    check_system,
    check_times,
    logdet_identity_plus,
)
from ._greedy import _Problem, greedy
from ._options import Partition, Proxy, checked_options

__all__ = ["random", "agnostic", "marginal_gains"]


def marginal_gains(
    indices, candidates, *, system: MisspecifiedSystem, times=None, gp: CorrectionGP, proxies=None, controls=None
) -> torch.Tensor:
    """Marginal proxy information gains (nats) of the candidates ``indices`` taken in the given order.

    One Cholesky factorization of ``I + K / sigma^2`` over all K T proxy points of the design: the log-diagonal of
    its k-th T x T diagonal block is the gain of the k-th pick given the earlier ones. Their sum is the design's
    :func:`information_gain`. ``controls``: for a system with inputs, every candidate's profile (as for
    :func:`greedy`).

    Returns:
        ``(K,)`` gains on the candidates' device.
    """
    cand = check_candidates(candidates, check_system(system, controls, with_controls=True))
    if isinstance(indices, DesignResult):
        indices = indices.indices
    n = cand.shape[0]
    # integers in range (not bools, not fractions: no quiet rounding); a design may repeat a candidate here
    idx = torch.tensor(check_indices(indices, n, "indices", distinct=False), dtype=torch.long)
    sel_prox = None
    if proxies is not None:
        sel_prox = check_proxies(proxies, n, system, None, dtype=cand.dtype, device=cand.device)[idx.to(cand.device)]
    # budget = K distinct candidates of the sub-problem; duplicates in ``indices`` are allowed here
    picked = None if controls is None else system.check_controls(controls, n)[idx.tolist()]
    sub = _Problem(
        cand[idx.to(cand.device)], idx.numel(), system, times, gp, None, None, sel_prox, 1e-9, controls=picked
    )
    K, T, d_in = sub.points.shape
    _, L = logdet_identity_plus(sub.kern(sub.points.reshape(K * T, d_in)), sub.kern.noise, "I + K / noise_variance")
    logs = torch.log(L.diagonal()).reshape(K, T).sum(-1)
    return (sub.d_out * logs).to(cand.device)


def _random_indices(n: int, budget: int, partition, generator) -> torch.Tensor:
    perm = torch.randperm(n, generator=generator)
    if partition is None:
        return perm[:budget]
    region, caps = (t.cpu() for t in partition)
    reg = region[perm]
    # rank of each position among the earlier positions of the same region
    order = torch.sort(reg, stable=True).indices
    starts = torch.zeros(int(caps.shape[0]) + 1, dtype=torch.long)
    starts[1:] = torch.cumsum(torch.bincount(reg, minlength=caps.shape[0]), 0)
    rank = torch.empty(n, dtype=torch.long)
    rank[order] = torch.arange(n) - starts[reg[order]]
    keep = perm[rank < caps[reg]]
    return keep[:budget]


def random(
    candidates,
    budget: int,
    *,
    generator: torch.Generator | None = None,
    system: MisspecifiedSystem | None = None,
    times=None,
    gp: CorrectionGP | None = None,
    partition: Partition | None = None,
    proxies=None,
    progress: bool = False,
    controls=None,
) -> DesignResult:
    """A random design: ``budget`` distinct candidates drawn uniformly (respecting region capacities if given).

    With a partition, candidates are scanned in a uniformly random order and kept while their region has room,
    which gives a uniformly random set per region once the region counts are fixed.

    The marginal gains (nats, pick order) and the total information gain are computed when ``system``, ``gp`` and
    ``times`` (or ``proxies``) are all given, so a random design can be compared with a greedy one; if any of
    them is missing, ``gains`` is all NaN and ``information_gain`` is NaN (no error).

    Args:
        candidates: ``(N, d)``.
        budget: number of experiments, 1 <= budget <= N.
        generator: a ``torch.Generator`` for reproducible draws.
        system: as for :func:`greedy`; only needed for the gains (likewise ``times``, ``gp``, ``proxies``).
        times: as for :func:`greedy`.
        gp: as for :func:`greedy`.
        partition: a :class:`Partition`, as for :func:`greedy`.
        proxies: ``(N, T, d)`` given proxy paths (as ``greedy``'s ``Proxy(paths=...)``), for the gains.
        progress: accepted for a signature uniform with :func:`greedy`; a random draw has nothing to show.
        controls: as for :func:`greedy` (a candidate is an initial state and a profile); for the gains.
    """
    start = time.perf_counter()
    if system is not None:
        cand = check_candidates(candidates, check_system(system, controls, with_controls=True))
    else:
        cand = check_ndim(as_tensor(candidates, "candidates"), 2, "candidates", "(N, d)")
        if cand.shape[0] < 1:
            raise ShapeError("candidates: expected at least one candidate, got shape (0, d)")
        check_finite(cand, "candidates")
    n = cand.shape[0]
    budget = check_budget(budget, n)
    partition = checked_options(partition, None, None)[0]
    regions, capacities = (None, None) if partition is None else (partition.regions, partition.capacities)
    part = check_partition(regions, capacities, n, budget, "cpu")
    if proxies is not None:  # checked even when the gains are not computed: a wrong shape is a mistake either way
        if system is not None:
            proxies = check_proxies(proxies, n, system, None, dtype=cand.dtype, device=cand.device)
        else:
            proxies = check_ndim(as_tensor(proxies, "proxies", dtype=cand.dtype), 3, "proxies", f"({n}, T, d)")
            if proxies.shape[0] != n:
                raise ShapeError(f"proxies: expected one proxy trajectory per candidate ({n}), got {proxies.shape[0]}")
    idx = _random_indices(n, budget, part, generator).to(cand.device)
    have_all = system is not None and gp is not None and (times is not None or proxies is not None)
    prox = None
    if have_all:
        gains = marginal_gains(idx, cand, system=system, times=times, gp=gp, proxies=proxies, controls=controls)
        info = float(gains.sum())
        if proxies is not None:
            prox = proxies[idx.to(proxies.device)].to(cand.device)
    else:
        gains = torch.full((budget,), math.nan, dtype=cand.dtype, device=cand.device)
        info = math.nan
    return DesignResult(
        indices=idx,
        gains=gains,
        information_gain=info,
        points=cand[idx],
        method="random",
        evaluations=0,
        proxies=prox,
        elapsed=time.perf_counter() - start,
    )


def agnostic(
    candidates,
    budget: int,
    *,
    system: MisspecifiedSystem,
    times,
    gp: CorrectionGP,
    method: str = "lazy",
    partition: Partition | None = None,
    progress: bool = False,
    **kwargs,
) -> DesignResult:
    """The design that ignores the known model: greedy on proxy trajectories that stay at the initial condition.

    Every one of the T proxy points of a candidate is the candidate itself (the trajectories of G = 0), so the
    criterion only sees where experiments start, not where the dynamics take them (paper §5.3's "agnostic"
    design). Same arguments and result as :func:`greedy` (``method`` is ``"agnostic-lazy"`` / ``"agnostic-plain"``
    / ``"agnostic-naive"``); gains are those of the constant proxies. With ``controls`` (a system with inputs), the
    inputs of F are still the profiles' values at each time.
    """
    system = check_system(system, kwargs.get("controls"), with_controls=True)
    cand = check_candidates(candidates, system)
    t = check_times(times, dtype=cand.dtype, device=cand.device)
    proxies = cand.unsqueeze(1).expand(-1, t.shape[0], -1)
    res = greedy(
        cand,
        budget,
        system=system,
        times=t,
        gp=gp,
        method=method,
        partition=partition,
        proxy=Proxy(paths=proxies),
        progress=progress,
        **kwargs,
    )
    return dataclasses.replace(res, method=f"agnostic-{res.method}")
