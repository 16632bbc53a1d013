"""dy/dt estimated in the space where the measurement errors are alike, and brought back to the states' units.

Under relative (log-normal) errors a concentration of 100 is off by 10 where one of 0.5 is off by 0.05. An estimator
of dy/dt run on the states themselves takes every error as one size: the GP in time learns one noise variance and one
lengthscale for the whole curve, so the derivative of a decay's tail (0.35 ng/mL on nlme's Remifentanil) came with a
posterior standard deviation of 6.7 ng/mL/min, larger than the elimination it should reveal (0.01-0.4 there), and F's
posterior was left free at low concentrations. In the noise model's space ``z = T(y)`` (:mod:`torchmisspec.noise`:
``log y``, ``log(1 + y)``, ``2 sqrt(y + 3/8)``) the errors are alike, which is what every estimator assumes; its
``dz/dt`` and variance come back by the chain rule,

    dy/dt = (dy/dz) dz/dt,        var(dy/dt) = (dy/dz)^2 var(dz/dt),

with ``dy/dz`` the slope of the noise model's inverse (``y`` for relative errors: a derivative known to 10 % in log
space is known to 10 % of the state). The estimator's self-check (``derivative="auto"``) runs there too, on the known
model in the same space, ``dz/dt = G(y) / (dy/dz)``.

A row whose measurement the noise model cannot hold (a 0 under relative errors: the 0 a lab writes at an infusion's
start) gives no sample: the transformed trajectories leave it out, and it is marked among the samples left out. Where
that would leave an experiment too short for an estimator, the derivatives are taken on the states as measured.
"""

from __future__ import annotations

import dataclasses

import torch

from ...data import Trajectories
from ...noise import Additive, NoiseModel
from ...systems import MisspecifiedSystem

__all__ = ["transforms", "in_noise_space"]

#: fewest rows an experiment keeps in the noise model's space (a central difference of order 2)
MIN_ROWS = 3


def transforms(noise) -> bool:
    """Whether ``noise`` (a :class:`~torchmisspec.noise.NoiseModel` or ``None``) estimates derivatives in a space of
    its own (any model but :class:`~torchmisspec.noise.Additive`)."""
    return isinstance(noise, NoiseModel) and not isinstance(noise, Additive)


def slope(noise: NoiseModel, z: torch.Tensor) -> torch.Tensor:
    """``dy/dz`` elementwise: the derivative of ``noise.inverse`` at ``z`` (autograd: any elementwise model)."""
    with torch.enable_grad():
        at = z.detach().requires_grad_(True)
        (grad,) = torch.autograd.grad(noise.inverse(at).sum(), at)
    return grad


def in_noise_space(trajectories: Trajectories, system: MisspecifiedSystem, noise: NoiseModel, derive):
    """``derive(trajectories, system)``'s ``(dy/dt, variance or None, filled states, name, left out or None)`` with
    the estimator run in ``noise``'s space (the module's notes); ``derive`` is
    :func:`~torchmisspec.learning.samples.observations.correction_samples`' derivative step."""
    kept, rows = _kept_rows(trajectories, noise)
    if kept is None:  # an experiment would be too short in that space: on the states as measured
        return derive(trajectories, system)
    dz, var_z, z, used, edges = derive(kept, _system_in(system, noise))
    flat = trajectories.flat_states()
    observed = torch.isfinite(flat[rows])
    y = torch.where(observed, flat[rows], noise.inverse(z))
    jac = slope(noise, z)
    dydt = torch.zeros_like(flat)
    dydt[rows] = dz * jac
    variance = None
    if var_z is not None:
        variance = torch.ones_like(flat)  # rows left out carry a placeholder: they give no sample
        variance[rows] = var_z * jac.pow(2)
    filled = flat.clone()
    filled[rows] = y
    out = torch.ones(flat.shape[0], dtype=torch.bool, device=flat.device)
    out[rows] = False if edges is None else edges
    left_out = out if bool(out.any()) else None
    return dydt, variance, filled, f"{used} (in the {noise.name} noise's space)", left_out


def _kept_rows(trajectories: Trajectories, noise: NoiseModel):
    """``(the trajectories in noise's space without the rows it cannot hold, their rows among the flat samples)``;
    ``(None, None)`` where that leaves an experiment shorter than :data:`MIN_ROWS`."""
    flat = trajectories.flat_states()
    bad = (torch.isfinite(flat) & ~noise.holds(flat)).any(-1)
    if not bool(bad.any()):
        whole = dataclasses.replace(trajectories, states=_transformed(noise, trajectories.states), initial_states=None)
        return whole, torch.arange(flat.shape[0], device=flat.device)
    times, states, start = [], [], 0
    for t, y in trajectories.experiments():
        keep = ~bad[start : start + t.numel()]
        start += t.numel()
        if int(keep.sum()) < MIN_ROWS:
            return None, None
        times.append(t[keep])
        states.append(_transformed(noise, y[keep]))
    kept = Trajectories(times, states, controls=trajectories.controls, state_names=trajectories.state_names)
    return kept, torch.nonzero(~bad).squeeze(-1)


def _transformed(noise: NoiseModel, states):
    """``noise.transform`` of the states (a tuple of ragged experiments too), missing entries kept missing."""
    if isinstance(states, tuple):
        return tuple(_transformed(noise, s) for s in states)
    return torch.where(torch.isfinite(states), noise.transform(states), states)


def _system_in(system: MisspecifiedSystem, noise: NoiseModel) -> MisspecifiedSystem:
    """The known model in ``noise``'s space: ``dz/dt = G(y) / (dy/dz)`` at ``y = inverse(z)`` (no uncertain
    parameters: G at its current values; no correction)."""

    def rate(z, g):
        return g / slope(noise, z)

    if system.autonomous:

        def known(z):
            return rate(z, system.known_rhs(noise.inverse(z)))

    else:

        def known(t, z, u=None):
            return rate(z, system.known_rhs(noise.inverse(z), t, u))

    return MisspecifiedSystem(
        known,
        system.state_dim,
        correction_inputs=system.correction_inputs,
        correction_outputs=system.correction_outputs,
        name=f"{system.name} (in the {noise.name} noise's space)",
        state_names=system.state_names,
        num_controls=system.num_controls,
        control_names=system.control_names if system.num_controls else None,
        time_dependent=system.time_dependent,
    )
