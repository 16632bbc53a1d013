"""Trajectories on disk: ``.npz`` archives and text tables (``.csv``, ``.tsv``, ``.txt``), written by
:meth:`Trajectories.save <torchmisspec.data.Trajectories.save>` and read by
:meth:`Trajectories.load <torchmisspec.data.Trajectories.load>`."""

from __future__ import annotations

import csv
import math
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from .._errors import InputError, ShapeError
from .._validation import as_tensor, check_path, unreadable
from ._input import _check_distinct
from ._readout import Readout

_TEXT_FORMATS = {".csv": ",", ".tsv": "\t", ".txt": None}  # the delimiter; None: any whitespace
_SUFFIXES = ".npz, .csv, .tsv or .txt"

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
            f"{path}: expected a UTF-8 text {kind[path.suffix]}, got a file that could not be read as one ({exc})"
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
    control_columns: Sequence[str] | None = None,
) -> tuple:
    """``times (T,) or (K, T)``, ``states (K, T, d)`` (NaN where a cell is missing), the state names and the controls
    ``(knots, values, names)`` (``None`` without control columns) from the named columns of a table (lists of
    per-experiment arrays when the experiments' lengths differ). A control is known at every row: an empty control
    cell is an error."""
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
    controls = []
    if control_columns is not None:
        if isinstance(control_columns, str):
            raise InputError(f"control_columns: expected a list of column names, got the string {control_columns!r}")
        controls = list(control_columns)
        _check_distinct(controls, "control_columns", "control_columns")
        absent = [c for c in controls if c not in header]
        if absent:
            raise InputError(f"{path}: expected control columns {controls}, got columns {header} (missing {absent})")
        clash = [c for c in controls if c in index_columns or (state_columns is not None and c in state_columns)]
        if clash:
            raise InputError(
                f"control_columns: expected columns other than the time, experiment and states, got {clash}"
            )
        index_columns = index_columns + controls
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
            raise InputError(f"{path}: expected state columns {names}, got columns {header} (missing {missing})")
    if not names:
        raise InputError(f"{path}: expected at least one state column besides {index_columns}, got columns {header}")

    value_columns = [time_column, *names, *controls]
    where = [header.index(c) for c in value_columns]
    first_control = 1 + len(names)
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
            if c >= first_control and not math.isfinite(value):
                raise InputError(
                    f"{path}: expected a value of the control {header[col]!r} on line {line}, got {cell!r} (a control "
                    "is known at every row: fill it in, e.g. repeat the last value of a piecewise-constant input)"
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
    control = None
    if controls:
        knots = [torch.from_numpy(p[:, 0].copy()) for p in per]
        control = (knots, [torch.from_numpy(p[:, first_control:].copy()) for p in per], controls)
    if len({len(p) for p in per}) > 1:  # ragged: one array per experiment
        times_list = [torch.from_numpy(p[:, 0].copy()) for p in per]
        return times_list, [torch.from_numpy(p[:, 1:first_control].copy()) for p in per], names, control
    times = np.stack([p[:, 0] for p in per])
    states = np.stack([p[:, 1:first_control] for p in per])
    if np.all(times == times[:1]):
        times = times[0]
    return torch.from_numpy(times), torch.from_numpy(states), names, control


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


def write(
    trajectories,
    path: str | Path,
    *,
    time_column: str,
    experiment_column: str,
    state_columns: Sequence[str] | None,
) -> Path:
    """What :meth:`Trajectories.save <torchmisspec.data.Trajectories.save>` does (see there)."""
    path = Path(check_path(path))
    readout = trajectories.readout
    if path.suffix == ".npz":
        names = np.asarray(trajectories.state_names, dtype=np.str_)
        # the dtype is recorded and restored by read (bfloat16, which numpy lacks, is stored exactly as float32)
        extra = {"dtype": np.asarray(str(trajectories.dtype).removeprefix("torch."))}
        if readout is not None:  # the readout's weights and names, and its values laid out as the states
            readings = trajectories.readings
            readings = torch.cat(readings) if trajectories.is_ragged else readings
            extra.update(
                readout_matrix=_numpy(readout.matrix),
                readout_names=np.asarray(readout.names, dtype=np.str_),
                readings=_numpy(readings),
            )
        if trajectories.is_ragged:  # no object arrays (they would need pickle): concatenated, with the lengths
            np.savez(
                path,
                times=_numpy(torch.cat(trajectories.times)),
                states=_numpy(trajectories.flat_states()),
                lengths=np.asarray(trajectories.lengths, dtype=np.int64),
                state_names=names,
                **extra,
            )
        else:
            np.savez(
                path,
                times=_numpy(trajectories.times),
                states=_numpy(trajectories.states),
                state_names=names,
                **extra,
            )
        return path
    if path.suffix not in _TEXT_FORMATS:
        raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
    names = list(trajectories.state_names) if state_columns is None else list(state_columns)
    if len(names) != trajectories.state_dim:
        raise ShapeError(
            f"state_columns: expected {trajectories.state_dim} names (one per state component), got {names}"
        )
    header = [experiment_column, time_column, *names, *([] if readout is None else readout.names)]
    for name in header:
        if not isinstance(name, str) or not name.strip() or name != name.strip():
            raise InputError(f"column names: expected non-empty strings without surrounding spaces, got {name!r}")
        if path.suffix == ".txt" and len(name.split()) != 1:
            raise InputError(
                f"column names: expected names without spaces (a .txt table is space separated), got {name!r}"
            )
    controls = trajectories.controls
    if controls is not None:
        if controls.is_function:
            raise InputError(
                "controls: a profile given as a function u(t) cannot be written to a table; sample it "
                "(Controls(knots, values)) first"
            )
        header += list(controls.names)
    _check_distinct(header, "column names", str(path))
    gap = "NaN" if path.suffix == ".txt" else ""

    def cells(values) -> list[str]:
        return [gap if v != v else repr(float(v)) for v in values]

    def rows_of(k: int, t: torch.Tensor, y: torch.Tensor):
        if controls is None:
            for t_j, y_j in zip(t.detach().cpu().tolist(), y.detach().cpu().tolist(), strict=True):
                yield [str(k), repr(float(t_j))] + cells(y_j)
            return
        knots = controls.profiles()[k][0]
        every = torch.unique(torch.cat([t.detach(), knots.to(t)]))  # observation times and the profile's knots
        u = controls[k].at(every.unsqueeze(0))[0].detach().cpu().tolist()
        at = {float(v): j for j, v in enumerate(t.detach().cpu().tolist())}
        y = y.detach().cpu().tolist()
        for t_j, u_j in zip(every.cpu().tolist(), u, strict=True):
            j = at.get(float(t_j))
            state = y[j] if j is not None else [math.nan] * width  # a knot between measurements
            yield [str(k), repr(float(t_j))] + cells(state) + cells(u_j)

    width = len(header) - 2 - (0 if controls is None else len(controls.names))
    values, _ = trajectories.observed_values()  # the states and any readings, side by side
    rows = (
        row
        for k, ((t, _), n) in enumerate(zip(trajectories.experiments(), trajectories.lengths, strict=True))
        for row in rows_of(k, t, values[k, :n])
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


def read(
    path: str | Path,
    *,
    time_column: str,
    experiment_column: str | None,
    state_columns: Sequence[str] | None,
    control_columns: Sequence[str] | None = None,
) -> tuple:
    """``(times, states, state_names, controls, readout)`` for :meth:`Trajectories.load
    <torchmisspec.data.Trajectories.load>` (see there): tensors, or lists of per-experiment tensors for ragged
    data."""
    path = Path(check_path(path))
    if path.suffix != ".npz" and path.suffix not in _TEXT_FORMATS:
        raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
    if not path.is_file():
        raise InputError(f"path: expected an existing file, got {str(path)!r}")
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = {"times", "states"} - set(data.files)
                if missing:
                    raise InputError(
                        f"{path}: expected arrays 'times' and 'states', got {sorted(data.files)} (missing "
                        f"{sorted(missing)})"
                    )
                times, states = data["times"], data["states"]
                lengths = data["lengths"] if "lengths" in data.files else None
                names = data["state_names"] if "state_names" in data.files else None
                readout = {key: data[key] for key in ("readout_matrix", "readout_names", "readings") if key in data}
                stored = data["dtype"] if "dtype" in data.files else None
        except InputError:
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
            raise InputError(
                f"{path}: expected an .npz archive with numeric arrays 'times' and 'states' (no pickled objects), "
                f"got a file that could not be read as one ({unreadable(exc)})"
            ) from exc
        if names is not None:
            if names.dtype.kind != "U" or names.ndim != 1:
                raise InputError(f"{path}: expected 'state_names' to be a 1-D array of strings, got {names!r:.80}")
            names = names.tolist()
        if control_columns is not None:
            raise InputError(
                f"control_columns: expected a text table to name the columns of, got the .npz archive {path}"
            )
        dtype = _stored_dtype(path, stored)
        readout = _npz_readout(path, readout, names, lengths)
        if lengths is not None:
            times, states = _split_ragged(path, times, states, lengths)
        else:
            times, states = as_tensor(times, f"{path}: times"), as_tensor(states, f"{path}: states")
        if dtype is not None:  # the dtype the trajectories were saved in
            times, states = _cast(times, dtype), _cast(states, dtype)
            readout = None if readout is None else (readout[0], _cast(readout[1], dtype))
        return times, states, names, None, readout
    header, body = _read_table(path)
    columns = dict(time_column=time_column, experiment_column=experiment_column, state_columns=state_columns)
    return (*_columns_to_arrays(path, header, body, control_columns=control_columns, **columns), None)


def _numpy(t: torch.Tensor) -> np.ndarray:
    """A tensor as numpy (bfloat16, which numpy lacks, as float32: exact)."""
    t = t.detach().cpu()
    return (t.float() if t.dtype == torch.bfloat16 else t).numpy()


_STORED_DTYPES = {
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float32": torch.float32,
    "float64": torch.float64,
}


def _stored_dtype(path: Path, stored) -> torch.dtype | None:
    """The dtype an ``.npz`` archive records (``None`` for older files: float64, or the arrays' own)."""
    if stored is None:
        return None
    name = str(stored)
    if stored.ndim != 0 or name not in _STORED_DTYPES:
        raise InputError(f"{path}: expected 'dtype' to name one of {sorted(_STORED_DTYPES)}, got {name!r:.40}")
    return _STORED_DTYPES[name]


def _cast(x, dtype: torch.dtype):
    return [v.to(dtype) for v in x] if isinstance(x, (list, tuple)) else x.to(dtype)


def _npz_readout(path: Path, arrays: dict, names, lengths):
    """``(Readout, readings)`` from an ``.npz`` archive's readout arrays (``None`` without them)."""
    if not arrays:
        return None
    if set(arrays) != {"readout_matrix", "readout_names", "readings"}:
        raise InputError(
            f"{path}: expected the arrays readout_matrix, readout_names and readings together, got {sorted(arrays)}"
        )
    if arrays["readout_names"].dtype.kind != "U" or arrays["readout_names"].ndim != 1:
        raise InputError(
            f"{path}: expected 'readout_names' to be a 1-D array of strings, got {arrays['readout_names']!r:.80}"
        )
    readout = Readout(
        as_tensor(arrays["readout_matrix"], f"{path}: readout_matrix"),
        arrays["readout_names"].tolist(),
        state_names=names,
    )
    readings = as_tensor(arrays["readings"], f"{path}: readings")
    if lengths is not None:
        if readings.dim() != 2 or readings.shape[0] != int(np.asarray(lengths).sum()):
            raise ShapeError(f"{path}: expected readings (N, m) with N = sum(lengths), got {tuple(readings.shape)}")
        readings = list(readings.split(np.asarray(lengths).tolist()))
    return readout, readings


def header(path: str | Path) -> list[str] | None:
    """The column names of a text table (``None`` for an ``.npz`` archive or a missing file)."""
    path = Path(check_path(path))
    if path.suffix not in _TEXT_FORMATS or not path.is_file():
        return None
    return _read_table(path)[0]


def read_with_readout(
    path, *, readout, time_column: str, experiment_column: str | None, state_columns, control_columns=None
) -> tuple:
    """:func:`read` of a text table holding a readout's columns (:meth:`Trajectories.load
    <torchmisspec.data.Trajectories.load>` with ``readout``): the states are ``state_columns`` (default
    ``readout.state_names``), those without a column all missing; the last item is ``(readout, readings)``."""
    if not isinstance(readout, Readout):
        raise InputError(f"readout: expected a torchmisspec.data.Readout or None, got {type(readout).__name__}")
    names = list(state_columns) if state_columns is not None else list(readout.state_names or [])
    if len(names) != readout.state_dim:
        raise InputError(
            f"state_columns: expected the names of the {readout.state_dim} states the readout reads from (or a "
            f"readout built with state_names), got {names}"
        )
    columns = header(path)
    if columns is None:
        raise InputError(f"readout: expected a text table (.csv, .tsv, .txt) holding its columns, got {str(path)!r}")
    present = [n for n in names if n in columns]
    times, values, _, controls, _ = read(
        path,
        time_column=time_column,
        experiment_column=experiment_column,
        state_columns=present + list(readout.names),
        control_columns=control_columns,
    )
    where = [names.index(n) for n in present]

    def states_of(v):  # the states absent from the file: columns of missing values
        out = torch.full((*v.shape[:-1], len(names)), float("nan"), dtype=v.dtype)
        out[..., where] = v[..., : len(present)]
        return out

    if isinstance(values, list):
        states, readings = [states_of(v) for v in values], [v[..., len(present) :] for v in values]
    else:
        states, readings = states_of(values), values[..., len(present) :]
    return times, states, names, controls, (readout, readings)
