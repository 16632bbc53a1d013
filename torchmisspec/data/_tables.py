"""Trajectories on disk: ``.npz`` archives and text tables (``.csv``, ``.tsv``, ``.txt``), written by
:meth:`Trajectories.save <torchmisspec.data.Trajectories.save>` and read by
:meth:`Trajectories.load <torchmisspec.data.Trajectories.load>`."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from .._errors import InputError, ShapeError, TorchMisspecWarning, warn
from .._validation import check_path, check_writable, writing
from ..signals import KINDS, Controls
from ._input import _check_distinct
from ._npz import read_npz, write_npz
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


def _listed(columns, name: str) -> list | None:
    """Column names as a list (``None`` stays ``None``); a string or a non-iterable is refused."""
    if columns is None:
        return None
    if isinstance(columns, (str, bytes)) or not isinstance(columns, Iterable):
        raise InputError(f"{name}: expected a list of column names, got {columns!r:.80} ({type(columns).__name__})")
    return list(columns)


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
    state_columns, control_columns = (
        _listed(state_columns, "state_columns"),
        _listed(control_columns, "control_columns"),
    )
    experiment_column = _index_columns(path, header, time_column, experiment_column)
    index_columns = [time_column] + ([experiment_column] if experiment_column is not None else [])
    controls = _control_names(path, header, control_columns, index_columns, state_columns)
    index_columns = index_columns + controls
    names = _state_names(path, header, state_columns, index_columns)
    value_columns = [time_column, *names, *controls]
    first_control = 1 + len(names)
    labelable = state_columns is None and experiment_column is None  # a number column may be a label
    values = _values(path, header, body, value_columns, first_control, labelable)
    labels, order = _experiment_labels(path, header, body, experiment_column)
    per = _per_experiment(path, header, values, labels, order, experiment_column, value_columns)
    control = None
    if controls:
        _say_unmeasured_starts(path, per, order, first_control, experiment_column)
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


def _say_unmeasured_starts(path: Path, per: list, order: list[str], first_control: int, experiment_column) -> None:
    """Warn where an experiment's first rows measure nothing but give its inputs (a dose row with an empty
    concentration): those rows are dropped (:class:`~torchmisspec.data.Trajectories`), the experiment starts at its
    first measured row with that value as its initial state, and what the inputs did before it is not simulated (a
    user's trial on nlme's Remifentanil: the infusion's first 1.5 minutes, without a word)."""
    late = []
    for label, block in zip(order, per, strict=True):
        measured = ~np.isnan(block[:, 1:first_control]).all(-1)
        first = int(np.argmax(measured))
        if first > 0 and bool(measured.any()):
            late.append((label, float(block[0, 0]), float(block[first, 0])))
    if not late:
        return
    named = "; ".join(
        (f"experiment {label!r}: " if experiment_column is not None else "") + f"{t0:g} -> {t1:g}"
        for label, t0, t1 in late[:5]
    )
    warn(
        f"{path}: {len(late)} experiment(s) measure nothing in their first row(s) but give inputs there ({named}"
        f"{' ...' if len(late) > 5 else ''}): each starts at its first measured row, that value its initial state, "
        "and the inputs before it are not simulated. If the state is known there (0 before a dose), write it in the "
        "cell",
        TorchMisspecWarning,
    )


def _index_columns(path: Path, header: list[str], time_column, experiment_column) -> str | None:
    """The time and experiment columns checked against the header; the experiment column as found (``None`` where
    the default ``"experiment"`` is absent: one experiment, or several told apart by nothing)."""
    if not isinstance(time_column, str):
        raise InputError(f"time_column: expected a column name, got {type(time_column).__name__}")
    if experiment_column is not None and not isinstance(experiment_column, str):
        raise InputError(f"experiment_column: expected a column name or None, got {type(experiment_column).__name__}")
    if time_column not in header:
        raise InputError(
            f"{path}: expected a time column {time_column!r}, got columns {header}; name the one that holds the times "
            "(time_column=...; on the command line --time-column)"
        )
    if experiment_column is not None and experiment_column not in header:
        if experiment_column != "experiment":  # named by the caller: a typo must not merge all experiments
            raise InputError(
                f"{path}: expected an experiment column {experiment_column!r}, got columns {header}; name the one that "
                "tells the experiments apart (experiment_column=...; on the command line --experiment-column)"
            )
        experiment_column = None
    if experiment_column == time_column:
        raise InputError(f"experiment_column: expected a column other than the time column, got {time_column!r}")
    return experiment_column


def _control_names(path: Path, header: list[str], control_columns, index_columns: list[str], state_columns) -> list:
    """The control columns (none by default), checked: distinct, in the header, none of them an index or state
    column."""
    if control_columns is None:
        return []
    controls = list(control_columns)
    _check_distinct(controls, "control_columns", "control_columns")
    absent = [c for c in controls if c not in header]
    if absent:
        raise InputError(f"{path}: expected control columns {controls}, got columns {header} (missing {absent})")
    clash = [c for c in controls if c in index_columns or (state_columns is not None and c in state_columns)]
    if clash:
        raise InputError(f"control_columns: expected columns other than the time, experiment and states, got {clash}")
    return controls


def _state_names(path: Path, header: list[str], state_columns, index_columns: list[str]) -> list[str]:
    """The state columns: those named (checked: distinct, in the header, no index column), or by default every
    column that is not an index (time, experiment, control) column; at least one."""
    if state_columns is None:
        names = [c for c in header if c not in index_columns]
    else:
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
    return names


def _values(path: Path, header, body, value_columns: list[str], first_control: int, labelable: bool) -> np.ndarray:
    """``(rows, columns)`` float64: the time, state and control cells of every row (NaN where a state is missing);
    a time or a control cannot be missing, and no value may be infinite."""
    where = [header.index(c) for c in value_columns]
    values = np.empty((len(body), len(value_columns)), dtype=np.float64)
    for r, (line, row) in enumerate(body):
        for c, col in enumerate(where):
            values[r, c] = _cell(path, header[col], row[col], line, c, first_control, labelable)
    return values


def _cell(path: Path, column: str, cell: str, line: int, c: int, first_control: int, labelable: bool) -> float:
    """One cell of value column ``c`` (0 the time, from ``first_control`` on the controls) read as a number, with
    the fix in the message where it cannot be: a column of labels not named as the experiment column, a missing
    time or control, an infinite value."""
    if cell.lower() in _MISSING:
        value = math.nan
    else:
        try:
            value = float(cell)
        except ValueError:
            raise InputError(
                f"{path}: expected a number in column {column!r} on line {line}, got {cell!r}"
                + (" (a missing value is an empty cell, NaN or NA)" if c > 0 else "")
                + (
                    f"; if {column!r} labels the experiments, name it with experiment_column="
                    f"{column!r} (--experiment-column {column} on the command line)"
                    if c > 0 and labelable
                    else ""
                )
            ) from None
    if c == 0 and not math.isfinite(value):
        raise InputError(
            f"{path}: expected a finite time in column {column!r} on line {line}, got {cell!r} (times "
            "cannot be missing: drop the row, or fill in its time)"
        )
    if c >= first_control and not math.isfinite(value):
        raise InputError(
            f"{path}: expected a value of the control {column!r} on line {line}, got {cell!r} (a control "
            "is known at every row: fill it in, e.g. repeat the last value of a piecewise-constant input)"
        )
    if math.isinf(value):
        raise InputError(
            f"{path}: expected a finite number in column {column!r} on line {line}, got {cell!r} "
            "(an empty cell, NaN or NA is a missing value; infinite values are refused)"
        )
    return value


def _experiment_labels(path: Path, header, body, experiment_column) -> tuple[list[str], list[str]]:
    """``(labels, order)``: every row's experiment label and the experiments in order: numeric labels by value (1
    and 1.0 one experiment), text labels as they first appear; one unlabelled experiment without the column."""
    if experiment_column is None:
        return [""] * len(body), [""]
    labels = [row[header.index(experiment_column)] for _, row in body]
    blank = next((line for (line, _), label in zip(body, labels, strict=True) if not label), None)
    if blank is not None:
        raise InputError(
            f"{path}: expected an experiment label in column {experiment_column!r} on line {blank}, got an empty cell"
        )
    try:  # numeric labels: 1 and 1.0 are the same experiment, sorted by value
        numbers = [float(label) for label in labels]
        if all(np.isfinite(numbers)):
            labels = [str(int(n)) if n == int(n) else repr(n) for n in numbers]
            return labels, sorted(dict.fromkeys(labels), key=float)
        return labels, list(dict.fromkeys(labels))
    except ValueError:
        return labels, list(dict.fromkeys(labels))  # text labels keep the order in which they first appear


def _per_experiment(path: Path, header, values, labels, order, experiment_column, value_columns) -> list:
    """Each experiment's rows of ``values``, sorted by time; a time given twice in one experiment is refused (with
    how to name the experiment column where none was found)."""
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
    return per


def write(
    trajectories,
    path: str | Path,
    *,
    time_column: str,
    experiment_column: str,
    state_columns: Sequence[str] | None,
) -> Path:
    """What :meth:`Trajectories.save <torchmisspec.data.Trajectories.save>` does (see there)."""
    path = check_writable(path)
    readout, controls = trajectories.readout, trajectories.controls
    if path.suffix not in _TEXT_FORMATS and path.suffix != ".npz":
        raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
    if controls is not None and controls.is_function:
        raise InputError(
            "controls: a profile given as a function u(t) cannot be saved (in any format: only samples are stored): "
            "expected samples, got a function; sample it first, e.g. Controls(knots, controls.at(knots), "
            "kind='linear') at knots (K, S) fine enough"
        )
    if path.suffix == ".npz":
        return write_npz(trajectories, path)
    _check_table_can_hold(trajectories, path)
    names = list(trajectories.state_names) if state_columns is None else _listed(state_columns, "state_columns")
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
    if controls is not None:
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
    with writing(path), path.open("w", newline="", encoding="utf-8") as fh:
        if path.suffix == ".txt":
            fh.write(" ".join(header) + "\n")
            for row in rows:
                fh.write(" ".join(row) + "\n")
        else:
            w = csv.writer(fh, delimiter=_TEXT_FORMATS[path.suffix])
            w.writerow(header)
            w.writerows(rows)
    return path


def _check_table_can_hold(trajectories, path: Path) -> None:
    """Refuse the fields a text table cannot keep (an ``.npz`` archive keeps every field)."""
    controls = trajectories.controls
    if controls is not None and controls.kind != "previous":
        raise InputError(
            f"controls: expected piecewise-constant profiles, got kind {controls.kind!r}: a table records the "
            "profiles' samples, not how they run between them: "
            f"{path.suffix} tables are read back as piecewise constant unless told otherwise; save to .npz, which "
            "keeps the kind"
        )
    if trajectories.initial_states is not None:
        raise InputError(
            "initial_states: expected none in a text table, got initial states: a table holds observations, not the "
            "initial_states estimated for them; save to .npz, "
            "which keeps them, or write the observations alone: trajectories.with_initial_states(None).save(...)"
        )


def read(
    path: str | Path,
    *,
    time_column: str,
    experiment_column: str | None,
    state_columns: Sequence[str] | None,
    control_columns: Sequence[str] | None = None,
    control_kind: str | None = None,
) -> dict:
    """The fields of :meth:`Trajectories.load <torchmisspec.data.Trajectories.load>` (see there), as keywords of
    :class:`~torchmisspec.data.Trajectories`: tensors, or lists of per-experiment tensors for ragged data."""
    path = Path(check_path(path))
    if path.suffix != ".npz" and path.suffix not in _TEXT_FORMATS:
        raise InputError(f"path: expected a {_SUFFIXES} file name, got {str(path)!r}")
    if not path.is_file():
        raise InputError(f"path: expected an existing file, got {str(path)!r}")
    if control_kind is not None and control_kind not in KINDS:
        raise InputError(
            f"control_kind: expected one of {KINDS} (how the profiles run between samples), got {control_kind!r}"
        )
    if path.suffix == ".npz":
        if control_columns is not None:
            raise InputError(
                f"control_columns: expected a text table to name the columns of, got the .npz archive {path}"
            )
        return read_npz(path, control_kind)
    header, body = _read_table(path)
    columns = dict(time_column=time_column, experiment_column=experiment_column, state_columns=state_columns)
    times, states, names, controls = _columns_to_arrays(path, header, body, control_columns=control_columns, **columns)
    if controls is not None:
        knots, values, control_names = controls
        controls = Controls(knots, values, kind=control_kind or "previous", names=control_names)
    return dict(times=times, states=states, state_names=names, controls=controls)


def header(path: str | Path) -> list[str] | None:
    """The column names of a text table (``None`` for an ``.npz`` archive or a missing file)."""
    path = Path(check_path(path))
    if path.suffix not in _TEXT_FORMATS or not path.is_file():
        return None
    return _read_table(path)[0]


def read_with_readout(
    path,
    *,
    readout,
    time_column: str,
    experiment_column: str | None,
    state_columns,
    control_columns=None,
    control_kind: str | None = None,
) -> dict:
    """:func:`read` of a text table holding a readout's columns (:meth:`Trajectories.load
    <torchmisspec.data.Trajectories.load>` with ``readout``): the states are ``state_columns`` (default
    ``readout.state_names``), those without a column all missing; the readout and its readings come with them."""
    if not isinstance(readout, Readout):
        raise InputError(f"readout: expected a torchmisspec.data.Readout or None, got {type(readout).__name__}")
    given = _listed(state_columns, "state_columns")
    names = given if given is not None else list(readout.state_names or [])
    if len(names) != readout.state_dim:
        raise InputError(
            f"state_columns: expected the names of the {readout.state_dim} states the readout reads from (or a "
            f"readout built with state_names), got {names}"
        )
    columns = header(path)
    if columns is None:
        raise InputError(f"readout: expected a text table (.csv, .tsv, .txt) holding its columns, got {str(path)!r}")
    present = [n for n in names if n in columns]
    fields = read(
        path,
        time_column=time_column,
        experiment_column=experiment_column,
        state_columns=present + list(readout.names),
        control_columns=control_columns,
        control_kind=control_kind,
    )
    values = fields["states"]
    where = [names.index(n) for n in present]

    def states_of(v):  # the states absent from the file: columns of missing values
        out = torch.full((*v.shape[:-1], len(names)), float("nan"), dtype=v.dtype)
        out[..., where] = v[..., : len(present)]
        return out

    if isinstance(values, list):
        states, readings = [states_of(v) for v in values], [v[..., len(present) :] for v in values]
    else:
        states, readings = states_of(values), values[..., len(present) :]
    return fields | dict(states=states, state_names=names, readout=readout, readings=readings)
