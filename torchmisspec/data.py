"""Trajectories: observed or simulated states of K experiments, and :func:`simulate`.

``Trajectories(times, states)`` holds ``states (K, T, d)`` sampled at ``times (T,)`` shared by all experiments or
``(K, T)`` one grid per experiment (irregular spacing allowed, strictly increasing along each row), or experiments
of different lengths given as lists of per-experiment arrays (ragged data). It wraps user
data as well as simulations and saves to / loads from ``.npz`` and text tables (``.csv``, ``.tsv``, ``.txt``) with
any column names. Missing entries (an empty cell, or NaN in arrays) are kept as NaN with a mask,
:attr:`Trajectories.observed`; infinite values are refused.
"""

from __future__ import annotations

import csv
import math
import numbers
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ._errors import InputError, IntegrationError, ShapeError
from ._missing import fill
from ._ode import SIMULATION_TOLERANCES, initial_conditions_and_times, solve
from ._threads import adaptive_threads
from ._validation import as_tensor, states_and_times
from .systems import MisspecifiedSystem

__all__ = ["Trajectories", "simulate"]


@dataclass(frozen=True)
class Trajectories:
    """States of K experiments, each observed at its own times.

    ``Trajectories(times, states)`` takes either tensors (arrays) for experiments of equal length, or lists with one
    array per experiment (*ragged* data: experiments of different lengths):

    * equal lengths: ``states (K, T, d)`` and ``times (T,)`` shared by all experiments or ``(K, T)`` one grid per
      experiment (irregular spacing allowed, strictly increasing along each row);
    * lists: ``states = [y_1 (T_1, d), ..., y_K (T_K, d)]`` and ``times = [t_1 (T_1,), ..., t_K (T_K,)]`` (or one
      shared ``(T,)`` array when the lengths agree). When every ``T_k`` is the same the lists are stacked into the
      equal-length form; otherwise the object is ragged: :attr:`is_ragged` is true, :attr:`times` and
      :attr:`states` are tuples of per-experiment tensors, :attr:`lengths` gives every ``T_k`` and
      :attr:`num_times` / :attr:`time_grid` raise :class:`~torchmisspec.ShapeError` (use :meth:`experiments` or
      :meth:`padded`). Everything in the package that takes trajectories accepts ragged ones.

    **Missing values.** A NaN state entry is a component that was not observed at that time (an empty cell of a
    table read by :meth:`load`); :attr:`observed` is the mask of the others. Every experiment must observe every
    component at least once (else :class:`~torchmisspec.InputError`), times can never be missing, and infinite
    values are refused. A time at which no component was observed carries no data and is dropped (so masking a whole
    row is the same as deleting it; the experiment may then become shorter than the others, i.e. ragged). The
    package's functions use only observed entries: the derivative estimators fit each component from its own
    observed times, :func:`~torchmisspec.correction_samples` fills what a sample's G(y) and inputs need from the
    estimator's fit, and the comparisons with the data (cross-validation, :func:`~torchmisspec.fit_trajectories`,
    band calibration) skip missing entries. :meth:`filled` and :attr:`initial_conditions` estimate missing entries.

    Attributes:
        times: ``(T,)``, ``(K, T)``, or a tuple of K ``(T_k,)`` tensors (ragged).
        states: ``(K, T, d)``, or a tuple of K ``(T_k, d)`` tensors (ragged); NaN where an entry is missing.
        state_names: the names of the d state components (the table's column names for :meth:`load`; default
            ``y0, ..., y{d-1}``); kept by indexing, :meth:`to`, :meth:`save` and :meth:`load`.
    """

    times: torch.Tensor | tuple[torch.Tensor, ...]
    states: torch.Tensor | tuple[torch.Tensor, ...]
    state_names: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.states, (list, tuple)):
            states, times = _per_experiment(self.states, self.times)
        else:
            if isinstance(self.times, (list, tuple)) and self.times and not _is_number(self.times[0]):
                raise InputError(
                    "times: a list of per-experiment time arrays needs a list of per-experiment state arrays, got "
                    f"states as one {type(self.states).__name__}"
                )
            states, times = states_and_times(self.states, self.times, missing=True)
        d = states[0].shape[-1]
        names = _check_state_names(self.state_names, d)
        states, times = _drop_empty_rows(states, times, names)
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "state_names", names)

    # ----------------------------------------------------------------------------------------------------------
    @property
    def is_ragged(self) -> bool:
        """Whether the experiments have different numbers of samples (then times and states are tuples)."""
        return isinstance(self.states, tuple)

    @property
    def lengths(self) -> tuple[int, ...]:
        """``(T_1, ..., T_K)``: the number of samples of every experiment."""
        if self.is_ragged:
            return tuple(s.shape[0] for s in self.states)
        return (self.states.shape[1],) * self.states.shape[0]

    @property
    def num_experiments(self) -> int:
        return len(self.states) if self.is_ragged else self.states.shape[0]

    @property
    def num_samples(self) -> int:
        """Total number of observed states, ``sum_k T_k``."""
        return sum(self.lengths)

    @property
    def num_times(self) -> int:
        """T, the number of samples of every experiment (ragged data has none: see :attr:`lengths`)."""
        if self.is_ragged:
            raise ShapeError(
                f"num_times: expected experiments of equal length, got ragged data with lengths "
                f"{_describe_lengths(self.lengths)}; use .lengths"
            )
        return self.states.shape[1]

    @property
    def state_dim(self) -> int:
        return self.states[0].shape[-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.states[0].dtype

    @property
    def device(self) -> torch.device:
        return self.states[0].device

    @property
    def time_grid(self) -> torch.Tensor:
        """Times as ``(K, T)``, expanded when shared (equal-length data only; see :meth:`padded`)."""
        if self.is_ragged:
            raise ShapeError(
                f"time_grid: expected experiments of equal length, got ragged data with lengths "
                f"{_describe_lengths(self.lengths)}; use .experiments() or .padded()"
            )
        return self.times.expand(self.num_experiments, -1) if self.times.dim() == 1 else self.times

    @property
    def observed(self) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """Boolean mask of the observed entries: ``(K, T, d)``, or a tuple of ``(T_k, d)`` (ragged)."""
        if self.is_ragged:
            return tuple(torch.isfinite(s) for s in self.states)
        return torch.isfinite(self.states)

    @property
    def num_missing(self) -> int:
        """The number of missing state entries (NaN)."""
        if self.is_ragged:
            return sum(int(torch.isnan(s).sum()) for s in self.states)
        return int(torch.isnan(self.states).sum())

    @property
    def has_missing(self) -> bool:
        """Whether some state entry is missing."""
        return self.num_missing > 0

    def filled(self) -> Trajectories:
        """These trajectories with every missing entry estimated from its component's own observed samples: the
        value at that time of a local quadratic least-squares fit through the 5 nearest (a local Savitzky-Golay
        smoother; fewer samples: their interpolant). Observed entries are unchanged; ``self`` when nothing is
        missing."""
        if not self.has_missing:
            return self
        times, states, mask = self.padded()
        out = fill(states, times, torch.isfinite(states) & mask.unsqueeze(-1))
        if not self.is_ragged:
            return Trajectories(self.times, out, state_names=self.state_names)
        rows = [out[k, :n] for k, n in enumerate(self.lengths)]
        return Trajectories(list(self.times), rows, state_names=self.state_names)

    @property
    def initial_conditions(self) -> torch.Tensor:
        """``(K, d)``: every experiment's first observed state (missing entries estimated as by :meth:`filled`)."""
        source = self.filled() if self.has_missing else self
        if source.is_ragged:
            return torch.stack([s[0] for s in source.states])
        return source.states[:, 0]

    def experiments(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``[(t_k (T_k,), y_k (T_k, d)), ...]``: every experiment's times and states."""
        if self.is_ragged:
            return list(zip(self.times, self.states, strict=True))
        grid = self.time_grid
        return [(grid[k], self.states[k]) for k in range(self.num_experiments)]

    def flat_states(self) -> torch.Tensor:
        """``(N, d)``: all observed states, experiment after experiment (N = sum of the lengths; NaN where missing)."""
        if self.is_ragged:
            return torch.cat(self.states)
        return self.states.reshape(-1, self.state_dim)

    def padded(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(times (K, T_max), states (K, T_max, d), mask (K, T_max))``, each experiment padded at its end.

        Padded entries repeat the experiment's last time and state; ``mask`` is true on the observed samples (rows:
        missing entries inside them stay NaN, see :attr:`observed`).
        """
        if not self.is_ragged:
            mask = torch.ones(self.states.shape[:2], dtype=torch.bool, device=self.device)
            return self.time_grid, self.states, mask
        T = max(self.lengths)
        times = torch.stack([torch.cat([t, t[-1:].expand(T - len(t))]) for t in self.times])
        states = torch.stack([torch.cat([s, s[-1:].expand(T - len(s), -1)]) for s in self.states])
        lengths = torch.tensor(self.lengths, device=self.device)
        mask = torch.arange(T, device=self.device) < lengths.unsqueeze(-1)
        return times, states, mask

    def by_length(self) -> list[tuple[list[int], Trajectories]]:
        """The experiments grouped by length: ``[(indices, equal-length Trajectories), ...]``, shortest first."""
        if not self.is_ragged:
            return [(list(range(self.num_experiments)), self)]
        groups: dict[int, list[int]] = {}
        for k, n in enumerate(self.lengths):
            groups.setdefault(n, []).append(k)
        return [
            (
                idx,
                Trajectories(
                    torch.stack([self.times[k] for k in idx]),
                    torch.stack([self.states[k] for k in idx]),
                    state_names=self.state_names,
                ),
            )
            for _, idx in sorted(groups.items())
        ]

    def __len__(self) -> int:
        return self.num_experiments

    def __getitem__(self, index) -> Trajectories:
        """A subset of experiments (int, slice, index list or boolean mask)."""
        if isinstance(index, numbers.Integral) or (isinstance(index, torch.Tensor) and index.dim() == 0):
            index = [int(index)]
        if self.is_ragged:
            picked = torch.arange(self.num_experiments)[index].tolist()
            return Trajectories(
                [self.times[k] for k in picked], [self.states[k] for k in picked], state_names=self.state_names
            )
        times = self.times if self.times.dim() == 1 else self.times[index]
        return Trajectories(times, self.states[index], state_names=self.state_names)

    def to(self, *args, **kwargs) -> Trajectories:
        if self.is_ragged:
            return Trajectories(
                [t.to(*args, **kwargs) for t in self.times],
                [s.to(*args, **kwargs) for s in self.states],
                state_names=self.state_names,
            )
        return Trajectories(
            self.times.to(*args, **kwargs), self.states.to(*args, **kwargs), state_names=self.state_names
        )

    def __repr__(self) -> str:
        if self.is_ragged:
            lo = min(float(t[0]) for t in self.times)
            hi = max(float(t[-1]) for t in self.times)
            count, grid = f"T={_describe_lengths(self.lengths)} times", "ragged"
        else:
            times = self.times.detach()
            lo, hi = float(times[..., 0].min()), float(times[..., -1].max())
            grid = "shared grid" if times.dim() == 1 else "per-experiment grids"
            count = f"T={self.num_times} time{'s' * (self.num_times != 1)}"
        device = "" if self.device.type == "cpu" else f", {self.device}"
        names = "" if self.state_names == _default_names(self.state_dim) else f" ({', '.join(self.state_names)})"
        missing = self.num_missing
        gaps = f", {missing} missing entr{'y' if missing == 1 else 'ies'}" if missing else ""
        return (
            f"Trajectories(K={self.num_experiments} experiment{'s' * (self.num_experiments != 1)}, "
            f"{count} on [{lo:.6g}, {hi:.6g}] ({grid}), "
            f"d={self.state_dim}{names}{gaps}, {str(self.dtype).removeprefix('torch.')}{device})"
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
        """Write to ``path``: ``.npz`` (arrays times, states, state_names) or a text table with a header row.

        Text tables: ``.csv`` (comma separated), ``.tsv`` (tab separated) or ``.txt`` (space separated), one row
        per experiment and time, columns ``experiment_column, time_column, *state_columns`` (state columns
        :attr:`state_names` by default; experiments numbered 0..K-1). Values are written with full precision, so
        :meth:`load` with the same column names (or the defaults) reads back the same times and states (as float64).
        A missing entry is written as an empty cell (``NaN`` in a ``.txt`` table, whose cells are separated by
        spaces). The column names are ignored for ``.npz``, which stores :attr:`state_names` as an array of strings.
        """
        path = Path(path)
        if path.suffix == ".npz":
            names = np.asarray(self.state_names, dtype=np.str_)
            if self.is_ragged:  # no object arrays (they would need pickle): concatenated, with the lengths
                np.savez(
                    path,
                    times=torch.cat(self.times).detach().cpu().numpy(),
                    states=self.flat_states().detach().cpu().numpy(),
                    lengths=np.asarray(self.lengths, dtype=np.int64),
                    state_names=names,
                )
            else:
                np.savez(
                    path,
                    times=self.times.detach().cpu().numpy(),
                    states=self.states.detach().cpu().numpy(),
                    state_names=names,
                )
            return path
        if path.suffix not in _TEXT_FORMATS:
            raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
        names = list(self.state_names) if state_columns is None else list(state_columns)
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
        gap = "NaN" if path.suffix == ".txt" else ""
        rows = (
            [str(k), repr(float(t_j))] + [gap if v != v else repr(float(v)) for v in y_j]
            for k, (t, y) in enumerate(self.experiments())
            for t_j, y_j in zip(t.detach().cpu().tolist(), y.detach().cpu().tolist(), strict=True)
        )
        with path.open("w", newline="", encoding="utf-8") as fh:
            if path.suffix == ".txt":
                fh.write(" ".join(header) + "\n")
                for row in rows:
                    fh.write(" ".join(row) + "\n")
            else:
                w = csv.writer(fh, delimiter=_TEXT_FORMATS[path.suffix])
                w.writerow(header)
                w.writerows(rows)
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
                other column, in file order). They become :attr:`state_names`.

        A state cell that is empty or reads ``NaN``, ``NA`` or ``N/A`` (any case) is a missing entry (see the class
        docstring); a missing time or experiment label is an error, and so is an experiment with no value at all in
        some state column. Each experiment's rows are sorted by time. The times come back shared ``(T,)`` when every
        experiment has the same grid, ``(K, T)`` when the experiments have equal lengths, and ragged (one tensor per
        experiment) when their lengths differ. Column names are ignored for ``.npz`` (ragged ``.npz`` files, as
        :meth:`save` writes them, hold the concatenated ``times (N,)``, ``states (N, d)`` and ``lengths (K,)``).

        Nothing is unpickled and no code can run. Raises :class:`InputError` for a missing, unreadable, non-UTF-8
        or malformed file, missing or duplicate columns, non-numeric or infinite cells, missing times or labels, or
        repeated (experiment, time) rows,
        and :class:`ShapeError` for rows of the wrong width, each naming what was expected and what the file holds.
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
                    lengths = data["lengths"] if "lengths" in data.files else None
                    names = data["state_names"] if "state_names" in data.files else None
            except InputError:
                raise
            except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
                raise InputError(
                    f"{path}: expected an .npz archive with numeric arrays 'times' and 'states' (no pickled objects), "
                    f"but it could not be read ({type(exc).__name__}: {str(exc)[:160]})"
                ) from exc
            if names is not None:
                if names.dtype.kind != "U" or names.ndim != 1:
                    raise InputError(f"{path}: expected 'state_names' to be a 1-D array of strings, got {names!r:.80}")
                names = names.tolist()
            if lengths is not None:
                return cls(*_split_ragged(path, times, states, lengths), state_names=names)
            return cls(as_tensor(times, f"{path}: times"), as_tensor(states, f"{path}: states"), state_names=names)
        header, body = _read_table(path)
        columns = dict(time_column=time_column, experiment_column=experiment_column, state_columns=state_columns)
        times, states, names = _columns_to_arrays(path, header, body, **columns)
        return cls(times, states, state_names=names)


# ---------------------------------------------------------------------------------------------------------------
# Per-experiment (possibly ragged) input
def _is_number(x) -> bool:
    return isinstance(x, numbers.Number) or (isinstance(x, (torch.Tensor, np.ndarray)) and x.ndim == 0)


def _describe_lengths(lengths: Sequence[int]) -> str:
    lo, hi = min(lengths), max(lengths)
    return f"{lo}" if lo == hi else f"{lo}..{hi}"


def _default_names(d: int) -> tuple[str, ...]:
    return tuple(f"y{i}" for i in range(d))


def _check_state_names(names, d: int) -> tuple[str, ...]:
    """``d`` distinct non-empty strings (default ``y0..y{d-1}``)."""
    if names is None:
        return _default_names(d)
    if isinstance(names, str) or not isinstance(names, Sequence):
        raise InputError(f"state_names: expected a list of {d} names (one per state component), got {names!r:.80}")
    names = tuple(names)
    if len(names) != d or not all(isinstance(n, str) and n.strip() for n in names):
        raise ShapeError(
            f"state_names: expected {d} non-empty strings (one per state component), got {list(names)!r:.200}"
        )
    _check_distinct(names, "state_names", "state_names")
    return names


def _drop_empty_rows(states, times, names):
    """Check that every experiment observes every component, and drop the times at which nothing was observed."""
    per = list(states) if isinstance(states, tuple) else list(states.unbind(0))
    for k, y in enumerate(per):
        never = (~torch.isfinite(y)).all(0).nonzero().flatten().tolist()
        if never:
            what = ", ".join(f"{j} ({names[j]!r})" for j in never)
            raise InputError(
                f"states: expected at least one observed value of every state component in every experiment, got "
                f"none of component{'s' * (len(never) > 1)} {what} in experiment {k} (all {y.shape[0]} entries "
                "missing); drop that experiment, or that component from the data and the system"
            )
    empty = [torch.isnan(y).all(-1) for y in per]
    if not any(bool(e.any()) for e in empty):
        return states, times
    if isinstance(times, tuple):
        grids = list(times)
    else:
        grids = list(times.expand(len(per), -1).unbind(0)) if times.dim() == 1 else list(times.unbind(0))
    kept_t = [t[~e] for t, e in zip(grids, empty, strict=True)]
    kept_y = [y[~e] for y, e in zip(per, empty, strict=True)]
    if len({len(t) for t in kept_t}) == 1:
        stacked_t = torch.stack(kept_t)
        shared = bool((stacked_t == stacked_t[:1]).all())
        return torch.stack(kept_y), stacked_t[0] if shared and not isinstance(times, tuple) else stacked_t
    return tuple(kept_y), tuple(kept_t)


def _per_experiment(states_list, times) -> tuple:
    """Validate lists of per-experiment states (and times): stacked tensors when the lengths agree, else tuples."""
    K = len(states_list)
    if K == 0:
        raise ShapeError("states: expected at least one experiment, got an empty list")
    states = []
    for k, y in enumerate(states_list):
        y = as_tensor(y, f"states[{k}]")
        if y.dim() != 2:
            raise ShapeError(f"states[{k}]: expected a (T_k, d) array for experiment {k}, got shape {tuple(y.shape)}")
        states.append(y)
    dims = {y.shape[-1] for y in states}
    if len(dims) != 1 and len({y.shape[0] for y in states}) == 1:
        raise ShapeError(
            f"states: expected (T_k, d) arrays with the same d in every experiment, got shapes "
            f"{[tuple(y.shape) for y in states][:6]}: the arrays look transposed, (d, T_k) instead of (T_k, d) (one "
            "row per time, one column per state component); pass [y.T for y in states]"
        )
    if len(dims) != 1:
        raise ShapeError(
            f"states: expected the same state dimension d in every experiment, got {[y.shape[-1] for y in states]}"
        )
    devices = {y.device for y in states}
    if len(devices) != 1:
        raise InputError(f"states: expected every experiment on one device, got {sorted(map(str, devices))}")
    dtype = states[0].dtype
    for y in states[1:]:
        dtype = torch.promote_types(dtype, y.dtype)
    states = [y.to(dtype) for y in states]
    lengths = [y.shape[0] for y in states]
    per_times = isinstance(times, (list, tuple)) and len(times) > 0 and not _is_number(times[0])
    if per_times:
        if len(times) != K:
            raise ShapeError(f"times: expected {K} time arrays (one per experiment in states), got {len(times)}")
        checked = [
            states_and_times(y.unsqueeze(0), t, states_name=f"states[{k}]", times_name=f"times[{k}]", missing=True)
            for k, (y, t) in enumerate(zip(states, times, strict=True))
        ]
        times_list = [t.reshape(-1) for _, t in checked]
    else:
        shared = as_tensor(times, "times", dtype=dtype, device=states[0].device)
        if shared.dim() != 1:
            raise ShapeError(
                "times: with a list of per-experiment states, expected one (T,) array shared by all or a list of "
                f"(T_k,) arrays, got shape {tuple(shared.shape)}"
            )
        if len(set(lengths)) != 1:
            raise ShapeError(
                f"times: one shared (T,) array needs experiments of equal length, got lengths {lengths}; pass a "
                "list with one time array per experiment"
            )
        stacked, shared = states_and_times(torch.stack(states), shared, missing=True)
        return stacked, shared
    if len(set(lengths)) == 1:
        return torch.stack(states), torch.stack(times_list)
    return tuple(states), tuple(times_list)


# ---------------------------------------------------------------------------------------------------------------
# Text tables
_TEXT_FORMATS = {".csv": ",", ".tsv": "\t", ".txt": None}  # the delimiter; None: any whitespace
_SUFFIXES = ".npz, .csv, .tsv or .txt"


def _check_distinct(names: Sequence[str], what: str, where: str) -> None:
    repeated = sorted({n for n in names if list(names).count(n) > 1})
    if repeated:
        raise InputError(f"{where}: expected distinct {what}, got {repeated} more than once (in {list(names)})")


#: Cells read as a missing state value (lower case): empty, NaN, NA, N/A.
_MISSING = ("", "nan", "na", "n/a")


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
) -> tuple:
    """``times (T,) or (K, T)``, ``states (K, T, d)`` (NaN where a cell is missing) and the state names from the named
    columns of a table (lists of per-experiment arrays when the experiments' lengths differ)."""
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
            cell = row[col]
            if cell.lower() in _MISSING:
                value = math.nan
            else:
                try:
                    value = float(cell)
                except ValueError:
                    label = c > 0 and state_columns is None and experiment_column is None
                    raise InputError(
                        f"{path}: expected a number in column {header[col]!r} on line {line}, got {cell!r}"
                        + (" (a missing value is an empty cell, NaN or NA)" if c > 0 else "")
                        + (
                            f"; if {header[col]!r} labels the experiments, name it with experiment_column="
                            f"{header[col]!r} (--experiment-column {header[col]} on the command line)"
                            if label
                            else ""
                        )
                    ) from None
            if c == 0 and not math.isfinite(value):
                raise InputError(
                    f"{path}: expected a finite time in column {header[col]!r} on line {line}, got {cell!r} (times "
                    "cannot be missing: drop the row, or fill in its time)"
                )
            if math.isinf(value):
                raise InputError(
                    f"{path}: expected a finite number in column {header[col]!r} on line {line}, got {cell!r} "
                    "(an empty cell, NaN or NA is a missing value; infinite values are refused)"
                )
            values[r, c] = value
    if experiment_column is None:
        labels = [""] * len(body)
        order = [""]
    else:
        labels = [row[header.index(experiment_column)] for _, row in body]
        blank = next((line for (line, _), label in zip(body, labels, strict=True) if not label), None)
        if blank is not None:
            raise InputError(
                f"{path}: expected an experiment label in column {experiment_column!r} on line {blank}, got an empty "
                "cell"
            )
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
    per = []
    for label in order:
        block = values[rows_of[label]]
        block = block[np.argsort(block[:, 0], kind="stable")]
        repeated = np.flatnonzero(np.diff(block[:, 0]) == 0)
        if repeated.size:
            what = "" if experiment_column is None else f" for experiment {label!r}"
            if experiment_column is None:  # several experiments with no label column found: say how to name it
                others = [c for c in header if c not in value_columns]
                what = " (no column 'experiment' labels the experiments: name yours with experiment_column=" + (
                    f"{others[0]!r}, --experiment-column {others[0]} on the command line)" if others else "...)"
                )
            raise InputError(
                f"{path}: expected one row per experiment and time, got time {float(block[repeated[0], 0])!r} "
                f"more than once{what}"
            )
        per.append(block)
    if len({len(p) for p in per}) > 1:  # ragged: one array per experiment
        times_list = [torch.from_numpy(p[:, 0].copy()) for p in per]
        return times_list, [torch.from_numpy(p[:, 1:].copy()) for p in per], names
    times = np.stack([p[:, 0] for p in per])
    states = np.stack([p[:, 1:] for p in per])
    if np.all(times == times[:1]):
        times = times[0]
    return torch.from_numpy(times), torch.from_numpy(states), names


def _split_ragged(path: Path, times: np.ndarray, states: np.ndarray, lengths: np.ndarray) -> tuple[list, list]:
    """Per-experiment lists from a ragged ``.npz`` (concatenated times and states plus the lengths)."""
    lengths = np.asarray(lengths)
    if lengths.dtype.kind not in "iu" or lengths.ndim != 1 or lengths.size == 0 or (lengths < 1).any():
        raise InputError(f"{path}: expected 'lengths' to be a 1-D array of positive integers, got {lengths!r:.80}")
    if times.ndim != 1 or states.ndim != 2 or len(times) != len(states) or len(times) != int(lengths.sum()):
        raise ShapeError(
            f"{path}: expected ragged arrays times (N,) and states (N, d) with N = sum(lengths) = "
            f"{int(lengths.sum())}, got times {times.shape} and states {states.shape}"
        )
    cuts = np.cumsum(lengths)[:-1]
    times_list = [as_tensor(t, f"{path}: times") for t in np.split(times, cuts)]
    states_list = [as_tensor(y, f"{path}: states") for y in np.split(states, cuts)]
    return times_list, states_list


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
        times: ``(T,)`` shared, ``(K, T)`` per experiment, or a list of K ``(T_k,)`` arrays of different lengths
            (ragged: one batched solve per distinct length); strictly increasing.
        known_only: integrate the misspecified model G alone (the proxy / baseline trajectories).
        method: torchdiffeq method (dopri5 by default).
        rtol: relative tolerance (the package's simulation tolerance by default, see :mod:`torchmisspec._ode`:
            this is the ground truth).
        atol: absolute tolerance (likewise).
        max_steps: most solver steps (default 10,000); beyond it :class:`IntegrationError` names the initial
            conditions that stalled the solve.

    Returns:
        :class:`Trajectories` with ``states (K, T, d)`` (ragged for ragged times).
    """
    if isinstance(times, (list, tuple)) and len(times) > 0 and not _is_number(times[0]):
        y0 = as_tensor(y0, "y0")
        y0 = y0.unsqueeze(0) if y0.dim() == 1 else y0
        if y0.dim() != 2 or y0.shape[0] != len(times):
            raise ShapeError(
                f"y0: expected ({len(times)}, {system.state_dim}) initial conditions, one per time array, got shape "
                f"{tuple(y0.shape)}"
            )
        grids = [as_tensor(t, f"times[{k}]", dtype=y0.dtype, device=y0.device) for k, t in enumerate(times)]
        if any(t.dim() != 1 for t in grids):
            shapes = [tuple(t.shape) for t in grids]
            raise ShapeError(f"times: expected a list of 1-D (T_k,) arrays, got shapes {shapes}")
        if len({len(t) for t in grids}) == 1:
            times = torch.stack(grids)
        else:
            options = dict(known_only=known_only, method=method, rtol=rtol, atol=atol, max_steps=max_steps)
            groups: dict[int, list[int]] = {}
            for k, t in enumerate(grids):
                groups.setdefault(len(t), []).append(k)
            states: list = [None] * len(grids)
            for idx in groups.values():
                part = simulate(system, y0[idx], torch.stack([grids[k] for k in idx]), **options)
                for i, k in enumerate(idx):
                    states[k] = part.states[i]
            return Trajectories(grids, states)
    y0, times = initial_conditions_and_times(y0, times, system.state_dim, system.check_states)
    field = system.known_rhs if known_only else system.true_rhs
    with torch.no_grad():
        states, _ = solve(
            field, y0, times, method=method, rtol=rtol, atol=atol, max_steps=max_steps, what=f"simulate({system.name})"
        )
    return Trajectories(times, states)


def simulate_known_each(system: MisspecifiedSystem, trajectories: Trajectories, **options) -> list[torch.Tensor | None]:
    """The known model G alone from each experiment's first observed state over its own times, one experiment at a
    time: ``(T_k, d)`` states, or ``None`` where G cannot be integrated (:class:`IntegrationError`). For when a
    batched ``simulate(..., known_only=True)`` failed: G may diverge where the true system does not, which is what a
    correction may exist to fix. ``options``: as for :func:`simulate`."""
    out: list[torch.Tensor | None] = []
    first = trajectories.initial_conditions  # missing entries estimated
    for k, (times, _) in enumerate(trajectories.experiments()):
        try:
            out.append(simulate(system, first[k : k + 1], times, known_only=True, **options).states[0])
        except IntegrationError:
            out.append(None)
    return out
