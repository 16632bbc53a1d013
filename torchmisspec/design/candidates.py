"""Candidate initial conditions to design among: a grid over a box, uniform draws in a box, orbits about a mass.

Every generator returns a ``(N, d)`` tensor of full initial states (float64 unless ``dtype`` says otherwise), ready
for :func:`torchmisspec.design.greedy` and the other designs.

* :func:`grid` - the tensor-product grid of ``size`` points per axis over a box (paper §5.2: 13 x 13 on [-1, 1]^2).
* :func:`uniform_box` - ``n`` points drawn uniformly in a box (random training and test sets).
* :func:`orbits` - ``n`` satellites released on circular orbits about a central point mass (paper §5.3).
"""

from __future__ import annotations

import torch

from .._errors import InputError
from .._validation import check_domain, check_positive_int, check_real
from ..metrics import box_grid
from ..systems import PAPER_GRAVITY_KNOWN_MASS

__all__ = ["grid", "uniform_box", "orbits"]


def grid(domain, size: int, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """A uniform grid of ``size`` points per axis over the box ``domain`` (both ends included).

    Args:
        domain: the box, ``(lo, hi)`` per dimension, n dimensions.
        size: points per axis, at least 2.

    Returns:
        ``(size**n, n)`` points; the last coordinate varies fastest.
    """
    size = check_positive_int(size, "size", minimum=2)
    points, _ = box_grid(check_domain(domain), size, dtype=dtype, device=device)
    return points


def uniform_box(
    n: int, domain, *, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64, device=None
) -> torch.Tensor:
    """``n`` points drawn independently and uniformly in the box ``domain``.

    Args:
        n: number of points, at least 1.
        domain: the box, ``(lo, hi)`` per dimension, d dimensions.
        generator: a :class:`torch.Generator` for reproducible draws (drawn on its device, then moved to
            ``device``).

    Returns:
        ``(n, d)`` points.
    """
    n = check_positive_int(n, "n")
    box = check_domain(domain)
    draw_device = generator.device if generator is not None else device
    u = torch.rand(n, len(box), generator=generator, dtype=dtype, device=draw_device).to(device=device)
    lo = torch.tensor([b[0] for b in box], dtype=dtype, device=u.device)
    hi = torch.tensor([b[1] for b in box], dtype=dtype, device=u.device)
    return lo + (hi - lo) * u


def orbits(
    n: int = 300,
    *,
    mass: float = PAPER_GRAVITY_KNOWN_MASS,
    generator: torch.Generator | None = None,
    half_width: float = 2.0,
    min_radius: float = 0.75,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """``n`` initial states ``(x1, x2, v1, v2)`` on circular orbits about a point mass at the origin.

    Positions are uniform in the square [-half_width, half_width]^2 outside the disc of radius ``min_radius``
    around the mass (rejection sampling); velocities are those of a circular counter-clockwise orbit about the mass,
    speed ``sqrt(mass / r)`` (gravitational constant 1). With the default mass, the known mass of
    :func:`~torchmisspec.systems.paper_gravity`, every experiment is a satellite released into the orbit the known
    model G predicts, which the unknown masses then perturb (the paper's §5.3 does not list its candidate set; this
    is the package's choice).

    Args:
        n: number of candidates, at least 1.
        mass: the central mass, > 0.
        generator: a :class:`torch.Generator` for reproducible draws.
        half_width: half the side of the square of positions.
        min_radius: no position closer than this to the mass, ``0 < min_radius < half_width``.

    Returns:
        ``(n, 4)`` states: positions ``[:, :2]``, velocities ``[:, 2:]``.
    """
    n = check_positive_int(n, "n")
    mass = check_real(mass, "mass", positive=True)
    half_width = check_real(half_width, "half_width", positive=True)
    min_radius = check_real(min_radius, "min_radius", positive=True)
    if not min_radius < half_width:
        raise InputError(f"min_radius: expected 0 < min_radius < half_width={half_width}, got {min_radius}")
    points, count = [], 0
    while count < n:  # at least 1 - pi/4 of the square lies outside the disc, so this ends quickly
        x = (torch.rand(2 * n, 2, generator=generator, dtype=dtype) * 2 - 1) * half_width
        x = x[torch.linalg.vector_norm(x, dim=-1) >= min_radius]
        points.append(x)
        count += x.shape[0]
    x = torch.cat(points)[:n]
    r = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    speed = torch.sqrt(mass / r)
    v = speed * torch.stack([-x[:, 1], x[:, 0]], -1) / r
    return torch.cat([x, v], dim=-1)
