"""A new subject's bands calibrated by leaving subjects out.

:func:`~torchmisspec.population.predict.predict_subject` updated by a subject's first measurements draws its
parameters from their Laplace posterior given those few points and the population, and F from its posterior. Both
are exact for the model, but the model is not the truth: two early heights of a pine pin its growth curve as if the
population's residual scale held for its whole future, while extrapolating its own path carries the model's error
too. On R's Loblolly, 0.68 of a new tree's later heights fell in the 90 % band (``scripts/study_population_data.py``).

:func:`calibrate_subjects` measures that on the data in hand: the subjects are held out in folds (experiment k in fold
``k % folds``, :data:`~torchmisspec.population._held_out.FOLDS` at most), F is conditioned without the fold's
samples (its hyperparameters kept, as do no harm does), and every held-out subject with more than ``first``
measurements is predicted from its first ``first`` ones exactly as a user's new subject is. The band's spread is
widened (or narrowed) by one factor ``c`` on every drawn path's deviation from the mean path, in the noise model's
space (:func:`~torchmisspec.prediction._bands.widened`: a relative band widens by a factor, and stays positive), and
``c`` is the smallest one under
which the subject's later measurements lie in the central ``level`` band of new measurements (paths plus the
population's measurement noise) at least a fraction ``level`` of the time, by the bisection of
:func:`~torchmisspec.torchmisspec.calibrate_bands` (Kuleshov et al. 2018, with subjects as the calibration set).
``first=0`` calibrates the band from the population alone (the subject's measured initial state, no measurement
after it: the textbook prediction interval of :func:`~torchmisspec.population.uncertainty.new_subject_prior`); it is
conservative where the population's spread is known poorly (R's Theoph: 0.97 of a held-out subject's measurements in
the 90 % band; Loblolly: 1.00), and narrowed to what the held-out subjects need.
The population's values are those fitted with every subject (refitting them per fold costs a population fit each):
the held-out subjects' spread counted in them makes the calibration, if anything, optimistic.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import torch

from .._errors import FittingError, InputError, IntegrationError, LinearAlgebraError, TorchMisspecWarning
from .._validation import check_positive_int, progress_bar
from ..data import Trajectories
from ..gp._calibration import BandCalibration
from ..prediction._bands import band_quantiles, path_quantiles, widened
from ..prediction.calibration import _check_level, _smallest_covering_scale
from ._held_out import FOLDS, fold_gp
from .predict import subject_draws

__all__ = [
    "ALONE",
    "FIRST",
    "MIN_TO_NARROW",
    "SubjectCalibration",
    "calibrate_subjects",
    "calibrations",
    "interval_score",
]

#: the measurements a held-out subject is predicted from by default (the issue's new subject: its first 2)
FIRST = 2
#: ``first`` for a band from the population alone (the subject's initial state only)
ALONE = 0
#: the held-out subjects a band must be checked on before it is narrowed (widened, it may be on any number): from
#: the population alone R's Orange (4 held-out trees each time) narrowed the textbook band to 0.30 of its spread and
#: held 0.70 of a fifth tree's measurements, where Theoph (11) and Loblolly (13) held 0.88 and 0.90
#: (``scripts/study_population_data.py``)
MIN_TO_NARROW = 8
#: what a held-out subject's fit or prediction may raise (it is left out of the calibration then)
FAILURES = (FittingError, IntegrationError, LinearAlgebraError)


@dataclass(frozen=True)
class SubjectCalibration:
    """A new subject's band calibrated on held-out subjects (:func:`calibrate_subjects`).

    Attributes:
        band: the scale on the drawn paths' deviation from the mean path, and its held-out coverage
            (:class:`~torchmisspec.BandCalibration`, ``held_out="subjects"``).
        f_draws: whether the band draws F from its posterior (``False``: the paths are the parameters' draws under
            F's mean, F's uncertainty absorbed into the scale: where F's draws moved the held-out subjects' paths
            away from their measurements, as on R's Loblolly, where a draw of F that wiggles below the growth rate
            stalls a tree's height).
        first: how many of each held-out subject's first measurements it was predicted from (:data:`ALONE`, 0: from
            the population alone, its first row the initial state).
        score: the held-out interval score of the band chosen; ``other``: that of the other way (``None``: F = 0,
            no other way).
        subjects: how many held-out subjects it was measured on (fewer than :data:`MIN_TO_NARROW`: a band is
            widened where they need it, never narrowed).
    """

    band: BandCalibration
    f_draws: bool
    first: int
    score: float
    other: float | None = None
    subjects: int = 0

    @property
    def scale(self) -> float:
        """The factor on the drawn paths' deviation from the mean path."""
        return self.band.scale

    def __str__(self) -> str:
        way = "F's posterior draws" if self.f_draws else "F's mean (its draws scored worse)"
        way = "the known model (F = 0)" if self.other is None else way
        source = "the population alone" if self.first == ALONE else f"its first {self.first} measurements"
        withheld = self.subjects < MIN_TO_NARROW and self.scale == 1.0 and self.band.coverage > self.band.level
        return (
            f"a new subject's {self.band.level:.0%} band from {source}: the paths under "
            f"{way}, their spread times {self.scale:.3g}; it held {self.band.coverage:.3f} of the held-out subjects' "
            f"later measurements (times 1: {self.band.coverage_at_one:.3f}; {self.band.num_points} measurements of "
            f"{self.subjects} subjects)"
            + (f"; not narrowed: {MIN_TO_NARROW} held-out subjects at least are needed for that" if withheld else "")
        )

    def to_dict(self) -> dict:
        """Plain values for a population file."""
        return {"band": self.band.to_dict(), "f_draws": self.f_draws, "first": self.first, "score": self.score,
                "other": self.other, "subjects": self.subjects}  # fmt: skip

    @classmethod
    def from_dict(cls, values, path) -> SubjectCalibration:
        """The record of :meth:`to_dict`, checked (``path`` names the file in errors)."""
        if not isinstance(values, dict) or set(values) != {"band", "f_draws", "first", "score", "other", "subjects"}:
            raise InputError(f"{path}: expected a subject calibration record, got {values!r:.200}")
        band = BandCalibration.from_dict(values["band"], path)
        counts = [values[k] for k in ("first", "subjects")]
        if not isinstance(values["f_draws"], bool) or not all(isinstance(v, int) and v >= 0 for v in counts):
            raise InputError(f"{path}: the subject calibration record is damaged ({values!r:.200})")
        other = None if values["other"] is None else float(values["other"])
        return cls(band, values["f_draws"], values["first"], float(values["score"]), other, values["subjects"])


