"""Error measures: the integrated error of a correction over a box domain, and trajectory errors.

The paper scores an estimate F_hat by the integral over D of ||F_hat(y) - F(y)||_2 (§5.2), computed here by
tensor-product trapezoidal quadrature on a grid. The "energy" of a field is the same integral of its norm, i.e.
the error of the zero estimate: the energy of F is the error of the misspecified model, the energy of G + F the
error of knowing nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from ._errors import InputError, ShapeError
from ._validation import (
    DEFAULT_DTYPE,
    as_tensor,
    check_callable,
    check_device,
    check_domain,
    check_finite,
    check_input_names,
    check_positive_int,
)

__all__ = [
    "box_grid",
    "integrate_over_box",
    "integrated_error",
    "integrated_norm",
    "mean_squared_error",
    "correction_error",
    "trajectory_rmse",
    "mean_and_standard_error",
]

#: most points of a quadrature grid (memory: 8 bytes x dimension each)
MAX_GRID_POINTS = 10**8

Field = Callable[[torch.Tensor], torch.Tensor]


def box_grid(domain, resolution: int = 101, *, dtype=DEFAULT_DTYPE, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Grid points ``(resolution**n, n)`` over the box and their trapezoidal weights ``(resolution**n,)``."""
    box = check_domain(domain)
    resolution = check_positive_int(resolution, "resolution", minimum=2)
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype: expected torch.float64 or torch.float32, got {dtype!r}")
    device = check_device(device)
    if resolution ** len(box) > MAX_GRID_POINTS:
        raise InputError(
            f"resolution: a grid of {resolution} points per axis over {len(box)} dimensions has more than "
            f"{MAX_GRID_POINTS:.0e} points; lower the resolution"
        )
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
    check_callable(fn, "fn", "fn(points) mapping points (M, n) to values (M,)")
    chunk = check_positive_int(chunk, "chunk")
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
    _check_fields(estimate=estimate, truth=truth)
    return integrate_over_box(
        lambda x: torch.linalg.vector_norm(_difference(estimate, truth, x), dim=-1), domain, resolution=resolution
    )


def _check_fields(**fields) -> None:
    for name, field in fields.items():
        check_callable(field, name, "field mapping points (M, n) to (M, m), e.g. gp.predict_mean or system.correction")


def _difference(estimate: Field, truth: Field, x: torch.Tensor) -> torch.Tensor:
    """estimate(x) - truth(x), refusing outputs of different shapes (broadcasting would hide a wrong field)."""
    a, b = estimate(x), truth(x)
    if not (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)) or a.shape != b.shape or a.dim() != 2:
        sa = tuple(a.shape) if isinstance(a, torch.Tensor) else type(a).__name__
        sb = tuple(b.shape) if isinstance(b, torch.Tensor) else type(b).__name__
        raise ShapeError(
            f"estimate: expected the estimate and the truth to return the same shape (M, m) at {x.shape[0]} points, "
            f"got {sa} and {sb}"
        )
    return a - b


def integrated_norm(field: Field, domain, *, resolution: int = 101) -> float:
    """Integral over D of ||field(y)||_2: the "energy" reference lines of paper Fig 5."""
    _check_fields(field=field)

    def norm(x: torch.Tensor) -> torch.Tensor:
        value = field(x)
        if not isinstance(value, torch.Tensor) or value.dim() != 2 or value.shape[0] != x.shape[0]:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ShapeError(f"field: expected values (M, m) at M = {x.shape[0]} points, got {got}")
        return torch.linalg.vector_norm(value, dim=-1)

    return integrate_over_box(norm, domain, resolution=resolution)


def mean_squared_error(estimate: Field, truth: Field, domain, *, resolution: int = 101) -> float:
    """(1 / |D|) times the integral over D of ||estimate - truth||_2^2 (paper Fig 8's mean squared error)."""
    _check_fields(estimate=estimate, truth=truth)
    box = check_domain(domain)
    volume = 1.0
    for lo, hi in box:
        volume *= hi - lo
    return (
        integrate_over_box(lambda x: _difference(estimate, truth, x).pow(2).sum(-1), box, resolution=resolution)
        / volume
    )


CORRECTION_METRICS = ("integrated", "mean_squared")


