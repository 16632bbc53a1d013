"""Hyperparameters before any data (``CorrectionGP.prior``): from the known model G and the domain of interest D.

The rule, documented so that a design can start from it: the correction is expected to be a fraction of what G
already explains and to vary on the scale of D (see :meth:`~torchmisspec.gp.CorrectionGP.prior`).
"""

from __future__ import annotations

import math

import torch

from .._errors import InputError, ShapeError
from .._validation import as_tensor, check_real
from ._kernels import as_kernel

__all__ = ["prior_hyperparameters"]


def prior_hyperparameters(
    system, *, noise_variance, relative_size, lengthscale_fraction, kernel, states, grid_size, dtype, device
) -> dict:
    """The constructor arguments of :meth:`CorrectionGP.prior <torchmisspec.gp.CorrectionGP.prior>` (see there):
    ``kernel``, ``lengthscale``, ``outputscale`` and ``noise_variance``."""
    from ..systems import MisspecifiedSystem

    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
    spec = as_kernel(kernel)
    if not (spec.stationary and spec.has_lengthscale):
        raise InputError(
            f"kernel: expected a stationary kernel with a lengthscale such as 'rbf' or 'matern52', got {spec.name!r}"
        )
    if system.domain is None:
        raise InputError(
            f"system: '{system.name}' has no domain D; build it with MisspecifiedSystem(..., domain=((lo, hi), "
            "...)) (one box side per correction input)"
        )
    relative_size = check_real(relative_size, "relative_size", positive=True)
    fraction = check_real(lengthscale_fraction, "lengthscale_fraction", positive=True)
    noise_variance = check_real(noise_variance, "noise_variance", positive=True)
    kd = dict(dtype=dtype, device=device)
    box = torch.as_tensor(system.domain, **kd)  # (d_in, 2)
    states, controls = _evaluation_points(system, states, grid_size, kd)
    with torch.no_grad():
        t = None if system.autonomous else torch.zeros(states.shape[0], **kd)
        g = system.select_outputs(system.known_rhs(states, t, controls))
    size = g.norm(dim=-1) / math.sqrt(g.shape[-1])
    size = size[torch.isfinite(size)]
    if size.numel() == 0 or not float(size.median()) > 0:
        raise InputError(
            "system: the known model G is zero or not finite on D's correction outputs, so it gives no scale "
            "for F; pass CorrectionGP(outputscale=...) yourself"
        )
    outputscale = (relative_size * float(size.median())) ** 2
    widths = box[:, 1] - box[:, 0]
    lengthscale = fraction * float(widths.mean())
    if spec.input_scale is None and bool((widths != widths[0]).any()):  # D's sides differ: a lengthscale per input
        spec = type(spec)(**{**spec.config(), "input_scale": tuple((widths / widths.mean()).tolist())})
    return {"kernel": spec, "lengthscale": lengthscale, "outputscale": outputscale, "noise_variance": noise_variance}


def _evaluation_points(system, states, grid_size: int, kd: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(states (M, d), controls (M, m) or None)`` at which G's size is taken: by default a ``grid_size`` per axis
    grid over D in the correction inputs (states, then controls), every other component at 0; or the user's
    ``states`` (a system with controls takes the default grid only: D gives the controls' values)."""
    m = system.num_controls
    if states is None:
        from ..design.candidates import grid  # the package's one grid over a box (checks grid_size >= 2)

        inputs = grid(system.domain, grid_size, **kd)
        full = torch.zeros((inputs.shape[0], system.state_dim + m), **kd)
        full[:, list(system.correction_inputs)] = inputs
        return full[:, : system.state_dim], (full[:, system.state_dim :] if m else None)
    if m:
        raise InputError(
            f"states: expected None for system '{system.name}' with {m} control(s) (G is evaluated on a grid over D, "
            "whose sides give the controls' values), got states; leave states out"
        )
    states = as_tensor(states, "states", **kd)
    if states.dim() != 2 or states.shape[1] != system.state_dim:
        raise ShapeError(f"states: expected (M, {system.state_dim}) full states, got {tuple(states.shape)}")
    return states, None