def _head(one: Trajectories, m: int) -> Trajectories:
    """The first ``m`` rows of the one experiment ``one`` (its controls and readout kept)."""
    t, y = one.experiments()[0]
    readings = None
    if one.readings is not None:
        readings = (one.readings[0] if one.is_ragged else one.readings[0])[:m][None]
    return Trajectories(
        t[:m], y[:m][None], state_names=one.state_names, controls=one.controls, readout=one.readout, readings=readings
    )


def _observed(one: Trajectories) -> torch.Tensor:
    """``(T, o)`` the one experiment's observed values (states and any readings; NaN where not measured)."""
    values, mask = one.observed_values()
    return torch.where(mask[0].unsqueeze(-1), values[0], math.nan)


def _predicted(fit, one: Trajectories, k: int, m: int, num_samples: int, generator):
    """``(draws, later observed values (T - m, o))`` of experiment ``k`` (``one``) predicted from its first ``m`` rows
    (``m = 0``: from the population alone, its first row's states the initial state, later values those after it)
    under ``fit`` (:func:`~torchmisspec.population.predict.subject_draws`, with F's draws where F is kept; its
    warnings held: they are the calibration's, not the user's); ``None`` where it cannot be predicted (from the
    population alone: a state not measured in its first row)."""
    covariates = {n: float(fit.nlme.covariates[k, c]) for c, n in enumerate(fit.population.covariate_names)}
    t = one.experiments()[0][0]
    y0, first = None, None
    if m == ALONE:  # the state a user gives: set (a dose), or measured in full in the first row (not estimated)
        y0, m = one.initial_conditions[0], 1
        if not bool(torch.isfinite(y0 if one.initial_states is not None else one.experiments()[0][1][0]).all()):
            return None
    else:
        first = _head(one, m)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TorchMisspecWarning)
            draws = subject_draws(
                fit, y0, t, covariates=covariates, first=first, controls=one.controls, num_samples=num_samples,
                generator=generator,
            )  # fmt: skip
    except FAILURES:
        return None
    return draws, _observed(one)[m:]


