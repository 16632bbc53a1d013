"""Covariates of a lab's table: one value per experiment (a subject's weight, a batch's strain), read from its rows.

A population's covariates (:mod:`torchmisspec.population`) sit in the same table as the measurements, repeated on
every row of an experiment (R's ``Theoph``: ``Wt`` on each of a subject's rows). :func:`read_covariates` reads them in
the experiments' order of :meth:`Trajectories.load <torchmisspec.Trajectories.load>` and refuses a covariate that
changes within an experiment (a time-varying quantity is an input, ``control_columns``), a cell that is not a number,
or an experiment without any value.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch

from .._errors import InputError
from ._tables import _experiment_labels, _read_table

__all__ = ["read_covariates", "experiment_labels"]


def experiment_labels(path, experiment_column: str | None = "experiment") -> list[str]:
    """The experiments' labels of a text table, in the order :meth:`Trajectories.load` gives them."""
    header, body = _read_table(Path(path))
    column = experiment_column if experiment_column in header else None
    return _experiment_labels(Path(path), header, body, column)[1]


def read_covariates(path, names: Sequence[str], *, experiment_column: str | None = "experiment") -> dict:
    """``{name: (K,) float64}``: the covariates ``names`` of the table ``path``, one value per experiment (the
    module's notes)."""
    path = Path(path)
    header, body = _read_table(path)
    missing = [n for n in names if n not in header]
    if missing:
        raise InputError(
            f"{path}: expected covariate column(s) {missing}, got columns {header}; name them as the table"
        )
    column = experiment_column if experiment_column in header else None
    labels, order = _experiment_labels(path, header, body, column)
    out = {}
    for name in names:
        c = header.index(name)
        seen: dict[str, tuple[float, int]] = {}
        for (line, row), label in zip(body, labels, strict=True):
            if not row[c]:
                continue
            value = _number(path, name, row[c], line)
            if label in seen and seen[label][0] != value:
                raise InputError(
                    f"{path}: expected one value of covariate {name!r} per experiment, got {seen[label][0]:g} (line "
                    f"{seen[label][1]}) and {value:g} (line {line}) in experiment {label!r}; a quantity that changes "
                    "within an experiment is an input (--input-columns)"
                )
            seen.setdefault(label, (value, line))
        absent = [label for label in order if label not in seen]
        if absent:
            raise InputError(
                f"{path}: expected a value of covariate {name!r} in every experiment, got none in {absent}"
            )
        out[name] = torch.tensor([seen[label][0] for label in order], dtype=torch.float64)
    return out


def _number(path: Path, name: str, cell: str, line: int) -> float:
    try:
        value = float(cell)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"{path}: expected a finite number in covariate column {name!r} on line {line}, got {cell!r}")
    return value
