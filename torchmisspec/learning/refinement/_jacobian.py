"""The Jacobians of the fits through the ODE (:mod:`torchmisspec.learning.refinement._trajectory_map`): the derivatives
of the scaled residuals with respect to the feature coefficients, G's uncertain parameters and the initial-state
offsets, by central differences, the perturbed models in one batched solve (single shooting), or one solve per
perturbation. A perturbation that cannot be integrated gives a column of zeros
(:func:`~torchmisspec.learning.refinement._fit_fallbacks._dropped`): a rejected direction, not the end of the fit."""

from __future__ import annotations

import math

import torch

from ..._errors import IntegrationError
from ._fit_fallbacks import _batched, _dropped

__all__ = ["_coefficient_columns", "_joint_columns"]


def _joint_columns(residuals, make_fields, beta, active, v, off, sd) -> torch.Tensor:
    """``(n e, q + k + K d)``: d (residual / s) by central differences with respect to the active coefficients
    (as :func:`_coefficient_columns`), G's parameters ``v (k,)`` where learned (``None``: k = 0) and the
    initial-state offsets (moving component j of every initial state at once gives each experiment's own column),
    all 2 (q + k + d) perturbed models in one batched solve (``make_fields(bs, vs)``, ``vs`` ``(m, k)`` one theta
    per copy, or ``None``): one solve per Jacobian (the per-step cost of a solve of a few states barely grows with
    its copies). A coefficient's or parameter's perturbation that cannot be integrated gives a column of zeros
    (dropped), an offset's zeros where its experiments' residuals are not finite."""
    typical = float(beta.abs().max()) * 1e-3
    pairs = active.nonzero(as_tuple=False).tolist()
    q, k, (K, d) = len(pairs), 0 if v is None else v.numel(), off.shape
    m = 2 * (q + k + d)
    hq = torch.tensor([_step(float(beta[i, o]), typical) for i, o in pairs], dtype=beta.dtype, device=beta.device)
    h = 1e-5  # the parameters' (in prior sds) and the offsets' (in state noise) step
    bs = beta.unsqueeze(0).repeat(m, 1, 1)
    rows = torch.arange(q, device=beta.device)
    idx_i = torch.tensor([i for i, _ in pairs], dtype=torch.long, device=beta.device)
    idx_o = torch.tensor([o for _, o in pairs], dtype=torch.long, device=beta.device)
    bs[rows, idx_i, idx_o] += hq
    bs[q + rows, idx_i, idx_o] -= hq
    vs = None if v is None else v.unsqueeze(0).repeat(m, 1)
    if k:
        j = torch.arange(k, device=v.device)
        vs[2 * q + j, j] += h
        vs[2 * q + k + j, j] -= h
    offs = off.unsqueeze(0).repeat(m, 1, 1)
    j, at = torch.arange(d, device=off.device), 2 * (q + k)
    offs[at + j, :, j] += h
    offs[at + d + j, :, j] -= h

    def run(lo, hi):
        return residuals.many(make_fields(bs[lo:hi], None if vs is None else vs[lo:hi]), hi - lo, offs[lo:hi], sd)

    res = _batched(run, m)  # (m, n, e)
    steps = torch.cat([hq, torch.full((k + d,), h, dtype=beta.dtype, device=beta.device)])
    plus = torch.cat([res[:q], res[2 * q : 2 * q + k], res[at : at + d]])
    minus = torch.cat([res[q : 2 * q], res[2 * q + k : at], res[at + d :]])
    delta = (plus - minus) / (2 * steps.reshape(-1, 1, 1)) / sd  # (q + k + d, n, e)
    zero = torch.zeros((), dtype=delta.dtype, device=delta.device)
    whole = torch.isfinite(delta[: q + k]).all(-1).all(-1)[:, None, None]  # a failed model: its column dropped
    delta = torch.cat(
        [torch.where(whole, delta[: q + k], zero), torch.where(delta[q + k :].isfinite(), delta[q + k :], zero)]
    )
    n, e = delta.shape[1], delta.shape[2]
    J_o = torch.zeros((n, e, K, d), dtype=delta.dtype, device=delta.device)
    experiment = residuals.experiment
    for jj in range(d):  # moving component jj of every initial state at once: each experiment's own column
        J_o[torch.arange(n, device=off.device), :, experiment, jj] = delta[q + k + jj]
    return torch.cat([delta[: q + k].reshape(q + k, -1).T, J_o.reshape(n * e, K * d)], dim=1)


def _step(value: float, typical: float) -> float:
    """A central-difference step for a parameter of size ``value`` among parameters of size ``typical``."""
    return 1e-5 * max(abs(value), typical, 1e-12)


def _coefficient_columns(residuals, make_field, beta, active, off, sd, make_fields=None) -> torch.Tensor:
    """``(n d, q)``: d (residual / s) / d beta over the active coefficients, by central differences; with
    ``make_fields`` (a field for a stack of coefficient sets) and single shooting, every perturbed model in one
    batched solve."""
    typical = float(beta.abs().max()) * 1e-3
    pairs = active.nonzero(as_tuple=False).tolist()
    if make_fields is not None and hasattr(residuals, "many"):
        h = torch.tensor([_step(float(beta[i, o]), typical) for i, o in pairs], dtype=beta.dtype, device=beta.device)
        q = len(pairs)
        stack = beta.unsqueeze(0).repeat(2 * q, 1, 1)
        rows = torch.arange(q, device=beta.device)
        idx_i = torch.tensor([i for i, _ in pairs], device=beta.device)
        idx_o = torch.tensor([o for _, o in pairs], device=beta.device)
        stack[rows, idx_i, idx_o] += h
        stack[q + rows, idx_i, idx_o] -= h
        res = _batched(lambda lo, hi: residuals.many(make_fields(stack[lo:hi]), hi - lo, off, sd), 2 * q)
        diff = (res[:q] - res[q:]) / (2 * h.reshape(-1, 1, 1)) / sd  # (q, n, d)
        return _dropped(diff.reshape(q, -1).T)
    cols = []
    for i, o in pairs:
        h = _step(float(beta[i, o]), typical)
        plus, minus = beta.clone(), beta.clone()
        plus[i, o] += h
        minus[i, o] -= h
        try:
            diff = residuals(make_field(plus), off, sd) - residuals(make_field(minus), off, sd)
        except IntegrationError:  # a perturbation that cannot be integrated: its column is dropped
            diff = torch.full_like(residuals(make_field(beta), off, sd), math.nan)
        cols.append((diff / (2 * h) / sd).reshape(-1))
    return _dropped(torch.stack(cols, dim=-1))
