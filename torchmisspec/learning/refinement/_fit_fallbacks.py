"""What the fits through the ODE (:mod:`torchmisspec.learning.refinement._trajectory_map`) do when a solve fails or a
model cannot be carried (issue 41, item 3: a fit never ends on a trial step): a starting correction that cannot be
integrated is shrunk towards the known model alone (:func:`_shrink_until_integrable`); a batched solve of perturbed
models that fails is split until the failing perturbations are isolated, and their Jacobian columns dropped
(:func:`_batched`, :func:`_dropped`); a feature model with more active terms than samples gets inputs that can carry its
coefficients (:func:`_spanning_inputs`).
"""

from __future__ import annotations

import math

import torch

from ..._errors import IntegrationError, TorchMisspecWarning, warn

#: the factors by which a starting correction whose paths cannot be integrated over the experiments is shrunk, in
#: turn: the last is the known model alone (F = 0, G's learned parameters at their prior mean, the initial states as
#: observed), which the fit then starts from
SHRINK = (0.5, 0.1, 0.01, 0.0)


def _shrink_until_integrable(tensors, attempt, error=None) -> None:
    """Shrink ``tensors`` (the starting coefficients or targets, offsets, parameters: each zero at the known model
    alone) in place by the factors of :data:`SHRINK` until ``attempt()`` (the :class:`IntegrationError` of a solve at
    their current values, or None) integrates, with a warning saying by how much; raise the last error when even
    F = 0 cannot be integrated (nothing to start from). ``error``: that of the start, when known already."""
    error = attempt() if error is None else error
    if error is None:
        return
    start = [t.detach().clone() for t in tensors]
    for factor in SHRINK:
        with torch.no_grad():
            for t, s in zip(tensors, start, strict=True):
                t.copy_(s * factor)
        last = attempt()
        if last is None:
            what = "the known model alone (F = 0)" if factor == 0 else f"it shrunk by a factor {factor:g}"
            warn(
                "fit_trajectories: the starting correction cannot be integrated over the experiments "
                f"({str(error)[:160]}); the fit starts from {what} instead",
                TorchMisspecWarning,
            )
            return
    raise IntegrationError(
        "fit_trajectories: the starting correction cannot be integrated over the experiments, nor any smaller one "
        f"down to the known model alone (F = 0): {last}"
    ) from last


def _batched(run, copies: int) -> torch.Tensor:
    """``run(lo, hi)`` (the residuals ``(hi - lo, n, e)`` of copies lo ... hi - 1 in one batched solve) for all
    ``copies``; a batch whose solve fails is split in halves, and a copy that cannot be integrated alone gives NaN
    (its Jacobian column is then dropped by the caller: a rejected perturbation, not the end of the fit). Raises the
    last :class:`IntegrationError` when no copy can be integrated."""
    parts, pending, error = [], [(0, copies)], None
    while pending:
        lo, hi = pending.pop(0)
        try:
            parts.append(run(lo, hi))
        except IntegrationError as exc:
            error = exc
            if hi - lo > 1:
                mid = (lo + hi) // 2
                pending[:0] = [(lo, mid), (mid, hi)]
            else:
                parts.append(None)
    like = next((r for r in parts if r is not None), None)
    if like is None:
        raise error
    return torch.cat([torch.full_like(like[:1], math.nan) if r is None else r for r in parts])


def _dropped(J: torch.Tensor) -> torch.Tensor:
    """Jacobian columns ``J (rows, cols)`` with a non-finite entry set to 0 (a perturbation that failed: dropped)."""
    return torch.where(torch.isfinite(J).all(0, keepdim=True), J, torch.zeros((), dtype=J.dtype, device=J.device))


def _spanning_inputs(X: torch.Tensor, targets: torch.Tensor, noise, features, W: torch.Tensor):
    """``(X, targets, noise)`` with inputs added where the features ``features(X)`` of some output's active terms
    (``W[:, o] > 0``) have a lower rank than their number (fewer samples than terms, e.g. 12 days of an epidemic and
    20 monomials of degree 3 in 3 states): pseudo-targets at X alone cannot reproduce F = phi(x)^T beta away from
    X, and the model returned would not be the one fitted (on the influenza data its paths blew up). The added inputs
    are fixed quasi-random points of X's bounding box (widened by a tenth, or by 0.1 where a column is constant),
    their targets 0 and their known noise the mean of the samples' (they only carry the pseudo-targets)."""
    active = W > 0
    Phi = features(X)

    def deficient(P):
        return any(
            int(torch.linalg.matrix_rank(P[:, active[:, o]])) < int(active[:, o].sum())
            for o in range(W.shape[1])
            if bool(active[:, o].any())
        )

    if not deficient(Phi):
        return X, targets, noise
    lo, hi = X.min(0).values, X.max(0).values
    pad = torch.where(hi > lo, 0.1 * (hi - lo), 0.1 * torch.ones_like(lo))
    engine = torch.quasirandom.SobolEngine(X.shape[1], scramble=True, seed=0)
    extra = (lo - pad) + (hi - lo + 2 * pad) * engine.draw(2 * Phi.shape[1]).to(X)
    X = torch.cat([X, extra])
    targets = torch.cat([targets, targets.new_zeros(extra.shape[0], *targets.shape[1:])])
    if noise is not None:
        noise = torch.cat([noise, noise.mean(0, keepdim=True).expand(extra.shape[0], *noise.shape[1:])])
    return X, targets, noise
