"""Samples at a trajectory's edges that its derivative estimator cannot be trusted at.

A stencil or a local fit is one-sided at a trajectory's first and last samples. Where the path bends sharply there
(a drug's concentration rising from zero as the depot empties into it), the estimate there is mostly the
estimator's own error, and a correction learned from it is wrong where only those samples reach. On issue 43's
population (``scripts/study_population_design.py``, seed 43501: both states of 12 subjects every 30 min) the chosen
estimator's error at each subject's first sample (concentration 0, rising at 8 mg/L/h) was 3.8 times the RMS of all
the samples, at every other position 0.1-0.7 times; the correction learned with them put F at -1.7 mg/L/h near
concentration 0, where the truth is -0.01, and the new subject's designed sampling times, fitted with that F, gave
3.4 times the error of the standard schedule's. Without those 12 samples: 0.95 times.

``correction_samples(derivative="auto")`` measures the error at each edge position on the known model's copy of the
data (the self-check's, :func:`~torchmisspec.learning.samples._estimators.estimator_error`: G alone from the same
initial states on the same times, with noise of the data's level), pooled over the experiments (root mean square),
in units of the samples' RMS, and leaves out the samples at positions above :data:`EDGE_ERROR_LIMIT` (the samples'
``derivative`` says how many), where the estimator is good away from the edges (its error there within the
self-check's bar, ``ESTIMATOR_ERROR_THRESHOLD``): where it is poor everywhere, the edges do not stand out and the
self-check's warning says what to do. The edge is the estimator's one-sided reach (half a stencil or a window;
one sample for the GP in time). Explicit estimators keep every sample: they are the user's choice.
"""

from __future__ import annotations

import math

import torch

from ._estimators import ESTIMATOR_ERROR_THRESHOLD

__all__ = ["EDGE_ERROR_LIMIT", "edge_reach", "rms_rows", "unreliable_edges"]

#: an edge position whose estimator error (on the known model's copy, pooled over experiments) is above this many
#: times the samples' RMS is left out: the samples there are mostly the estimator's error (the module's notes)
EDGE_ERROR_LIMIT = 1.0
#: at least this fraction of the samples is kept (more flagged: every sample is kept, and the self-check's warning on
#: the whole estimator speaks)
MIN_KEPT = 0.5


def edge_reach(name: str, options: dict) -> int:
    """How many samples at each end of a trajectory the estimator ``name`` with ``options`` computes one-sidedly."""
    if name == "central":
        return int(options.get("order", 2)) // 2
    if name == "smooth":
        return int(options.get("window", 7)) // 2
    return 1


def _positions(lengths: list[int], reach: int, device) -> torch.Tensor:
    """``(N,)`` each row's edge position: ``j`` for the (j+1)-th sample from the start, ``-1 - j`` from the end,
    ``reach`` (no edge) elsewhere; a sample within reach of both ends takes the nearer."""
    out = []
    for n in lengths:
        j = torch.arange(n, device=device)
        from_end = n - 1 - j
        pos = torch.where(j <= from_end, j, -1 - from_end)
        out.append(torch.where(torch.minimum(j, from_end) < reach, pos, torch.full_like(pos, reach)))
    return torch.cat(out)


def unreliable_edges(errors: torch.Tensor, targets: torch.Tensor, copy_lengths: list[int], lengths: list[int], reach):
    """``(left out (N,), left out of the copy (N_copy,), the worst edge position's ratio)``: the rows of the data
    (experiments of ``lengths``, samples ``targets (N, o)``) at the edge positions where the estimator's ``errors
    (N_copy, o)`` on the known model's copy (its experiments of ``copy_lengths``) have a root mean square, pooled
    over its experiments, above :data:`EDGE_ERROR_LIMIT` times the samples' RMS (NaN rows give no sample and are not
    counted). Only where the estimator is good away from the edges (its error there at most
    ``ESTIMATOR_ERROR_THRESHOLD`` of the samples' RMS, the self-check's own bar): where it is poor everywhere its
    edges do not stand out, and the self-check's warning speaks. Nothing is left out where that would take more than
    half the samples."""
    device = errors.device
    none = torch.zeros(sum(lengths), dtype=torch.bool, device=device), torch.zeros_like(errors[:, 0], dtype=torch.bool)
    spread = rms_rows(targets)
    if reach < 1 or not spread > 0:
        return (*none, 0.0)
    on_copy = _positions(copy_lengths, reach, device)
    positions = _positions(lengths, reach, device)
    if rms_rows(errors[on_copy == reach]) > ESTIMATOR_ERROR_THRESHOLD * spread:
        return (*none, 0.0)  # the estimator is poor away from the edges too (nothing inside: NaN, the same)
    worst, out, out_copy = 0.0, none[0].clone(), none[1].clone()
    for p in range(-reach, reach):
        ratio = rms_rows(errors[on_copy == p]) / spread
        if not ratio > 0:  # no sample there
            continue
        worst = max(worst, ratio)
        if ratio > EDGE_ERROR_LIMIT:
            out |= positions == p
            out_copy |= on_copy == p
    if int(out.sum()) > (1 - MIN_KEPT) * out.numel():
        return (*none, worst)
    return out, out_copy, worst


def rms_rows(x: torch.Tensor) -> float:
    """The root mean square of the rows of ``x (n, o)`` that are finite (NaN: none)."""
    x = x[torch.isfinite(x).all(-1)]
    return float(x.pow(2).mean().sqrt()) if x.numel() else math.nan
