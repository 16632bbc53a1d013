"""The population fit's residual scale over time: what a measurement at a time is worth.

A model that misses a term misses it most at some times (a drug's late, low concentrations under a missing saturable
elimination): the population's residuals there are the measurement noise and the model's own misfit. The design of a
new subject (:mod:`~torchmisspec.population.design`) and the fit of its parameters to its first measurements
(:func:`~torchmisspec.population.predict.subject_parameters`) weight a sample at time t by the inverse square of this
scale near t, so that the design's information is the information the subject's fit draws, and neither trusts the
times where the population's model is known to be off.
"""

from __future__ import annotations

import math

import torch

from ._modes import _paths

__all__ = ["misfit_scale", "residuals_by_time"]


def residuals_by_time(fit) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(times (N,), squares (N, o), seen (N, o))``: every measurement's time, its squared residual under the
    population ``fit`` (the noise model's space; 0 where not seen; each component's raised by the freedom the
    fitted parameters took, as the fit's scale is) and whether it was seen, over all experiments. A
    first row given as the initial state is not seen (its residual is 0 by construction, not a sample's worth).
    One solve of every experiment; :class:`~torchmisspec.population.fit.PopulationFit` keeps it
    (``fit.residuals_by_time``)."""
    data, nlme = fit.data, fit.nlme
    floor = fit.noise.resolution(data)
    pred = _paths(nlme.layout, fit.mean_correction, data, floor)(nlme.thetas[None], nlme.modes.initial_states[None])[0]
    values, mask = data.observed_values()
    seen = torch.isfinite(values) & mask.unsqueeze(-1)
    d = nlme.free.shape[-1]
    seen[:, 0, :d] &= nlme.free.to(seen.device)
    r2 = torch.where(seen, fit.noise.transform(pred) - fit.noise.transform(values), 0.0).pow(2)
    times = data.padded()[0].expand(values.shape[:2])
    o = values.shape[-1]
    # the squares at the modes are too small by the freedom the fitted parameters took (the fit's scale counts it:
    # :mod:`~torchmisspec.population._modes`): each component's squares are raised to the fit's scale on average
    mean_square = r2.sum((0, 1)) / seen.sum((0, 1)).clamp_min(1)
    raise_by = (nlme.modes.scale.to(r2).pow(2) / mean_square).nan_to_num(nan=1.0, posinf=1.0).clamp_min(1.0)
    r2 = r2 * raise_by
    return times.reshape(-1), r2.reshape(-1, o), seen.reshape(-1, o)


def misfit_scale(fit, grid: torch.Tensor) -> torch.Tensor:
    """``(T, o)`` the population fit's residual root mean square at each candidate time (the noise model's space):
    the residuals of every experiment at its data times (:func:`residuals_by_time`), pooled at the nearest candidate
    time; a candidate time without data takes the nearest one's. What a sample there is worth is its measurement
    noise and the model's own misfit there: a model that misses a term misses it most at some times (a drug's late,
    low concentrations under a missing saturable elimination), and the design should not trust those most. Without
    the data (``fit.data`` ``None``), the fit's one scale per component at every time."""
    scale = fit.nlme.modes.scale
    if fit.data is None:
        return scale.expand(grid.numel(), -1)
    times, r2, seen = fit.residuals_by_time
    nearest = (times.unsqueeze(-1) - grid).abs().argmin(-1)  # (N,)
    o = r2.shape[-1]
    total = torch.zeros(grid.numel(), o, dtype=r2.dtype).index_add_(0, nearest, r2)
    count = torch.zeros(grid.numel(), o, dtype=r2.dtype).index_add_(0, nearest, seen.to(r2))
    out = torch.full_like(total, math.nan)
    for j in range(o):
        have = (count[:, j] > 0).nonzero().flatten()
        if have.numel():
            near = have[(grid[:, None] - grid[have]).abs().argmin(-1)]
            out[:, j] = (total[near, j] / count[near, j]).sqrt()
    return torch.where(torch.isfinite(scale).expand_as(out), out.clamp_min(1e-12), math.nan)
