"""Error measures: the integrated error of a correction over a box domain, and trajectory errors.

The paper scores an estimate F_hat by the integral over D of ||F_hat(y) - F(y)||_2 (§5.2), computed here by
tensor-product trapezoidal quadrature on a grid. The "energy" of a field is the same integral of its norm, i.e.
the error of the zero estimate: the energy of F is the error of the misspecified model, the energy of G + F the
error of knowing nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from ._errors import InputError, ShapeError
from ._validation import DEFAULT_DTYPE, as_tensor, check_finite

__all__ = [
    "box_grid",
    "integrate_over_box",
    "integrated_error",
    "integrated_norm",
    "mean_squared_error",
    "correction_error",
    "trajectory_rmse",
]

Field = Callable[[torch.Tensor], torch.Tensor]


def _check_domain(domain: Sequence[Sequence[float]]) -> tuple[tuple[float, float], ...]:
    try:
        box = tuple((float(lo), float(hi)) for lo, hi in domain)
    except (TypeError, ValueError) as exc:
        raise InputError(f"domain: expected a sequence of (lo, hi) pairs, got {domain!r}") from exc
    if not box or any(not lo < hi for lo, hi in box):
        raise InputError(f"domain: expected at least one interval with lo < hi, got {box}")
    return box


def box_grid(domain, resolution: int = 101, *, dtype=DEFAULT_DTYPE, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Grid points ``(resolution**n, n)`` over the box and their trapezoidal weights ``(resolution**n,)``."""
    box = _check_domain(domain)
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 2:
        raise InputError(f"resolution: expected an integer >= 2, got {resolution!r}")
    axes, weights = [], []
    for lo, hi in box:
        axes.append(torch.linspace(lo, hi, resolution, dtype=dtype, device=device))
        w = torch.full((resolution,), (hi - lo) / (resolution - 1), dtype=dtype, device=device)
        w[0] = w[-1] = w[0] / 2
        weights.append(w)
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, len(box))
    weight = weights[0]
    for w in weights[1:]:
        weight = (weight.unsqueeze(-1) * w).reshape(-1)
    return points, weight


def integrate_over_box(
    fn: Callable[[torch.Tensor], torch.Tensor], domain, *, resolution: int = 101, chunk: int = 65536
) -> float:
    """Trapezoidal integral over the box of a scalar function ``fn: (M, n) -> (M,)``."""
    points, weight = box_grid(domain, resolution)
    total = 0.0
    for start in range(0, points.shape[0], chunk):
        vals = as_tensor(fn(points[start : start + chunk]), "fn(points)", dtype=points.dtype)
        if vals.shape != (min(chunk, points.shape[0] - start),):
            raise ShapeError(f"fn(points): expected shape (M,) for M points, got {tuple(vals.shape)}")
        check_finite(vals, "fn(points)")
        total += float((vals * weight[start : start + chunk]).sum())
    return total


def integrated_error(estimate: Field, truth: Field, domain, *, resolution: int = 101) -> float:
    """Integral over the box D of ||estimate(y) - truth(y)||_2 (paper §5.2); fields map ``(M, n) -> (M, m)``."""
    return integrate_over_box(
        lambda x: torch.linalg.vector_norm(estimate(x) - truth(x), dim=-1), domain, resolution=resolution
    )


def integrated_norm(field: Field, domain, *, resolution: int = 101) -> float:
    """Integral over D of ||field(y)||_2: the "energy" reference lines of paper Fig 5."""
    return integrate_over_box(lambda x: torch.linalg.vector_norm(field(x), dim=-1), domain, resolution=resolution)


def mean_squared_error(estimate: Field, truth: Field, domain, *, resolution: int = 101) -> float:
    """(1 / |D|) times the integral over D of ||estimate - truth||_2^2 (paper Fig 8's mean squared error)."""
    box = _check_domain(domain)
    volume = 1.0
    for lo, hi in box:
        volume *= hi - lo
    return integrate_over_box(lambda x: (estimate(x) - truth(x)).pow(2).sum(-1), box, resolution=resolution) / volume


def correction_error(gp, system, *, domain=None, resolution: int = 101, squared: bool = False) -> float:
    """Error of a fitted correction GP against the system's true F over ``domain`` (default ``system.domain``).

    ``squared=False``: the paper's integrated error; ``squared=True``: the mean squared error over D.
    """
    domain = system.domain if domain is None else domain
    if domain is None:
        raise InputError(f"domain: system '{system.name}' has no domain; pass domain=((lo, hi), ...)")

    def estimate(x):
        with torch.no_grad():
            return gp.predict_mean(x)

    metric = mean_squared_error if squared else integrated_error
    return metric(estimate, system.true_correction, domain, resolution=resolution)


def trajectory_rmse(predicted, true, *, per_trajectory: bool = False) -> torch.Tensor:
    """Root mean squared error between state trajectories ``(B, T, d)``; ``(B,)`` with ``per_trajectory``."""
    predicted = as_tensor(predicted, "predicted")
    true = as_tensor(true, "true", dtype=predicted.dtype, device=predicted.device)
    if predicted.shape != true.shape:
        raise ShapeError(f"predicted: expected the shape of true {tuple(true.shape)}, got {tuple(predicted.shape)}")
    sq = (predicted - true).pow(2)
    return sq.flatten(1).mean(-1).sqrt() if per_trajectory else sq.mean().sqrt()
