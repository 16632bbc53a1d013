"""Which times to measure: a per-experiment sample budget spent where the samples teach the most about F.

For experiments already chosen (initial states, and input profiles for a system with inputs), each candidate time
t_i of experiment k is one candidate *sample*: the state of the proxy trajectory of k at t_i (G alone, or G + the
GP's mean once data are in). Choosing at most ``per_experiment`` of them in every experiment is a partition matroid
over the K x T candidate samples, and the criterion is the one :func:`~torchmisspec.design.greedy` maximises
(information about F, or the domain criterion), conditioned on the GP's data: so this is ``greedy`` over one-point
proxies with one region per experiment. Nearby times along one trajectory carry nearly the same information, so the
picks spread along each path where it moves through new states, and thin out where it rests.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .._errors import InputError
from .._validation import check_flag, check_positive_int
from ..gp import CorrectionGP
from ..systems import MisspecifiedSystem
from ._common import DesignResult, check_candidates, check_system, check_times
from ._greedy import greedy
from ._options import DomainCriterion, Partition, Proxy
from ._proxy import choose_proxy, proxy_paths

__all__ = ["SamplingTimes", "sampling_times"]


@dataclass(frozen=True)
class SamplingTimes:
    """The times chosen for each experiment (:func:`sampling_times`).

    Attributes:
        times: one ``(n_k,)`` tensor of chosen times per experiment, increasing.
        indices: one ``(n_k,)`` tensor of their positions in the candidate times per experiment.
        design: the underlying :class:`DesignResult` over the K x T candidate samples (candidate ``k * T + i`` is
            time ``i`` of experiment ``k``; its gains, information gain and diagnostics).
    """

    times: tuple[torch.Tensor, ...]
    indices: tuple[torch.Tensor, ...]
    design: DesignResult

    def __repr__(self) -> str:
        counts = [len(t) for t in self.times]
        return (
            f"SamplingTimes({len(counts)} experiments, {sum(counts)} times, {min(counts)}-{max(counts)} each; "
            f"{self.design.diagnostics.get('criterion', 'information')} gain {self.design.information_gain:.4g})"
        )


def sampling_times(
    initial_states,
    times,
    per_experiment: int,
    *,
    system: MisspecifiedSystem,
    gp: CorrectionGP,
    controls=None,
    criterion: str | DomainCriterion = "information",
    proxy: Proxy | None = None,
    progress: bool = False,
    skip_first: bool = False,
    **options,
) -> SamplingTimes:
    """Choose at most ``per_experiment`` of the candidate ``times`` to measure in each experiment.

    Args:
        initial_states: ``(K, d)`` the experiments' initial states (e.g. a design's picks).
        times: ``(T,)`` candidate measurement times, strictly increasing; the first is the time of the initial state.
        per_experiment: the sample budget of each experiment, 1 <= per_experiment <= T.
        system: the misspecified system.
        gp: the correction GP (a prior with its hyperparameters set, or fitted: the choice is then conditioned on its
            data, see :func:`~torchmisspec.design.greedy`'s ``condition``).
        controls: for a system with inputs, the K experiments' input profiles (the proxies run under them; where F
            depends on an input, each sample's inputs are the profile's values at its time).
        criterion: ``"information"`` or a :class:`~torchmisspec.design.DomainCriterion` (``"domain"``), as for
            :func:`~torchmisspec.design.greedy`.
        proxy: a :class:`~torchmisspec.design.Proxy` with ``"known"`` or ``"corrected"`` dynamics (default: corrected
            for a fitted GP), as for ``greedy``; its paths are the ones computed here.
        progress: a progress bar over the picks.
        skip_first: the first time is only the initial state's, never a sample (a new subject's design: its start is
            known). Default: it is a candidate like the others.
        **options: further keywords of :func:`~torchmisspec.design.greedy` (``method``, ``condition``, ``engine``,
            ...).

    Returns:
        :class:`SamplingTimes`: every experiment's chosen times, increasing (each experiment gets exactly
        ``per_experiment``: the criterion is monotone, so the budget is always spent).
    """
    system = check_system(system, controls, with_controls=True)
    if not isinstance(gp, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP, got {type(gp).__name__}")
    for key in ("partition", "proxy", "times", "candidates"):
        if key in options:
            raise InputError(
                f"{key}: expected none (sampling_times sets it: one region of candidate times per experiment), got one"
            )
    kd = dict(dtype=gp.dtype, device=gp.device)
    y0 = check_candidates(initial_states, system, name="initial_states", **kd)
    grid = check_times(times, **kd)
    K, T = y0.shape[0], grid.numel()
    per_experiment = check_positive_int(per_experiment, "per_experiment")
    first = int(check_flag(skip_first, "skip_first"))
    if per_experiment > T - first:
        raise InputError(
            f"per_experiment: expected at most the {T - first} candidate times, got {per_experiment}; pass more "
            "candidate times"
        )
    controls = system.check_controls(controls, K)
    if proxy is not None and (not isinstance(proxy, Proxy) or proxy.paths is not None):
        raise InputError(
            f"proxy: expected a design.Proxy with dynamics 'known' or 'corrected' (sampling_times solves the paths), "
            f"got {proxy!r:.80}"
        )
    paths = proxy_paths(choose_proxy(None if proxy is None else proxy.dynamics, gp), system, gp, y0, grid, controls)
    width = system.state_dim
    if system.uses_controls:  # F's inputs include u: each sample carries the inputs at its own time
        paths = torch.cat([paths, controls.at(grid.expand(K, -1)).to(paths)], dim=-1)
        width += system.num_controls
    Tc = T - first
    samples = paths[:, first:].reshape(K * Tc, 1, width)  # candidate k Tc + i: time first + i of experiment k
    region = torch.arange(K, device=samples.device).repeat_interleave(Tc)
    # the samples' view of the system: F's inputs (states, then inputs u) and outputs; G is in the proxies already
    view = MisspecifiedSystem(
        lambda y: torch.zeros_like(y),
        width,
        correction_inputs=system.correction_inputs,
        correction_outputs=system.correction_outputs,
        domain=system.domain,
        name=system.name,
    )
    design = greedy(
        samples[:, 0],
        K * per_experiment,
        system=view,
        gp=gp,
        partition=Partition(region, [per_experiment] * K),
        proxy=Proxy(paths=samples),
        criterion=criterion,
        progress=progress,
        **options,
    )
    picked = design.indices.to(samples.device)
    chosen = [torch.sort(picked[picked // Tc == k] % Tc).values + first for k in range(K)]
    return SamplingTimes(tuple(grid[c] for c in chosen), tuple(chosen), design)
