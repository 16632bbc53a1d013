"""Paired comparisons of two methods' errors over realizations: how much worse (or better) one is than the other.

A study runs both methods on the same realizations, so each gives a ratio r_i = a_i / b_i. Which summary says "a is
no worse than b"?

* the **geometric mean** exp(mean log r_i), with its standard error as a factor exp(se of log r_i): symmetric (the
  comparison of b with a gives exactly its reciprocal) and not pulled by one realization where b was lucky. The
  studies' goals on ratios are judged on it;
* the **arithmetic mean** of the ratios: dominated by the realizations where b's error is small, and biased above 1
  for any two methods whose errors vary (Jensen's inequality: for two methods of equal skill, the mean of a / b and
  the mean of b / a both exceed 1). Reported, with the mean of the reciprocals that shows the bias;
* the **ratio of the mean errors** (its standard error by the delta method, the errors paired): the comparison of
  expected errors, dominated by the realizations where both errors are large.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .._errors import InputError
from ..metrics import mean_and_standard_error

__all__ = ["describe", "paired_ratio"]


def paired_ratio(a: Sequence[float], b: Sequence[float]) -> dict:
    """Summaries of the per-realization ratios ``a_i / b_i`` of positive errors (see the module docstring)."""
    x = torch.tensor(list(a), dtype=torch.float64)
    y = torch.tensor(list(b), dtype=torch.float64)
    if x.shape != y.shape or x.numel() == 0 or not bool((x > 0).all() and (y > 0).all()):
        raise InputError(f"expected two equal-length sequences of positive errors, got {x.tolist()} and {y.tolist()}")
    ratios = x / y
    n = ratios.numel()
    log_mean, log_se = mean_and_standard_error(ratios.log())
    mean, se = mean_and_standard_error(ratios)
    inverse, inverse_se = mean_and_standard_error(1.0 / ratios)
    ma, mb = float(x.mean()), float(y.mean())
    of_means = ma / mb
    of_means_se = math.nan
    if n > 1:
        va, vb = float(x.var()) / n, float(y.var()) / n
        cov = float(((x - ma) * (y - mb)).sum()) / (n - 1) / n
        of_means_se = of_means * math.sqrt(max(va / ma**2 + vb / mb**2 - 2 * cov / (ma * mb), 0.0))
    return {
        "n": n,
        "geometric": math.exp(float(log_mean)),
        "geometric_factor": math.exp(float(log_se)),
        "mean": float(mean),
        "mean_se": float(se),
        "mean_of_reciprocals": float(inverse),
        "mean_of_reciprocals_se": float(inverse_se),
        "of_means": of_means,
        "of_means_se": of_means_se,
        "median": float(ratios.median()),
        "min": float(ratios.min()),
        "max": float(ratios.max()),
        "better": int((ratios < 1).sum()),
    }


def describe(stats: dict, digits: int = 3) -> str:
    """One table cell: ``geometric ×/÷ factor; mean ± se (of b / a: ...); of means ...; min-max``."""
    f = f".{digits}f"
    return (
        f"{stats['geometric']:{f}} ×/÷ {stats['geometric_factor']:{f}} (geometric mean); arithmetic "
        f"{stats['mean']:{f}} ± {stats['mean_se']:{f}} (reciprocals {stats['mean_of_reciprocals']:{f}} ± "
        f"{stats['mean_of_reciprocals_se']:{f}}); of means {stats['of_means']:{f}} ± {stats['of_means_se']:{f}}; "
        f"{stats['min']:{f}}-{stats['max']:{f}}, below 1 in {stats['better']} of {stats['n']}"
    )
