"""One trajectory cut in time: the held-out pieces that stand in for held-out experiments.

With one experiment there is no other experiment to hold out. :func:`time_pieces` cuts a fully measured trajectory
into consecutive pieces, each an experiment of its own that a model fitted on the others forecasts from its first
state: :func:`~torchmisspec.fit_correction` scores its candidates on them, and
:meth:`CorrectedODE.calibrate <torchmisspec.CorrectedODE.calibrate>` calibrates the bands on them
(:func:`piece_samples` gives the fit's samples the pieces' experiment indices).
"""

from __future__ import annotations

import dataclasses

import torch

from ..._errors import InputError
from ...data import Trajectories
from ..samples.observations import CorrectionSamples

__all__ = ["MIN_PIECE", "TIME_PIECES", "piece_samples", "time_pieces"]

#: With one experiment, the trajectory is cut in time into at most this many consecutive pieces, each held out in
#: turn (forecast from its first state by a model fitted on the others)...
TIME_PIECES = 3
#: ... of at least this many times each (the default derivative estimator's widest stencil).
MIN_PIECE = 5


def _cuts(trajectories: Trajectories) -> list[int] | None:
    """The pieces' boundaries (row indices) of one fully measured experiment, or ``None`` (see :func:`time_pieces`)."""
    if trajectories.num_experiments != 1 or trajectories.readout is not None or trajectories.is_partial:
        return None
    T = trajectories.experiments()[0][0].shape[0]
    n = min(TIME_PIECES, T // MIN_PIECE)
    return None if n < 2 else [round(i * T / n) for i in range(n + 1)]


def time_pieces(trajectories: Trajectories) -> Trajectories | None:
    """One fully measured experiment (states, no readout) cut in time into :data:`TIME_PIECES` consecutive pieces of
    at least :data:`MIN_PIECE` times, as experiments of their own (each under the experiment's input profile);
    ``None`` when it is too short for two pieces, or is not of that kind."""
    cuts = _cuts(trajectories)
    if cuts is None:
        return None
    t, y = trajectories.experiments()[0]
    n = len(cuts) - 1
    controls = None if trajectories.controls is None else trajectories.controls[[0] * n]
    return Trajectories(
        [t[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True)],
        [y[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True)],
        state_names=trajectories.state_names,
        controls=controls,
    )


def piece_samples(samples: CorrectionSamples, trajectories: Trajectories) -> CorrectionSamples:
    """``samples`` of the one experiment ``trajectories`` (one per row whose states are all observed, in time
    order, as :func:`~torchmisspec.correction_samples` makes them) with the experiment index of the
    :func:`time_pieces` piece each falls in."""
    cuts = _cuts(trajectories)
    if cuts is None:
        raise InputError(
            "trajectories: expected one fully measured experiment of at least "
            f"{2 * MIN_PIECE} times to cut into pieces, got {trajectories.num_experiments} experiment(s)"
        )
    states = trajectories.experiments()[0][1]
    rows = torch.isfinite(states).all(-1).nonzero().flatten()
    if rows.numel() != samples.num_samples:
        raise InputError(
            f"samples: expected one sample per fully observed time of the trajectory ({rows.numel()}), got "
            f"{samples.num_samples}; pass the samples fitted on this trajectory (gp.samples_ of fit_correction)"
        )
    bounds = torch.tensor(cuts[1:-1], device=rows.device)
    piece = torch.bucketize(rows, bounds, right=True).to(samples.experiment)
    return dataclasses.replace(samples, experiment=piece)