def correction_error(gp, system, *, domain=None, resolution: int = 101, metric: str = "integrated") -> float:
    """Error of a fitted correction GP's posterior mean against the system's true F over ``domain``.

    Args:
        gp: a fitted :class:`~torchmisspec.CorrectionGP`.
        system: a system with a true correction F.
        domain: the box D (default ``system.domain``).
        resolution: quadrature points per axis.
        metric: ``"integrated"``, the paper's integral over D of ``||F_hat - F||_2`` (§5.2), or
            ``"mean_squared"``, ``(1 / |D|)`` times the integral of ``||F_hat - F||_2^2`` (paper Fig 8).
    """
    if metric not in CORRECTION_METRICS:
        raise InputError(f"metric: expected one of {CORRECTION_METRICS}, got {metric!r}")
    if not callable(getattr(gp, "predict_mean", None)):
        raise InputError(
            f"gp: expected a fitted torchmisspec.CorrectionGP (its posterior mean is compared with the true F), got "
            f"{gp!r:.60} ({type(gp).__name__})"
        )
    if not hasattr(system, "true_correction") or not hasattr(system, "domain"):
        raise InputError(
            f"system: expected a torchmisspec.MisspecifiedSystem with its true correction F, got "
            f"{type(system).__name__}"
        )
    check_input_names(gp, system.input_names(), f"system '{system.name}'")
    domain = system.domain if domain is None else domain
    if domain is None:
        raise InputError(
            f"domain: expected a box to integrate over, got none (system '{system.name}' has no domain); pass "
            "domain=((lo, hi), ...)"
        )

    def estimate(x):  # x on the CPU (the quadrature grid), F_hat on the GP's device
        with torch.no_grad():
            return gp.predict_mean(x).to(x.device)

    fn = mean_squared_error if metric == "mean_squared" else integrated_error
    return fn(estimate, system.true_correction, domain, resolution=resolution)


def mean_and_standard_error(values, dim: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over ``dim`` and the standard error of that mean, ``std(unbiased) / sqrt(n)`` (0 when n = 1).

    ``values`` is a tensor or a sequence of numbers (float64); NaN entries are refused.
    """
    v = as_tensor(values, "values")
    dim = check_positive_int(dim, "dim", minimum=-max(v.dim(), 1), maximum=max(v.dim(), 1) - 1)
    if v.dim() == 0 or v.shape[dim] == 0:
        raise ShapeError(f"values: expected at least one value along dim {dim}, got shape {tuple(v.shape)}")
    check_finite(v, "values")
    n = v.shape[dim]
    # scaled by the largest magnitude, so that finite values whose squares (or sums) would overflow stay finite
    scale = v.abs().amax(dim, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)
    mean = (v / scale).mean(dim) * scale.squeeze(dim)
    if n == 1:
        return mean, torch.zeros_like(mean)
    return mean, (v / scale).std(dim, unbiased=True) * scale.squeeze(dim) / math.sqrt(n)


def trajectory_rmse(predicted, true, *, per_trajectory: bool = False) -> torch.Tensor:
    """Root mean squared error between state trajectories ``(B, T, d)``; ``(B,)`` with ``per_trajectory``."""
    predicted = as_tensor(predicted, "predicted")
    true = as_tensor(true, "true", dtype=predicted.dtype, device=predicted.device)
    if predicted.shape != true.shape:
        raise ShapeError(f"predicted: expected the shape of true {tuple(true.shape)}, got {tuple(predicted.shape)}")
    if predicted.dim() != 3 or predicted.numel() == 0:
        raise ShapeError(f"predicted: expected non-empty trajectories (B, T, d), got shape {tuple(predicted.shape)}")
    check_finite(predicted, "predicted")
    check_finite(true, "true")
    diff = (predicted - true).flatten(1) if per_trajectory else (predicted - true).reshape(1, -1)
    if not bool(torch.isfinite(diff).all()):
        raise InputError(
            f"predicted: the differences from true overflow {str(diff.dtype).removeprefix('torch.')} (values near "
            f"{float(predicted.abs().max()):.3g}); compare in float64 (.double())"
        )
    # scaled by the largest difference, so finite errors whose squares would overflow stay finite
    scale = diff.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(diff.dtype).tiny)
    rms = scale.squeeze(-1) * (diff / scale).pow(2).mean(-1).sqrt()
    return rms if per_trajectory else rms[0]
