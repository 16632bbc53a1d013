"""Checking what a :class:`~torchmisspec.gp.CorrectionGP` is given: inputs, samples of F and their known noise.

Every entry point (``fit``, ``condition``, the posterior's ``mean``, ``predict`` and ``covariance``) converts and
checks through these, so that each refuses bad data with the same message naming what was expected and received.
"""

from __future__ import annotations

import torch

from .._errors import FittingError, InputError, ShapeError
from .._validation import as_tensor, check_finite, check_ndim

__all__ = ["check_inputs", "check_samples", "check_noise", "unpack"]


def check_inputs(gp, x, name: str) -> torch.Tensor:
    x = as_tensor(x, name, dtype=gp.dtype, device=gp.device)
    d_in = gp.input_dim
    if x.dim() == 1 and d_in == 1:
        x = x.unsqueeze(-1)
    check_ndim(x, 2, name, "(M, d_in)")
    check_finite(x, name)
    if d_in is not None and x.shape[1] != d_in:
        raise ShapeError(f"{name}: expected {d_in} input columns (as in training), got shape {tuple(x.shape)}")
    return x


def unpack(inputs, targets, noise):
    """``fit(samples)`` or ``fit(inputs, targets, noise=...)``: the three arrays."""
    from ..learning.samples.observations import CorrectionSamples

    if isinstance(inputs, CorrectionSamples):
        if targets is not None or noise is not None:
            given = [name for name, v in (("targets", targets), ("noise", noise)) if v is not None]
            raise InputError(
                f"fit: expected either a CorrectionSamples object alone or inputs and targets (and noise), got a "
                f"CorrectionSamples object and {' and '.join(given)} (the samples already carry their targets "
                "and noise)"
            )
        return inputs.inputs, inputs.targets, inputs.noise
    if targets is None:
        raise InputError(
            f"targets: expected (N, d_out) samples of F (or a CorrectionSamples object as the only argument), "
            f"got None with inputs of type {type(inputs).__name__}"
        )
    return inputs, targets, noise


def check_noise(gp, noise, N: int, d_out: int) -> torch.Tensor | None:
    """Known noise variances ``(N,)`` or ``(N, d_out)`` -> ``(N, d_out)`` (finite, >= 0), or ``None``."""
    if noise is None:
        return None
    noise = as_tensor(noise, "noise", dtype=gp.dtype, device=gp.device)
    if noise.dim() == 1 and noise.shape[0] == N:
        noise = noise.unsqueeze(-1).expand(N, d_out)
    if noise.shape != (N, d_out):
        raise ShapeError(
            f"noise: expected known noise variances ({N},) (the same for every output) or ({N}, {d_out}) (per "
            f"sample and output), got shape {tuple(noise.shape)}"
        )
    check_finite(noise, "noise")
    if bool((noise < 0).any()):
        raise InputError(
            f"noise: expected non-negative variances, got {int((noise < 0).sum())} negative values (smallest "
            f"{float(noise.min()):.3g})"
        )
    return noise.contiguous()


def check_samples(gp, inputs, targets, noise) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``fit``'s data: ``(X (N, d_in), Y (N, d_out), noise (N, d_out) or None)`` in the model's dtype and device,
    finite, with matching rows (``fit(samples)`` or ``fit(inputs, targets, noise=...)``)."""
    inputs, targets, noise = unpack(inputs, targets, noise)
    X = as_tensor(inputs, "inputs", dtype=gp.dtype, device=gp.device)
    Y = as_tensor(targets, "targets", dtype=gp.dtype, device=gp.device)
    if Y.dim() == 1:
        Y = Y.unsqueeze(-1)
    check_ndim(X, 2, "inputs", "(N, d_in)")
    check_ndim(Y, 2, "targets", "(N, d_out)")
    if X.shape[0] != Y.shape[0]:
        raise ShapeError(f"targets: expected {X.shape[0]} rows to match inputs {tuple(X.shape)}, got {tuple(Y.shape)}")
    if X.shape[0] < 1:
        raise FittingError("inputs: expected at least one sample, got 0")
    check_finite(X, "inputs")
    check_finite(Y, "targets")
    return X, Y, check_noise(gp, noise, Y.shape[0], Y.shape[1])
