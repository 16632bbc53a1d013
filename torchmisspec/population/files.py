"""Saving and loading a fitted population (:meth:`PopulationFit.save <torchmisspec.population.fit.PopulationFit.save>`)
without pickled code.

A population fit takes from half a minute (theophylline's 12 subjects) to a few minutes; a lab fits it once and
designs or predicts each next subject later. A file holds one dictionary of plain values, written with ``torch.save``
and read with ``torch.load(weights_only=True)`` (tensors and plain containers only: a crafted file cannot run code):
the population's declaration (its varying parameters' names, their distributions by name, the covariates), the
noise model by name, both mixed-effects fits (the classical one, F = 0, and the one with F: their values, every
experiment's modes, the standard errors and F's shifts of them), F (:func:`~torchmisspec.gp._persistence.to_blob`),
the data fitted, and the calibration of a new subject's bands (:mod:`~torchmisspec.population.calibration`). The
system is code and is not saved: :func:`load` takes it again, checked by name, state dimension and parameter names,
and rebuilds everything derived from it (the layout, the system F reads, F's mean).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch

from .._errors import InputError, TorchMisspecError
from .._validation import check_writable, writing
from ..design._campaign_data import _noise_blob, _noise_from, data_blob, data_from
from ..gp import CorrectionGP, _persistence
from ..noise import NOISE_MODELS
from ..systems import MisspecifiedSystem
from ._f_uncertainty import Shifts
from ._modes import Modes, mean_correction
from ._subjects import fitted_system
from .calibration import SubjectCalibration
from .distributions import DISTRIBUTIONS
from .model import Population, PopulationValues
from .nlme import NLMEFit, make_layout

__all__ = ["save", "load", "FORMAT", "VERSION"]

FORMAT = "torchmisspec.PopulationFit"
VERSION = 1
_VALUES = ("mean", "spread", "effects", "centre", "acts")
_MODES = ("eta", "covariance", "shared", "initial_states", "scale", "z")


def save(fit, path: str | Path) -> Path:
    """Write the population ``fit`` to ``path`` atomically; the folder must exist."""
    path = check_writable(path)
    if NOISE_MODELS.get(getattr(fit.noise, "name", None)) is not type(fit.noise):
        raise InputError(
            f"save: expected a population fitted with one of the package's noise models {sorted(NOISE_MODELS)}, got "
            f"{fit.noise!r:.80}, which is code and cannot be saved; refit with a named noise model to save it"
        )
    gp = fit.gp
    if gp is not None and getattr(gp, "library", None) is not None:
        _persistence.config_of(gp)  # raises: a feature library is code
    blob = {
        "format": FORMAT,
        "version": VERSION,
        "system": _system_record(fit.system),
        "population": _population_blob(fit.population),
        "noise": _noise_blob(fit.noise),
        "classical": _nlme_blob(fit.classical),
        "nlme": None if fit.nlme is fit.classical else _nlme_blob(fit.nlme),
        "gp": None if gp is None else _persistence.to_blob(gp),
        "data": None if fit.data is None else data_blob(fit.data),
        "held_out": None if fit.held_out is None else [float(v) for v in fit.held_out],
        "calibration": None if fit.calibration is None else fit.calibration.to_dict(),
        "calibration_alone": None if fit.calibration_alone is None else fit.calibration_alone.to_dict(),
    }
    tmp = path.with_name(path.name + ".tmp")
    with writing(path):
        torch.save(blob, tmp)
        os.replace(tmp, path)
    return path


def load(cls, path: str | Path, system: MisspecifiedSystem):
    """The ``cls`` (:class:`~torchmisspec.population.fit.PopulationFit`) that :func:`save` wrote to ``path``, for
    ``system`` (the one it was fitted with). A file that is not one, or is damaged, raises an InputError naming
    what is wrong."""
    blob = _persistence.read_safely(path, "PopulationFit", "PopulationFit.save")
    path = Path(path)
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(
            f"system: expected the MisspecifiedSystem the population was fitted with, got {type(system).__name__}"
        )
    _check_header(blob, path, system)
    try:
        population = _population_from(blob["population"])
        layout = make_layout(system, population)
        classical = _nlme_from(blob["classical"], layout, None)
        gp = None if blob["gp"] is None else _persistence.from_blob(CorrectionGP, blob["gp"], f"{path} (field 'gp')")
        nlme = classical
        if blob["nlme"] is not None:
            nlme = _nlme_from(blob["nlme"], layout, None)
        fit = cls(
            system, population, _noise_from(blob["noise"], f"{path} (field 'noise')"), classical, nlme, gp,
            fitted_system(system, nlme), data_from(blob["data"], path, torch.float64, torch.device("cpu")),
            None if blob["held_out"] is None else tuple(float(v) for v in blob["held_out"]),
            _calibration_from(blob.get("calibration"), path, "calibration"),
            _calibration_from(blob.get("calibration_alone"), path, "calibration_alone"),
        )  # fmt: skip
    except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as exc:
        raise InputError(f"{path}: a damaged PopulationFit file ({type(exc).__name__}: {exc})") from exc
    except TorchMisspecError as exc:
        if isinstance(exc, InputError) and str(exc).startswith(str(path)):
            raise
        raise InputError(f"{path}: a damaged PopulationFit file ({type(exc).__name__}: {exc})") from exc
    if fit.gp is not None and not fit.known_model:  # F's mean on the system it reads, as the fit left it
        correction = mean_correction(fit.subject_system, fit.gp)
        fit = _with_correction(fit, correction)
    return fit


def _calibration_from(record, path: Path, field: str):
    """The subject calibration of a file's ``field`` (``None``: none saved, as in a file from before calibrations)."""
    return None if record is None else SubjectCalibration.from_dict(record, f"{path} (field '{field}')")


