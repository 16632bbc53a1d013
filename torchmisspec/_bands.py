"""Bands from sampled paths: which order statistics of S draws make a band that covers ``level`` of new draws.

The central ``level`` band of S draws taken at the plain quantiles ``(1 -/+ level) / 2`` is too narrow: a new draw
from the same distribution falls between the i-th and j-th smallest of S exchangeable draws with probability
``(j - i) / (S + 1)`` (whatever the distribution), so the plain 5 % and 95 % quantiles of 64 draws (ranks 4.15 and
60.85 under linear interpolation) cover a new draw with probability 0.87, not 0.9. :func:`band_quantiles` places
the ranks at ``(S + 1)(1 -/+ level) / 2`` instead, which makes the expected coverage ``level`` exactly wherever the
ranks are whole numbers (and to within the interpolation between two neighbouring draws elsewhere).
"""

from __future__ import annotations

import math

import torch

from ._errors import TorchMisspecWarning, warn


def band_quantiles(
    level: float, num_draws: int, *, dtype=torch.float64, device=None, what: str = "band"
) -> torch.Tensor:
    """``(2,)`` quantile positions (for :func:`torch.quantile`'s linear interpolation) of the central band of
    ``num_draws`` exchangeable draws that covers a new draw with probability ``level``.

    When ``level`` exceeds ``(S - 1) / (S + 1)`` no band within the draws reaches it: the band is the draws' whole
    range, and a warning says how many draws the level needs.
    """
    S = int(num_draws)
    lo_rank = (S + 1) * (1.0 - level) / 2.0  # 1-based rank of the lower end
    if lo_rank < 1.0 - 1e-9 and level > 0.0:
        need = math.ceil(2.0 / (1.0 - level) - 1.0 - 1e-9) if level < 1.0 else None
        warn(
            f"{what}: the central {level:g} band of {S} draws is wider than the draws: their range covers a new draw "
            f"with probability {(S - 1) / (S + 1):.3f} only; "
            + (f"draw at least {need} (num_samples={need})" if need else "no finite number of draws covers all")
            + " for this level",
            TorchMisspecWarning,
        )
    if S < 2:
        return torch.tensor([0.0, 1.0], dtype=dtype, device=device)
    lo = min(max((lo_rank - 1.0) / (S - 1), 0.0), 0.5)
    return torch.tensor([lo, 1.0 - lo], dtype=dtype, device=device)


def path_quantiles(samples: torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
    """Quantiles ``qs (Q,)`` over the draws ``samples (S, ...)`` -> ``(Q, ...)``, where a NaN (a path that diverged
    before that time) counts as unbounded on the side of the quantile: as -inf for q < 1/2, +inf for q > 1/2 (and the
    mean of both for the median), so a band that such paths reach is infinite, never silently narrowed."""
    if not bool(torch.isnan(samples).any()):
        return torch.quantile(samples, qs, dim=0)
    # interpolating between two infinite values gives NaN: there the quantile is that infinity
    low = torch.quantile(samples.nan_to_num(nan=-math.inf), qs, dim=0).nan_to_num(nan=-math.inf)
    high = torch.quantile(samples.nan_to_num(nan=math.inf), qs, dim=0).nan_to_num(nan=math.inf)
    side = qs.reshape(-1, *([1] * (samples.dim() - 1)))
    return torch.where(side < 0.5, low, torch.where(side > 0.5, high, 0.5 * (low + high)))
