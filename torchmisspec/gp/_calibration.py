"""The record of a calibration of a correction GP's bands (:class:`BandCalibration`), kept and saved with the GP.

:func:`torchmisspec.prediction.calibration.calibrate_bands` finds the factor ``c`` on the posterior draws' deviation
from the posterior mean; :meth:`CorrectedODE.calibrate <torchmisspec.CorrectedODE.calibrate>` stores the result on the
GP (``gp.calibration_``), so that ``gp.save`` / ``CorrectionGP.load`` carry it and every later posterior of that GP uses
it. The record holds plain values only (a file never holds code).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .._errors import InputError

__all__ = ["BandCalibration"]


#: What a calibration can hold out.
HELD_OUT = ("experiments", "time pieces", "subjects")


@dataclass(frozen=True)
class BandCalibration:
    """The result of :func:`~torchmisspec.prediction.calibration.calibrate_bands`.

    Attributes:
        scale: the calibrated factor ``c`` on the posterior draws' deviation from the posterior mean (1: the GP's
            own bands were right; above 1: they were too narrow).
        level: the band's nominal coverage it was calibrated for.
        coverage_at_one: the held-out coverage of the uncalibrated bands (c = 1).
        coverage: the held-out coverage at ``scale``.
        scales / coverages: every scale the bisection tried, in order, with its held-out coverage.
        folds: the number of folds held out; ``refit``: whether the GP's hyperparameters were re-learned in every
            fold.
        reached: whether some scale reaches the level (when not, ``scale`` is the smallest doubling whose held-out
            coverage is within one standard error of the best one tried, and a warning was issued).
        num_points: the held-out (time, component) entries compared at each scale.
        held_out: what was held out: ``"experiments"``, or ``"time pieces"`` of one experiment (each forecast from
            its first state by the model refitted on the others), or ``"subjects"`` of a population (each
            predicted from its first measurements: :mod:`torchmisspec.population.calibration`).
    """

    scale: float
    level: float
    coverage_at_one: float
    coverage: float
    scales: tuple[float, ...]
    coverages: tuple[float, ...]
    folds: int
    refit: bool
    num_points: int
    reached: bool = True
    held_out: str = "experiments"

    def __str__(self) -> str:
        return (
            f"BandCalibration(scale={self.scale:.3g}: the central {self.level:.0%} band covers {self.coverage:.3f} "
            f"of the held-out observations (c = 1: {self.coverage_at_one:.3f}); {self.folds} folds of {self.held_out}, "
            f"{'refitted' if self.refit else 'conditioned'} GP"
            + ("" if self.reached else "; the level is out of reach")
            + f", {self.num_points} points)"
        )

    def to_dict(self) -> dict:
        """Plain values (floats, ints, bools, lists) for a model file."""
        out = dataclasses.asdict(self)
        out["scales"], out["coverages"] = list(self.scales), list(self.coverages)
        return out

    @classmethod
    def from_dict(cls, values, path) -> BandCalibration:
        """The record of :meth:`to_dict`, checked (``path`` names the file in errors)."""
        names = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(values, dict) or not set(values) <= names:
            raise InputError(f"{path}: expected a band calibration record with fields {sorted(names)}, got {values!r}")
        try:
            record = cls(
                **{
                    **values,
                    "scales": tuple(float(v) for v in values.get("scales", ())),
                    "coverages": tuple(float(v) for v in values.get("coverages", ())),
                }
            )
        except TypeError as exc:
            raise InputError(f"{path}: the band calibration record is damaged ({exc})") from exc
        if not (isinstance(record.scale, float) and math.isfinite(record.scale) and record.scale > 0):
            raise InputError(f"{path}: expected a positive finite calibrated scale, got {record.scale!r}")
        if record.held_out not in HELD_OUT:
            raise InputError(
                f"{path}: expected the calibration's held-out data to be one of {HELD_OUT}, got {record.held_out!r}"
            )
        return record
