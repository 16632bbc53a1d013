"""The Levenberg-Marquardt steps of the feature kernel's fit through the ODE
(:func:`~torchmisspec.learning.refinement._trajectory_map._fit_relevance`, single shooting): the MAP of the term
coefficients and initial-state offsets (and G's uncertain parameters), the Jacobian by central differences, every
perturbed model in one batched solve (:mod:`._jacobian`)."""

from __future__ import annotations

import math

import torch

from ..._errors import IntegrationError
from ..._ode import EVALS_PER_STEP, trial_budget
from ._fit_fallbacks import _shrink_until_integrable
from ._jacobian import _joint_columns


def _levenberg_marquardt(
    u, offsets, active, root, beta, make_field, make_fields, residuals, sd, *, max_iter: int, theta=None
):
    """Minimise ``1/2 ||r(u, o) / s||^2 + 1/2 ||u||^2`` (the MAP of the coefficients ``u``, in units of their prior
    standard deviations, and the initial-state offsets ``o``, in units of the state noise) by Levenberg-Marquardt
    steps: the Jacobian by central differences, every perturbed model in one batched solve. The problem has a few
    dozen parameters and is nearly linear in them, so a handful of steps replaces L-BFGS's dozens of evaluations,
    each of which differentiated through the solver. ``theta``: ``(v, field, fields)`` to learn G's uncertain
    parameters too, v ``(k,)`` in units of their prior standard deviations (``+ 1/2 ||v||^2``), ``field(b, v)`` and
    ``fields(bs, vs)`` taking them. ``u``, ``offsets`` (and v) are updated in place; returns ``(iterations, objective
    evaluations)``."""
    q = u.numel()
    K, d = offsets.shape
    kd = dict(dtype=u.dtype, device=u.device)
    k = 0 if theta is None else theta[0].numel()

    def coefficients(uv):
        b = torch.zeros_like(beta)
        b[active] = uv * root
        return b

    def fields(vv):  # (field, fields) with G at vv
        if theta is None:
            return make_field, make_fields
        return (lambda b: theta[1](b, vv)), (lambda bs: theta[2](bs, vv))

    failed = []

    def objective(uv, vv, ov, max_steps=None):  # a solve that fails is an infinite misfit: a rejected step
        try:
            r = residuals(fields(vv)[0](coefficients(uv)), ov, sd, max_steps) / sd
        except IntegrationError as exc:
            failed[:] = [exc]
            return math.inf, None
        prior = uv.pow(2).sum() + (0 if vv is None else vv.pow(2).sum())
        return 0.5 * float(r.pow(2).sum() + prior), r.reshape(-1)

    with torch.no_grad():
        uv, ov = u.detach().clone(), offsets.detach().clone()
        vv = None if theta is None else theta[0].detach().clone()
        value, r = objective(uv, vv, ov)
        if r is None:  # the start cannot be integrated: a smaller correction (at last G alone) that can
            _shrink_until_integrable(
                [uv, ov] + ([] if vv is None else [vv]),
                lambda: None if objective(uv, vv, ov)[1] is not None else failed[0],
                failed[0],
            )
            value, r = objective(uv, vv, ov)
        lam, evaluations, iterations = 1e-3, 1, 0
        steps = residuals.last / EVALS_PER_STEP  # the current point's solve: the trial steps' budget
        while iterations < max_iter:
            iterations += 1
            b = coefficients(uv)
            field, fields_ = fields(vv)
            J = _joint_columns(residuals, make_fields, b, active, vv, ov, sd)
            J[:, :q] *= root
            prior = torch.cat([uv] + ([] if vv is None else [vv]) + [torch.zeros(K * d, **kd)])
            grad = J.T @ r + prior
            H = J.T @ J
            H[range(q + k), range(q + k)] += 1.0
            accepted = False
            for _ in range(8):
                A = H + lam * torch.diag(H.diagonal().clamp_min(1e-12))
                try:
                    step = -torch.linalg.solve(A, grad)
                except torch.linalg.LinAlgError:
                    lam *= 10.0
                    continue
                new_u, new_o = uv + step[:q], ov + step[q + k :].reshape(K, d)
                new_v = None if vv is None else vv + step[q : q + k]
                new_value, new_r = objective(new_u, new_v, new_o, trial_budget(steps))
                evaluations += 1
                if new_value < value:
                    accepted = True
                    break
                lam *= 10.0
            if not accepted:
                break
            gain = value - new_value
            uv, vv, ov, value, r = new_u, new_v, new_o, new_value, new_r
            lam, steps = max(lam * 0.3, 1e-9), residuals.last / EVALS_PER_STEP
            if gain <= 1e-8 * max(value, 1.0):
                break
        u.data.copy_(uv)
        offsets.data.copy_(ov)
        if theta is not None:
            theta[0].copy_(vv)
    return iterations, evaluations
