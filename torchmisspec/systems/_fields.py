"""Vector fields of the built-in systems (re-exported by :mod:`torchmisspec.systems`): ``nn.Module`` s, so they
follow the states' dtype and device. Their arguments are checked where they are built, and the states where they are
called (a field called on states of the wrong width names the width it expects, not torch's matrix sizes)."""

from __future__ import annotations

import torch
from torch import nn

from .._errors import InputError, ShapeError
from .._validation import as_tensor, check_finite, check_last_dim, check_real


class LinearField(nn.Module):
    """y -> A y for states ``(..., d)``; ``matrix`` A is a finite ``(d, d)`` array."""

    def __init__(self, matrix) -> None:
        super().__init__()
        A = check_finite(as_tensor(matrix, "matrix", dtype=torch.float64), "matrix")
        if A.dim() != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
            raise ShapeError(f"matrix: expected a square (d, d) matrix A of y -> A y, got shape {tuple(A.shape)}")
        self.register_buffer("matrix", A)

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        y = check_last_dim(
            y, self.matrix.shape[1], "y", f"the states of a LinearField of {self.matrix.shape[1]} states"
        )
        return y @ self.matrix.to(dtype=y.dtype, device=y.device).T


class QuadraticField(nn.Module):
    """y -> coef * y**2 componentwise (paper §5.1: F(y) = 0.01 [y1^2, y2^2]); ``coef`` a finite number."""

    def __init__(self, coef: float) -> None:
        super().__init__()
        self.coef = check_real(coef, "coef")

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        return self.coef * as_tensor(y, "y") ** 2


class PointMassGravity(nn.Module):
    """Acceleration -sum_i m_i (x - x_i) / ||x - x_i||^3 at positions ``x (..., 2)``.

    ``masses`` ``(n,)`` and ``positions`` ``(n, 2)``, finite. With ``first_order=True`` it is the first-order field of
    the state (x1, x2, v1, v2): (v1, v2, a1(x), a2(x)).
    """

    def __init__(self, masses, positions, *, first_order: bool = False) -> None:
        super().__init__()
        m = check_finite(as_tensor(masses, "masses", dtype=torch.float64), "masses").reshape(-1)
        p = check_finite(as_tensor(positions, "positions", dtype=torch.float64), "positions")
        if p.dim() != 2 or p.shape != (m.numel(), 2) or m.numel() == 0:
            raise ShapeError(
                f"positions: expected ({m.numel()}, 2) positions, one (x1, x2) per mass, got shape {tuple(p.shape)}"
            )
        if not isinstance(first_order, bool):
            raise InputError(f"first_order: expected True or False, got {first_order!r:.40}")
        self.register_buffer("masses", m)
        self.register_buffer("positions", p)
        self.first_order = first_order

    def acceleration(self, x: torch.Tensor) -> torch.Tensor:
        x = check_last_dim(x, 2, "x", "positions (x1, x2)")
        m = self.masses.to(dtype=x.dtype, device=x.device)
        p = self.positions.to(dtype=x.dtype, device=x.device)
        diff = x.unsqueeze(-2) - p  # (..., n_masses, 2)
        r3 = diff.pow(2).sum(-1).pow(1.5)  # (..., n_masses)
        return -(m.unsqueeze(-1) * diff / r3.unsqueeze(-1)).sum(-2)

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        if not self.first_order:
            return self.acceleration(y)
        y = check_last_dim(y, 4, "y", "states (x1, x2, v1, v2) of the first-order field")
        return torch.cat([y[..., 2:4], self.acceleration(y[..., 0:2])], dim=-1)


class ZeroField(nn.Module):
    """y -> 0 (the known model of a fully data-driven estimator)."""

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(as_tensor(y, "y"))
