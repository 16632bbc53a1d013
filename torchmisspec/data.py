"""Trajectories: observed or simulated states of K experiments, and :func:`simulate`.

``Trajectories(times, states)`` holds ``states (K, T, d)`` sampled at ``times (T,)`` shared by all experiments or
``(K, T)`` one grid per experiment (irregular spacing allowed, strictly increasing along each row). It wraps user
data as well as simulations and saves to / loads from ``.npz`` and text tables (``.csv``, ``.tsv``, ``.txt``) with
any column names.
"""

from __future__ import annotations

import csv
import numbers
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ._errors import InputError, ShapeError
from ._ode import SIMULATION_TOLERANCES, initial_conditions_and_times, solve
from ._threads import adaptive_threads
from ._validation import as_tensor, states_and_times
from .systems import MisspecifiedSystem

__all__ = ["Trajectories", "simulate"]


@dataclass(frozen=True)
class Trajectories:
    """States of K experiments observed at T times.

    Attributes:
        times: ``(T,)`` shared by all experiments, or ``(K, T)`` one strictly increasing grid per experiment.
        states: ``(K, T, d)``.
    """

    times: torch.Tensor
    states: torch.Tensor

    def __post_init__(self) -> None:
        states, times = states_and_times(self.states, self.times)
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "times", times)

    # ----------------------------------------------------------------------------------------------------------
    @property
    def num_experiments(self) -> int:
        return self.states.shape[0]

    @property
    def num_times(self) -> int:
        return self.states.shape[1]

    @property
    def state_dim(self) -> int:
        return self.states.shape[2]

    @property
    def time_grid(self) -> torch.Tensor:
        """Times as ``(K, T)``, expanded when shared."""
        return self.times.expand(self.num_experiments, -1) if self.times.dim() == 1 else self.times

    @property
    def initial_conditions(self) -> torch.Tensor:
        """``(K, d)``."""
        return self.states[:, 0]

    def __len__(self) -> int:
        return self.num_experiments

    def __getitem__(self, index) -> Trajectories:
        """A subset of experiments (int, slice, index list or boolean mask)."""
        if isinstance(index, numbers.Integral) or (isinstance(index, torch.Tensor) and index.dim() == 0):
            index = [int(index)]
        times = self.times if self.times.dim() == 1 else self.times[index]
        return Trajectories(times, self.states[index])

    def to(self, *args, **kwargs) -> Trajectories:
        return Trajectories(self.times.to(*args, **kwargs), self.states.to(*args, **kwargs))

    def __repr__(self) -> str:
        times = self.times.detach()
        lo, hi = float(times[..., 0].min()), float(times[..., -1].max())
        grid = "shared grid" if times.dim() == 1 else "per-experiment grids"
        device = "" if self.states.device.type == "cpu" else f", {self.states.device}"
        return (
            f"Trajectories(K={self.num_experiments} experiment{'s' * (self.num_experiments != 1)}, "
            f"T={self.num_times} time{'s' * (self.num_times != 1)} on [{lo:.6g}, {hi:.6g}] ({grid}), "
            f"d={self.state_dim}, {str(self.states.dtype).removeprefix('torch.')}{device})"
        )

    # ----------------------------------------------------------------------------------------------------------
    def save(
        self,
        path: str | Path,
        *,
        time_column: str = "time",
        experiment_column: str = "experiment",
        state_columns: Sequence[str] | None = None,
    ) -> Path:
        """Write to ``path``: ``.npz`` (arrays times, states) or a text table with a header row.

        Text tables: ``.csv`` (comma separated), ``.tsv`` (tab separated) or ``.txt`` (space separated), one row
        per experiment and time, columns ``experiment_column, time_column, *state_columns`` (state columns
        ``y0, ..., y{d-1}`` by default; experiments numbered 0..K-1). Values are written with full precision, so
        :meth:`load` with the same column names (or the defaults) reads back the same times and states (as float64).
        The column names are ignored for ``.npz``.
        """
        path = Path(path)
        if path.suffix == ".npz":
            np.savez(path, times=self.times.detach().cpu().numpy(), states=self.states.detach().cpu().numpy())
            return path
        if path.suffix not in _TEXT_FORMATS:
            raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
        names = [f"y{i}" for i in range(self.state_dim)] if state_columns is None else list(state_columns)
        if len(names) != self.state_dim:
            raise ShapeError(f"state_columns: expected {self.state_dim} names (one per state component), got {names}")
        header = [experiment_column, time_column, *names]
        for name in header:
            if not isinstance(name, str) or not name.strip() or name != name.strip():
                raise InputError(f"column names: expected non-empty strings without surrounding spaces, got {name!r}")
            if path.suffix == ".txt" and len(name.split()) != 1:
                raise InputError(
                    f"column names: a .txt table is space separated, so names cannot hold spaces: {name!r}"
                )
        _check_distinct(header, "column names", str(path))
        grid = self.time_grid.detach().cpu().numpy()
        states = self.states.detach().cpu().numpy()
        with path.open("w", newline="", encoding="utf-8") as fh:
            if path.suffix == ".txt":
                fh.write(" ".join(header) + "\n")
                for k in range(self.num_experiments):
                    for j in range(self.num_times):
                        fh.write(" ".join([str(k), repr(float(grid[k, j]))] + [repr(float(v)) for v in states[k, j]]))
                        fh.write("\n")
            else:
                w = csv.writer(fh, delimiter=_TEXT_FORMATS[path.suffix])
                w.writerow(header)
                for k in range(self.num_experiments):
                    for j in range(self.num_times):
                        w.writerow([k, repr(float(grid[k, j]))] + [repr(float(v)) for v in states[k, j]])
        return path

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        time_column: str = "time",
        experiment_column: str | None = "experiment",
        state_columns: Sequence[str] | None = None,
    ) -> Trajectories:
        """Read trajectories from ``.npz`` (arrays ``times`` and ``states``) or a text table with a header row.

        Text tables are UTF-8 ``.csv`` (comma separated), ``.tsv`` (tab separated) or ``.txt`` (whitespace
        separated), one row per experiment and time, columns in any order and rows in any order.

        Args:
            path: the file.
            time_column: name of the time column.
            experiment_column: name of the column labelling the experiments (numbers, sorted numerically, or any
                text, in order of first appearance). When the file has no such column (or ``None``), all rows are
                one experiment; a name other than the default that is not in the file is an error.
            state_columns: names of the state columns, in the order of the state components (default: every
                other column, in file order).

        Each experiment's rows are sorted by time; every experiment must have the same number of rows (ragged
        data is not supported yet). The times come back shared ``(T,)`` when every experiment has the same grid,
        else ``(K, T)``. Column names are ignored for ``.npz``.

        Nothing is unpickled and no code can run. Raises :class:`InputError` for a missing, unreadable, non-UTF-8
        or malformed file, missing or duplicate columns, non-numeric cells or repeated (experiment, time) rows,
        and :class:`ShapeError` for rows of the wrong width or experiments with different numbers of rows, each
        naming what was expected and what the file holds.
        """
        path = Path(path)
        if path.suffix != ".npz" and path.suffix not in _TEXT_FORMATS:
            raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
        if not path.is_file():
            raise InputError(f"path: expected an existing file, got {str(path)!r}")
        if path.suffix == ".npz":
            try:
                with np.load(path, allow_pickle=False) as data:
                    missing = {"times", "states"} - set(data.files)
                    if missing:
                        raise InputError(f"{path}: expected arrays 'times' and 'states', missing {sorted(missing)}")
                    times, states = data["times"], data["states"]
            except InputError:
                raise
            except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
                raise InputError(
                    f"{path}: expected an .npz archive with numeric arrays 'times' and 'states' (no pickled objects), "
                    f"but it could not be read ({type(exc).__name__}: {str(exc)[:160]})"
                ) from exc
            return cls(as_tensor(times, f"{path}: times"), as_tensor(states, f"{path}: states"))
        header, body = _read_table(path)
        columns = dict(time_column=time_column, experiment_column=experiment_column, state_columns=state_columns)
        return cls(*_columns_to_arrays(path, header, body, **columns))


