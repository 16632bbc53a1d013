"""The option objects of :func:`~torchmisspec.design.greedy`: each groups the keywords of one question.

* :class:`Partition` - the budget's shape: at most so many experiments per region (a partition matroid).
* :class:`Proxy` - the trajectories along which a candidate's samples are predicted (G alone, G corrected by the
  GP's mean, or given ones).
* :class:`DomainCriterion` - the criterion that aims the design at a box D of F's inputs, with its quadrature.
* :class:`Engine` - how the greedy search runs: batches, screening, ties, the stochastic draw. Except the draw
  (``epsilon``, ``generator``), none of them changes the picks.

They are small frozen dataclasses, like diffrax's ``PIDController`` or ``SaveAt``: built once, checked at
construction (what depends on the candidates, e.g. one region label per candidate, is checked by the design).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from .._errors import InputError
from .._validation import check_positive_int, check_real
from ._domain import CRITERIA, DomainCriterion
from ._proxy import PROXIES
from ._readings import ReadoutCriterion

__all__ = ["DomainCriterion", "Engine", "Partition", "Proxy"]

EPSILON = 0.01  # method="stochastic": the default epsilon of the (1 - 1/e - epsilon) guarantee


@dataclass(frozen=True)
class Partition:
    """A partition-matroid budget: at most ``capacities[r]`` of the picks among the candidates of region r.

    Greedy then guarantees half the optimum instead of (1 - 1/e) (Fisher, Nemhauser, Wolsey 1978).

    Attributes:
        regions: ``(N,)`` integer region label per candidate (checked against the candidates by the design).
        capacities: most picks per region: a mapping label -> count, or a sequence indexed by label.
    """

    regions: Any
    capacities: Any

    def __post_init__(self) -> None:
        if self.regions is None:
            raise InputError(
                "Partition.regions: expected an integer region label per candidate, got None; pass "
                "Partition(regions=labels, capacities=...) or no partition at all"
            )
        caps = self.capacities
        if isinstance(caps, str) or not isinstance(caps, (Mapping, Sequence, torch.Tensor)):
            raise InputError(
                "Partition.capacities: expected a mapping label -> most picks or a sequence indexed by label, got "
                f"{type(caps).__name__}; e.g. Partition(regions, {{0: 3, 1: 6}})"
            )


@dataclass(frozen=True)
class Proxy:
    """The trajectories a candidate experiment's samples are predicted along (the design's proxy, paper §4.1).

    Attributes:
        dynamics: ``"known"`` (G alone, the paper's proxy) or ``"corrected"`` (G + the GP's posterior mean,
            :class:`~torchmisspec.CorrectedODE`, closer to the truth once data are in). Default ``None``:
            ``"corrected"`` for a fitted GP, ``"known"`` otherwise.
        paths: ``(N, T, d)`` trajectories to use as they are, one per candidate, instead of solving (e.g. the
            agnostic design's constant paths); ``dynamics`` must then be left ``None``.
    """

    dynamics: str | None = None
    paths: Any = None

    def __post_init__(self) -> None:
        if self.dynamics is not None and self.dynamics not in PROXIES:
            raise InputError(
                f"Proxy.dynamics: expected one of {PROXIES} or None (the default for the GP), got {self.dynamics!r}"
            )
        if self.dynamics is not None and self.paths is not None:
            raise InputError(
                f"Proxy: expected either dynamics to solve or given paths, got both (dynamics={self.dynamics!r}); "
                "drop dynamics when passing paths"
            )


@dataclass(frozen=True)
class Engine:
    """How the greedy search runs (lazy and stochastic greedy; ``tie_tol`` for every method).

    Attributes:
        batch_size: lazy greedy's first batch of re-evaluations per pick (doubling while needed; same picks for
            any value).
        tie_tol: relative tolerance in [0, 1e-3) under which two gains tie; ties go to the lowest candidate index.
        screen: tighten lazy greedy's stale bounds with a low-rank feature model of the kernel (rigorous bounds,
            same picks, much faster for smooth kernels and many candidates): ``True``, ``False`` or ``"auto"``
            (from 1000 candidates on). The features' rank and residual are in ``result.diagnostics``.
        max_rank: most features for the screening (default: what fits in 256 MiB, at least 64 and at most 1024;
            the features take ``8 N T r`` bytes for the rank r used, e.g. 0.7 GB for N = 10^5, T = 20, r = 46).
        epsilon: ``method="stochastic"`` only: the guarantee's epsilon in (0, 1), which sets the draw per pick
            (``result.diagnostics["sample_size"]``); smaller is closer to lazy greedy and slower.
        generator: ``method="stochastic"`` only: the random draws (default: a generator seeded with 0, so a design
            is reproducible).
    """

    batch_size: int = 16
    tie_tol: float = 1e-9
    screen: bool | str = "auto"
    max_rank: int | None = None
    epsilon: float = EPSILON
    generator: torch.Generator | None = None

    def __post_init__(self) -> None:
        check_positive_int(self.batch_size, "Engine.batch_size")
        tol = self.tie_tol
        if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not 0 <= tol < 1e-3:
            raise InputError(f"Engine.tie_tol: expected a number in [0, 1e-3), got {tol!r}; the default is 1e-9")
        if self.screen not in ("auto", True, False):
            raise InputError(f"Engine.screen: expected 'auto', True or False, got {self.screen!r}")
        if self.max_rank is not None:
            check_positive_int(self.max_rank, "Engine.max_rank")
        eps = check_real(self.epsilon, "Engine.epsilon", positive=True)
        if not eps < 1:
            raise InputError(f"Engine.epsilon: expected a number in (0, 1), got {self.epsilon!r}; the default is 0.01")
        if self.generator is not None and not isinstance(self.generator, torch.Generator):
            raise InputError(
                f"Engine.generator: expected a torch.Generator, got {type(self.generator).__name__}; pass "
                "torch.Generator().manual_seed(seed)"
            )

    @property
    def stochastic_only(self) -> bool:
        """Whether a stochastic-greedy option (``epsilon``, ``generator``) differs from its default."""
        return self.epsilon != EPSILON or self.generator is not None


def checked_criterion(criterion) -> tuple[str | ReadoutCriterion, DomainCriterion]:
    """The criterion as the engines take it (``"domain"`` for a :class:`DomainCriterion`) and the domain's options."""
    if isinstance(criterion, DomainCriterion):
        return "domain", criterion
    if isinstance(criterion, ReadoutCriterion) or criterion in CRITERIA:
        return criterion, DomainCriterion()
    raise InputError(
        f"criterion: expected one of {CRITERIA}, a design.DomainCriterion or a design.ReadoutCriterion, got "
        f"{criterion!r}"
    )


def checked_options(partition, proxy, engine) -> tuple[Partition | None, Proxy, Engine]:
    """The option objects, their defaults filled in; a keyword given something else is refused by name."""
    for name, value, kind in (("partition", partition, Partition), ("proxy", proxy, Proxy), ("engine", engine, Engine)):
        if value is not None and not isinstance(value, kind):
            raise InputError(
                f"{name}: expected a design.{kind.__name__} or None, got {type(value).__name__}; pass "
                f"{name}=design.{kind.__name__}(...)"
            )
    return partition, proxy or Proxy(), engine or Engine()


def check_stochastic(method: str, engine: Engine, partition, criterion) -> None:
    """Stochastic greedy's options only with it, and it only where its guarantee holds (a cardinality budget)."""
    if method != "stochastic" and engine.stochastic_only:
        raise InputError(
            f"Engine.epsilon / Engine.generator: expected method='stochastic' with them, got method={method!r}"
        )
    if method == "stochastic" and (partition is not None or criterion != "information"):
        raise InputError(
            "method='stochastic': expected a cardinality budget and criterion='information' (its guarantee "
            f"holds there), got {'a partition' if partition is not None else f'criterion={criterion!r}'}; "
            "use method='lazy'"
        )
