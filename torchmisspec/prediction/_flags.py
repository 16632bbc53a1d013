"""Where a band says something a reader must be told: each flagged state and the first time it is flagged."""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["first_flagged"]


def first_flagged(names: Sequence[str] | None, times: torch.Tensor, flags: torch.Tensor) -> list[tuple[int, str, str]]:
    """``[(j, state name, "from t = ...")]`` for each state ``j`` that ``flags (T, d)`` marks at some time, with the
    first such time (``names`` ``None``: ``y0, y1, ...``). What the population's band warnings and ``torchmisspec
    predict``'s below-zero note name."""
    names = list(names) if names else [f"y{j}" for j in range(flags.shape[-1])]
    return [
        (j, names[j], f"from t = {float(times[flags[:, j].nonzero()[0, 0]]):.4g}")
        for j in range(flags.shape[-1])
        if bool(flags[:, j].any())
    ]