# ---------------------------------------------------------------------------------------------------------------
# Text tables
_TEXT_FORMATS = {".csv": ",", ".tsv": "\t", ".txt": None}  # the delimiter; None: any whitespace
_SUFFIXES = ".npz, .csv, .tsv or .txt"


def _check_distinct(names: Sequence[str], what: str, where: str) -> None:
    repeated = sorted({n for n in names if list(names).count(n) > 1})
    if repeated:
        raise InputError(f"{where}: expected distinct {what}, got {repeated} more than once (in {list(names)})")


def _read_table(path: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """The header and the non-blank data rows (with their line numbers) of a UTF-8 text table."""
    delimiter = _TEXT_FORMATS[path.suffix]
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:  # -sig: a byte-order mark (Excel) is dropped
            if delimiter is None:
                rows = [(i, line.split()) for i, line in enumerate(fh, start=1)]
            else:
                rows = [(reader.line_num, row) for reader in [csv.reader(fh, delimiter=delimiter)] for row in reader]
    except (UnicodeDecodeError, csv.Error, OSError) as exc:
        kind = {".csv": "CSV file", ".tsv": "TSV file (tab separated)", ".txt": "TXT file (whitespace separated)"}
        raise InputError(
            f"{path}: expected a UTF-8 text {kind[path.suffix]}, but it could not be read ({exc})"
        ) from exc
    rows = [(i, [cell.strip() for cell in row]) for i, row in rows if any(cell.strip() for cell in row)]
    if not rows:
        raise InputError(f"{path}: expected a header row naming the columns, got an empty file")
    header, body = rows[0][1], rows[1:]
    if not body:
        raise InputError(f"{path}: expected at least one data row after the header, got none")
    bad = next((r for r, (_, row) in enumerate(body) if len(row) != len(header)), None)
    if bad is not None:
        line, row = body[bad]
        raise ShapeError(
            f"{path}: expected {len(header)} columns in every row (as in the header), got {len(row)} in data row "
            f"{bad + 1} (line {line}; header {header})"
        )
    return header, body


def _columns_to_arrays(
    path: Path,
    header: list[str],
    body: list[tuple[int, list[str]]],
    *,
    time_column: str,
    experiment_column: str | None,
    state_columns: Sequence[str] | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``times (T,) or (K, T)`` and ``states (K, T, d)`` from the named columns of a table."""
    _check_distinct(header, "column names in the header", str(path))
    if not isinstance(time_column, str):
        raise InputError(f"time_column: expected a column name, got {type(time_column).__name__}")
    if experiment_column is not None and not isinstance(experiment_column, str):
        raise InputError(f"experiment_column: expected a column name or None, got {type(experiment_column).__name__}")
    if time_column not in header:
        raise InputError(f"{path}: expected a time column {time_column!r}, got columns {header}")
    if experiment_column is not None and experiment_column not in header:
        if experiment_column != "experiment":  # named by the caller: a typo must not merge all experiments
            raise InputError(f"{path}: expected an experiment column {experiment_column!r}, got columns {header}")
        experiment_column = None
    if experiment_column == time_column:
        raise InputError(f"experiment_column: expected a column other than the time column, got {time_column!r}")
    index_columns = [time_column] + ([experiment_column] if experiment_column is not None else [])
    if state_columns is None:
        names = [c for c in header if c not in index_columns]
    else:
        if isinstance(state_columns, str):
            raise InputError(f"state_columns: expected a list of column names, got the string {state_columns!r}")
        names = list(state_columns)
        _check_distinct(names, "state_columns", "state_columns")
        clash = [c for c in names if c in index_columns]
        if clash:
            raise InputError(f"state_columns: expected state columns, got the time / experiment column {clash}")
        missing = [c for c in names if c not in header]
        if missing:
            raise InputError(f"{path}: expected state columns {names}, missing {missing}; the file has {header}")
    if not names:
        raise InputError(f"{path}: expected at least one state column besides {index_columns}, got columns {header}")

    value_columns = [time_column, *names]
    where = [header.index(c) for c in value_columns]
    values = np.empty((len(body), len(value_columns)), dtype=np.float64)
    for r, (line, row) in enumerate(body):
        for c, col in enumerate(where):
            try:
                values[r, c] = float(row[col])
            except ValueError:
                raise InputError(
                    f"{path}: expected a number in column {header[col]!r} on line {line}, got {row[col]!r}"
                ) from None
            if not np.isfinite(values[r, c]):
                raise InputError(
                    f"{path}: expected a finite number in column {header[col]!r} on line {line}, got {row[col]!r}"
                )
    if experiment_column is None:
        labels = [""] * len(body)
        order = [""]
    else:
        labels = [row[header.index(experiment_column)] for _, row in body]
        try:  # numeric labels: 1 and 1.0 are the same experiment, sorted by value
            numbers = [float(label) for label in labels]
            if all(np.isfinite(numbers)):
                labels = [str(int(n)) if n == int(n) else repr(n) for n in numbers]
                order = sorted(dict.fromkeys(labels), key=float)
            else:
                order = list(dict.fromkeys(labels))
        except ValueError:
            order = list(dict.fromkeys(labels))  # text labels keep the order in which they first appear
    rows_of = {label: [] for label in order}
    for r, label in enumerate(labels):
        rows_of[label].append(r)
    counts = {label: len(rows) for label, rows in rows_of.items()}
    if len(set(counts.values())) != 1:
        by_count: dict[int, list[str]] = {}
        for label, n in counts.items():
            by_count.setdefault(n, []).append(label)
        detail = "; ".join(
            f"{n} row{'s' * (n != 1)} for experiment{'s' * (len(ids) > 1)} "
            f"{', '.join(ids[:5])}{' ...' * (len(ids) > 5)}"
            for n, ids in sorted(by_count.items())
        )
        raise ShapeError(
            f"{path}: expected the same number of rows for every experiment (ragged data is not supported yet), got "
            f"{detail}"
        )
    per = []
    for label in order:
        block = values[rows_of[label]]
        block = block[np.argsort(block[:, 0], kind="stable")]
        repeated = np.flatnonzero(np.diff(block[:, 0]) == 0)
        if repeated.size:
            what = "" if experiment_column is None else f" for experiment {label!r}"
            raise InputError(
                f"{path}: expected one row per experiment and time, got time {float(block[repeated[0], 0])!r} "
                f"more than once{what}"
            )
        per.append(block)
    times = np.stack([p[:, 0] for p in per])
    states = np.stack([p[:, 1:] for p in per])
    if np.all(times == times[:1]):
        times = times[0]
    return torch.from_numpy(times), torch.from_numpy(states)


@adaptive_threads()
def simulate(
    system: MisspecifiedSystem,
    y0,
    times,
    *,
    known_only: bool = False,
    method: str = "dopri5",
    rtol: float = SIMULATION_TOLERANCES[0],
    atol: float = SIMULATION_TOLERANCES[1],
    max_steps: int | None = None,
) -> Trajectories:
    """Integrate the true dynamics G + F from every initial condition in one batched solve.

    Args:
        system: the system; for one without a true correction the known model G alone is integrated.
        y0: initial conditions ``(K, d)`` (or ``(d,)`` for one), the states at ``times[..., 0]``.
        times: ``(T,)`` shared, or ``(K, T)`` per experiment; strictly increasing.
        known_only: integrate the misspecified model G alone (the proxy / baseline trajectories).
        method: torchdiffeq method (dopri5 by default).
        rtol: relative tolerance (the package's simulation tolerance by default, see :mod:`torchmisspec._ode`:
            this is the ground truth).
        atol: absolute tolerance (likewise).
        max_steps: most solver steps (default 10,000); beyond it :class:`IntegrationError` names the initial
            conditions that stalled the solve.

    Returns:
        :class:`Trajectories` with ``states (K, T, d)``.
    """
    y0, times = initial_conditions_and_times(y0, times, system.state_dim, system.check_states)
    field = system.known_rhs if known_only else system.true_rhs
    with torch.no_grad():
        states, _ = solve(
            field, y0, times, method=method, rtol=rtol, atol=atol, max_steps=max_steps, what=f"simulate({system.name})"
        )
    return Trajectories(times, states)
