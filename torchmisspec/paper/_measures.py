"""Pieces several of the paper's figures share: run sizes (full or smoke), summaries of repeated measurements, the
prediction bands of Figs 1 and 6, the set-up numbers of Figs 3 and 6, and the error-vs-K figures 5 and 8."""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from .. import plotting
from .._errors import TorchMisspecWarning
from ..metrics import mean_and_standard_error, trajectory_rmse
from . import _layout
from .studies import StudyResult

if TYPE_CHECKING:  # pragma: no cover
    from ._session import _Designs

# Sizes: (full, smoke).
#: Posterior draws of F for the bands of Figs 1 and 6 (full run, smoke run).
_BAND_SAMPLES = (128, 16)
#: Central band probabilities whose empirical coverage of the true test trajectories Figs 1 and 6 report.
_BAND_LEVELS = (0.5, 0.9, 0.95)


def _pick(sizes: tuple, smoke: bool):
    return sizes[1] if smoke else sizes[0]


def _mean_se(values: Sequence[float]) -> dict:
    mean, se = mean_and_standard_error(values)
    return {"mean": float(mean), "stderr": float(se), "n": len(values), "values": [float(v) for v in values]}


def _rmse(pred: torch.Tensor, true: torch.Tensor) -> float:
    return float(trajectory_rmse(pred, true))


def _bands(model, y0, times, true, mis, *, samples, generator, title, path, files) -> dict:
    """Posterior draws of F integrated from the test initial conditions (``CorrectedODE.posterior``): a figure of the
    bands of the first one, and the empirical coverage of the true test trajectories by the central bands."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TorchMisspecWarning)
        post = model.posterior(y0, times, num_samples=samples, generator=generator)
    fig = plotting.plot_prediction_bands(post, index=0, true_states=true, misspecified_states=mis, title=title)
    _layout.save(fig, path, files)
    lower, upper = post.interval(0.9)
    return {
        "num_samples": samples,
        "coverage_of_true_paths": {f"{v:g}": float(post.covers(true, v).double().mean()) for v in _BAND_LEVELS},
        "mean_band_width_90": float((upper - lower).mean()),
        "extrapolating_paths": int(post.extrapolating.sum()),
        "warnings": [str(w.message) for w in caught if issubclass(w.category, TorchMisspecWarning)],
    }


def _setup_numbers(d: _Designs, candidates: str, prior: dict) -> dict:
    """The set-up of a design comparison, read from it: candidates, K, T, final time, prior, scoring grid."""
    t_final = float(d.times[-1])
    return {
        "candidates": candidates,
        "K": len(next(iter(d.plans.values()))),
        "T": int(d.times.numel()),
        "t_final": t_final,
        "prior": prior,
        "rmse_on": f"{d.fine.numel()} times on [0, {t_final:g}]",
    }


def _study_numbers(study: StudyResult, ratios: Iterable[tuple[str, str]]) -> dict:
    data = {
        "ks": study.ks,
        "metric": study.metric,
        "realizations": study.realizations,
        "references": study.references,
        "summary": {k: {"mean": m, "stderr": e} for k, (m, e) in study.summary().items()},
        "ratios": {},
        "meta": study.meta,
    }
    for a, b in ratios:
        mean, se = study.ratio(a, b)
        data["ratios"][f"{a}/{b}"] = {"mean": mean, "stderr": se}
    data["table"] = study.table(list(ratios))
    return data


def _study_figure(study, path: Path, labels: dict, ylabel: str, title: str, ratios: list[tuple[str, str]]) -> dict:
    """Error-vs-K curves of a study (Figs 5 and 8) and the numbers behind them."""
    files: list[str] = []
    fig = _layout.curves_figure(
        study.ks, study.summary(), references=study.references, ylabel=ylabel, title=title, labels=labels
    )
    _layout.save(fig, path, files)
    data = _study_numbers(study, ratios)
    data["files"] = files
    return data