def _without(fit, held: list[int]):
    """``fit`` with F conditioned without the experiments ``held`` (:func:`~torchmisspec.population._held_out.fold_gp`;
    the population's values and residual scale kept); ``fit`` itself where F = 0; ``None`` where F cannot be held
    out."""
    if fit.known_model:
        return dataclasses.replace(fit, calibration=None)
    keep = ~torch.isin(torch.arange(fit.data.num_experiments), torch.tensor(held))
    gp = fold_gp(fit, keep)
    if gp is None:
        return None
    fold = dataclasses.replace(fit, gp=gp, calibration=None)
    fold.__dict__["residuals_by_time"] = fit.residuals_by_time  # the population's residuals: solved once, not per fold
    return fold


def _held_out_draws(fit, counts: tuple[int, ...], num_samples: int, seed: int, progress: bool) -> dict:
    """``{m: [(draws, observed (T, o))]}`` for each ``m`` of ``counts``: every held-out subject with more than ``m``
    rows (more than 1 for the population alone) predicted from its first ``m``, F conditioned once per fold without
    it; ``draws`` cut to the times after them."""
    data = fit.data
    K = data.num_experiments
    folds = min(FOLDS, K)
    out = {m: [] for m in counts}
    with progress_bar(progress, folds, "population: bands calibrated on held-out subjects", "fold") as bar:
        for f in range(folds):
            held = [k for k in range(K) if k % folds == f and data.lengths[k] > max(min(counts), 1)]
            bar.update()
            fold = _without(fit, held) if held else None
            for k in held if fold is not None else []:
                for m in (m for m in counts if data.lengths[k] > max(m, 1)):
                    got = _predicted(fold, data[[k]], k, m, num_samples, torch.Generator().manual_seed(seed + k))
                    if got is not None:
                        out[m].append(got)
    return out


def _band(held: list, noise, scale: torch.Tensor, quantiles: torch.Tensor, seed: int, with_f: bool):
    """``band(c)``: ``[(lower, upper, observed)]`` of every held-out subject's later measurements: the central band of
    new measurements (the paths, with F's draws or under F's mean, widened by c in ``noise``'s space
    (:func:`~torchmisspec.prediction._bands.widened`), plus the population's noise ``scale``), the same noise draws
    at every c."""
    cases = []
    for i, (draws, observed) in enumerate(held):
        T = observed.shape[0]
        samples = (draws.with_f if with_f and draws.with_f is not None else draws.parameters)[:, 0, -T:]
        eps = torch.randn(samples.shape, generator=torch.Generator().manual_seed(seed + i), dtype=samples.dtype)
        d = samples.shape[-1]
        cases.append((draws.mean[0, -T:], samples, eps, observed[..., :d]))
    noise_scale = scale.nan_to_num(nan=0.0)

    def band(c: float) -> list:
        out = []
        for mean, samples, eps, observed in cases:
            paths = widened(samples, mean, c, noise)
            new = noise.inverse(noise.transform(paths) + noise_scale.to(paths) * eps)
            lo, hi = path_quantiles(torch.where(torch.isnan(paths), math.nan, new), quantiles)
            out.append((lo, hi, observed))
        return out

    return band


def _coverage(band, c: float) -> float:
    """The fraction of the held-out measurements inside ``band(c)``."""
    hits = total = 0
    for lo, hi, obs in band(c):
        hits += int(((obs >= lo) & (obs <= hi)).sum())  # False where obs is NaN (missing)
        total += int(torch.isfinite(obs).sum())
    return hits / max(total, 1)