def _system_record(system: MisspecifiedSystem) -> dict:
    names = [] if system.parameters is None else list(system.parameters.names)
    return {"name": system.name, "state_dim": system.state_dim, "parameters": names}


def _check_header(blob, path: Path, system: MisspecifiedSystem) -> None:
    """A PopulationFit file of this version, saved for a system of this name, dimension and parameters."""
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        got = f"format {blob.get('format')!r}" if isinstance(blob, dict) else type(blob).__name__
        raise InputError(f"{path}: expected a torchmisspec PopulationFit file (format {FORMAT!r}), got {got}")
    if blob.get("version") != VERSION:
        raise InputError(f"{path}: expected PopulationFit file version {VERSION}, got {blob.get('version')!r}")
    saved, here = blob.get("system"), _system_record(system)
    if saved != here:
        raise InputError(
            f"system: expected the system the population was fitted with, {saved!r:.200}, got {here!r:.200}; pass "
            "that system (PopulationFit.load's system, the command line's --system)"
        )


def _population_blob(population: Population) -> dict:
    return {
        "varying": list(population.varying),
        "distribution": {n: d.name for n, d in population.distribution.items()},
        "covariates": {p: list(c) for p, c in population.covariates.items()},
    }


def _population_from(blob: dict) -> Population:
    bad = [d for d in blob["distribution"].values() if d not in DISTRIBUTIONS]
    if bad:
        raise InputError(f"expected distributions among {sorted(DISTRIBUTIONS)}, got {bad}")
    dist = {n: DISTRIBUTIONS[d]() for n, d in blob["distribution"].items()}
    return Population(list(blob["varying"]), distribution=dist, covariates=dict(blob["covariates"]) or None)


def _nlme_blob(nlme: NLMEFit) -> dict:
    shifts = None if nlme.shifts is None else [f.detach().cpu() for f in nlme.shifts.fixed]
    return {
        "values": {k: getattr(nlme.values, k).detach().cpu() for k in _VALUES},
        "modes": {k: getattr(nlme.modes, k).detach().cpu() for k in _MODES},
        "num_residuals": int(nlme.modes.num_residuals),
        "standard_errors": [s.detach().cpu() for s in nlme.standard_errors],
        "covariates": nlme.covariates.detach().cpu(),
        "free": nlme.free.detach().cpu(),
        "rounds": int(nlme.rounds),
        "converged": bool(nlme.converged),
        "shifts": shifts,
    }


def _nlme_from(blob: dict, layout, correction) -> NLMEFit:
    values = PopulationValues(**{k: blob["values"][k] for k in _VALUES})
    modes = Modes(**{k: blob["modes"][k] for k in _MODES}, num_residuals=int(blob["num_residuals"]))
    kv = len(layout.vary)
    if values.mean.shape != (kv,) or modes.eta.shape[-1] != kv:
        raise InputError(f"expected {kv} varying parameters in the fit, got values of shape {tuple(values.mean.shape)}")
    shifts = None if blob["shifts"] is None else Shifts(list(blob["shifts"]))
    return NLMEFit(
        layout, values, modes, tuple(blob["standard_errors"]), blob["covariates"], blob["free"], correction,
        int(blob["rounds"]), bool(blob["converged"]), shifts,
    )  # fmt: skip


def _with_correction(fit, correction):
    return dataclasses.replace(fit, nlme=dataclasses.replace(fit.nlme, correction=correction))