def interval_score(band, noise, level: float) -> float:
    """The mean interval score (Gneiting & Raftery 2007) of the held-out measurements in the bands ``band``
    (``[(lower, upper, observed)]``), in ``noise``'s space: the band's width plus ``2 / (1 - level)`` times how far a
    measurement lies outside it; lower is better (a proper scoring rule: it rewards bands both narrow and right)."""
    alpha, scores = 1.0 - level, []
    for lo, hi, obs in band:
        seen = torch.isfinite(obs)
        z, zl, zh = (noise.transform(v)[seen] for v in (obs, lo, hi))
        scores.append((zh - zl) + (2.0 / alpha) * ((zl - z).clamp_min(0) + (z - zh).clamp_min(0)))
    flat = torch.cat(scores)
    return float(flat.mean()) if flat.numel() and bool(torch.isfinite(flat).all()) else math.inf


def _candidate(held: list, fit, level: float, seed: int, with_f: bool):
    """``(BandCalibration, interval score)``: the smallest covering scale of the bands with F's draws or under F's
    mean (:func:`~torchmisspec.prediction.calibration._smallest_covering_scale`), and their interval score there."""
    S = (held[0][0].with_f if with_f else held[0][0].parameters).shape[0]
    quantiles = band_quantiles(level, S, what="calibrate_subjects")
    band = _band(held, fit.noise, fit.nlme.modes.scale, quantiles, seed, with_f)
    total = sum(int(torch.isfinite(obs).sum()) for _, _, obs in band(1.0))
    scale, tried, reached = _smallest_covering_scale(lambda c: _coverage(band, c), level, total)
    if scale < 1.0 and len(held) < MIN_TO_NARROW:  # too few subjects to narrow on: the model's own band stands
        scale = 1.0
    final = next(v for c, v in reversed(tried) if c == scale)
    record = BandCalibration(
        scale=scale,
        level=level,
        coverage_at_one=tried[0][1],
        coverage=final,
        scales=tuple(c for c, _ in tried),
        coverages=tuple(v for _, v in tried),
        folds=min(FOLDS, fit.data.num_experiments),
        refit=False,
        num_points=total,
        reached=reached,
        held_out="subjects",
    )
    return record, interval_score(band(scale), fit.noise, level)


def calibrate_subjects(
    fit, *, first: int = FIRST, level: float = 0.9, num_samples: int = 32, seed: int = 0, progress: bool = False
) -> SubjectCalibration | None:
    """How a new subject's band from its ``first`` measurements must be drawn and scaled (the module's notes;
    ``first=0``, :data:`ALONE`: from the population alone), measured on the subjects of the population ``fit``
    (:class:`~torchmisspec.population.fit.PopulationFit` with its data); ``None`` where no subject has more than
    ``first`` measurements or none can be predicted. ``num_samples`` parameter draws per held-out subject (each with
    F's draws); ``seed`` fixes them."""
    first = check_positive_int(first, "first", minimum=0)
    return calibrations(fit, (first,), level=level, num_samples=num_samples, seed=seed, progress=progress)[first]


def calibrations(
    fit, counts: tuple[int, ...], *, level: float = 0.9, num_samples: int = 32, seed: int = 0, progress: bool = False
) -> dict:
    """``{m: SubjectCalibration or None}``: :func:`calibrate_subjects` for each ``m`` of ``counts`` (checked counts,
    0 or more), F conditioned once per fold for all of them."""
    level = _check_level(level)
    num_samples = check_positive_int(num_samples, "num_samples")
    if fit.data is None:
        return dict.fromkeys(counts)
    held = _held_out_draws(fit, counts, num_samples, seed, progress)
    return {m: _chosen(held[m], fit, level, seed, m) if held[m] else None for m in counts}


def _chosen(held: list, fit, level: float, seed: int, first: int) -> SubjectCalibration:
    """The calibration of the bands with F's draws or under F's mean, whichever has the lower held-out interval
    score (a tie: F's own draws)."""
    options = [False] if held[0][0].with_f is None else [True, False]
    scored = {with_f: _candidate(held, fit, level, seed, with_f) for with_f in options}
    f_draws = min(options, key=lambda with_f: (scored[with_f][1], not with_f))
    band, score = scored[f_draws]
    other = scored.get(not f_draws)
    return SubjectCalibration(band, f_draws, first, score, None if other is None else other[1], len(held))
