"""What every command shares: the data options, reading tables and model files, checking output paths."""

from __future__ import annotations

import argparse
import math
import os
from contextlib import contextmanager
from pathlib import Path

from .._errors import InputError
from ._tables import is_number, read_table, text_rows

__all__ = [
    "add_column_options",
    "add_data_options",
    "add_system_option",
    "check_names",
    "check_output",
    "describe_system",
    "input_columns",
    "known_state_names",
    "load_model",
    "read_controls",
    "read_observations",
    "read_states",
]


def seed(text: str) -> int:
    """An ``--seed`` value: an integer in [0, 2**63) (torch reduces larger ones modulo 2**64, so two seeds would give
    the same draws)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2**63), got {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2**63), got {text[:30]!r}")
    return value


def add_system_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--system",
        required=True,
        help="the known model: a built-in name (paper_linear, paper_gravity) or 'module:function' / "
        "'path/to/file.py:function', a function returning a torchmisspec.MisspecifiedSystem (its code is run)",
    )


def add_column_options(parser: argparse.ArgumentParser) -> None:
    """The columns of a lab's tables, the same options for every command (read and written)."""
    parser.add_argument(
        "--time-column", default="time", help="name of the time column in the tables (default: %(default)s)"
    )
    parser.add_argument(
        "--experiment-column",
        default="experiment",
        help="name of the column labelling the experiments (default: %(default)s; when a file has no such column, "
        "or with '', all rows of --data are one experiment)",
    )
    parser.add_argument(
        "--state-columns",
        help="comma separated names of the columns holding the system's states, in the system's order (default: the "
        "columns named as the system's states; for a system that names none, every other column in file order)",
    )
    parser.add_argument(
        "--readout",
        action="append",
        metavar="NAME=EXPRESSION",
        help="a column holding a measured combination of states, e.g. 'total = free + bound' or 'A280 = 1.5*P + "
        "0.2*L' (repeat for several); states with no column of their own are then read only through it",
    )
    parser.add_argument(
        "--input-columns",
        help="comma separated names of the columns holding known inputs u(t) (the system's controls, in its order): "
        "each experiment's rows sample its input profile, known at every row",
    )
    parser.add_argument(
        "--input-kind",
        choices=["previous", "linear"],
        help="how an input runs between its rows: previous (piecewise constant, default) or linear (an .npz archive "
        "records its own)",
    )


def add_data_options(parser: argparse.ArgumentParser, *, required: bool, help: str) -> None:
    """``--data`` and the column options."""
    parser.add_argument("--data", required=required, help=help)
    add_column_options(parser)


def state_columns(args: argparse.Namespace, option: str = "state_columns") -> list[str] | None:
    text = getattr(args, option, None)
    if text is None:
        return None
    names = [c.strip() for c in text.split(",")]
    flag = "--" + option.replace("_", "-")
    if not all(names) or len(set(names)) != len(names):
        raise InputError(f"{flag}: expected distinct comma separated column names, got {text!r}")
    return names


def read_observations(args: argparse.Namespace, system=None):
    """The ``Trajectories`` of ``--data`` with the column options, checked against ``system``.

    A system that names its states: a text table's state columns are read by those names, in the system's order,
    whatever the file's order; a state whose column is absent is *not measured* (all missing: partial measurements,
    learned through the ODE); other columns are left out. ``--state-columns`` names the columns of the system's states
    instead, in its order (they are then called by the system's names). A time, experiment or input column named as
    a state is refused. An ``.npz`` archive's states are matched to the system's by name. A system that names no
    states: ``--state-columns``, else every column but the time, experiment and inputs, in file order (their names
    go with the model, so later commands match their columns by them)."""
    from ..data import Readout, Trajectories

    names = list(getattr(system, "state_names", None) or [])
    inputs = input_columns(args, system)
    wanted = _state_columns_for(args, system, names)
    if system is not None and system.num_controls and inputs is None and Path(args.data).suffix != ".npz":
        controls = list(system.control_names)
        raise InputError(
            f"--data: the system also takes {system.num_controls} input(s) {controls}: name their columns in "
            f"{args.data!r} with --input-columns (e.g. --input-columns {','.join(controls)}), in the system's order"
        )
    options = dict(
        time_column=args.time_column,
        experiment_column=args.experiment_column or None,  # '' = no experiment column: one experiment
        control_columns=inputs,
        control_kind=getattr(args, "input_kind", None),
    )
    if getattr(args, "readout", None):
        states = wanted or names or default_names(system)
        readout = Readout.parse(args.readout, states)
        _check_readings(args, readout, system, states if not (wanted or names) else None)
        observed = Trajectories.load(args.data, state_columns=states, readout=readout, **options)
        return observed.with_state_names(names) if wanted and names else observed
    present = _present(args.data, names, system) if names and wanted is None else None
    observed = Trajectories.load(args.data, state_columns=present or wanted, **options)
    if wanted and names:  # the columns --state-columns names are the system's states, in its order
        return observed.with_state_names(names)
    if present is not None and len(present) < len(names):
        return _with_absent_states(observed, names)
    if names and set(observed.state_names) == set(names):  # an archive: its states matched to the system's by name
        return observed.reordered(names)
    return observed


def _check_readings(args: argparse.Namespace, readout, system, unnamed: list[str] | None) -> None:
    """The readings' columns apart from the time, experiment and input columns; for a system that names no states
    (``unnamed``: the names the readout then uses), no other column of the table left out unread."""
    from ..data._tables import header

    _check_apart("--readout", "a reading named apart from the table's other columns", list(readout.names), args)
    columns = header(args.data) if unnamed is not None else None
    if columns is None:
        return
    used = {args.time_column, args.experiment_column, *readout.names, *unnamed}
    left = [c for c in columns if c not in used and c not in (state_columns(args, "input_columns") or [])]
    if left:
        raise InputError(
            f"--readout: system '{system.name}' names no states, so its state columns cannot be found by name: "
            f"expected --state-columns naming them in the system's order, got columns {left} that would be left out "
            f"(e.g. --state-columns {','.join((left + unnamed)[: system.state_dim])}; the readout then names the "
            "states by them)"
        )


def _check_apart(option: str, what: str, given: list[str], args: argparse.Namespace) -> None:
    """Refuse ``given`` (the columns ``option`` names) holding the time, experiment or another option's columns."""
    others = [("--time-column", args.time_column), ("--experiment-column", args.experiment_column)]
    if option != "--input-columns":
        others += [("--input-columns", c) for c in state_columns(args, "input_columns") or []]
    for other, column in others:
        if column and column in given:
            which = f"one of the {other}" if other == "--input-columns" else f"the {other}"
            raise InputError(
                f"{option}: expected {what}, got {column!r}, {which}; name each column once, with the option it is for"
            )


def input_columns(args: argparse.Namespace, system) -> list[str] | None:
    """``--input-columns``, checked against ``system``: one column per input, in its order, none the time,
    experiment or a state column (``None`` when not given)."""
    inputs = state_columns(args, "input_columns")
    if inputs is None or system is None:
        return inputs
    if not system.num_controls:
        raise InputError(
            f"--input-columns: expected no input columns (system '{system.name}' has no inputs u(t)), got {inputs}; "
            "drop --input-columns"
        )
    if len(inputs) != system.num_controls:
        raise InputError(
            f"--input-columns: expected {system.num_controls} column(s), one per input of system '{system.name}' "
            f"({', '.join(system.control_names)}), got {inputs}"
        )
    _check_apart("--input-columns", "the columns of the inputs", inputs, args)
    _check_order("--input-columns", inputs, list(system.control_names), "inputs")
    return inputs


def _state_columns_for(args: argparse.Namespace, system, names: list[str]) -> list[str] | None:
    """``--state-columns``, checked against the system: one column per state, in its order; a time, experiment or
    input column named as one of its states is refused."""
    wanted = state_columns(args)
    if names:
        label = f"a state of system '{system.name}' ({', '.join(names)})"
        others = [("--time-column", args.time_column), ("--experiment-column", args.experiment_column)]
        others += [("--input-columns", c) for c in state_columns(args, "input_columns") or []]
        for option, column in others:
            if column and column in names:
                raise InputError(
                    f"{option}: expected a column other than the states, got {column!r}, {label}; name the "
                    f"{option.removeprefix('--').split('-')[0]} column of the file"
                )
    if wanted is not None:
        _check_apart("--state-columns", "the columns of the states", wanted, args)
    if wanted is None or system is None:
        return wanted
    if len(wanted) != system.state_dim:
        raise InputError(
            f"--state-columns: expected state dimension {system.state_dim} of system '{system.name}' (one column "
            "name per state" + (f": {', '.join(names)}" if names else "") + f", in its order), got {wanted}"
        )
    _check_order("--state-columns", wanted, names, "states")
    return wanted


def _check_order(option: str, given: list[str], names: list[str], what: str) -> None:
    """Refuse columns ``given`` (in the system's order) that name the system's ``names`` in another order."""
    misplaced = [(c, names.index(c)) for i, c in enumerate(given) if c in names and names.index(c) != i]
    if misplaced:
        column, at = misplaced[0]
        raise InputError(
            f"{option}: {','.join(given)} names the system's {what} in another order: {column!r} is its "
            f"{what[:-1]} {at + 1} of ({', '.join(names)}), and {option} lists the columns in the system's order; "
            f"pass them in that order ({','.join(c for c in names if c in given)})"
            + (", or leave it out (columns named as the states are read by name)" if what == "states" else "")
        )


def _present(path: str, names: list[str], system) -> list[str] | None:
    """The system's state names that are columns of the text table ``path`` (``None`` for an archive); none is an
    error: a table of a system that names its states is read by those names."""
    from ..data._tables import header

    columns = header(path)
    if columns is None:
        return None
    present = [n for n in names if n in columns]
    if not present:
        raise InputError(
            f"--data: expected state columns named as the states of system '{system.name}' ({', '.join(names)}), got "
            f"columns "
            f"{columns} in {path!r}; rename them, or name them in the system's order with --state-columns"
        )
    return present


def _with_absent_states(observed, names: list[str]):
    """``observed`` with the system's states that have no column as columns of missing values, in its order."""
    import torch

    from ..data import Trajectories

    where = [names.index(n) for n in observed.state_names]
    rows = []
    for _, y in observed.experiments():
        full = torch.full((y.shape[0], len(names)), float("nan"), dtype=y.dtype, device=y.device)
        full[:, where] = y
        rows.append(full)
    times = [t for t, _ in observed.experiments()]
    return Trajectories(times, rows, state_names=names, controls=observed.controls)


def default_names(system) -> list[str]:
    names = getattr(system, "state_names", None)
    return list(names) if names is not None else [f"y{j}" for j in range(system.state_dim)]


def known_state_names(system, gp=None) -> list[str | None] | None:
    """The states' names the system declares, else those the model was fitted on (``None`` for a state that is not an
    input of the correction), else ``None``."""
    if getattr(system, "state_names", None) is not None:
        return list(system.state_names)
    names = getattr(gp, "input_names_", None)
    if names is None:
        return None
    out = [None] * system.state_dim  # the correction's inputs are named; the other states may not be
    for i, n in zip(system.correction_inputs, names, strict=True):
        out[i] = n
    return out


def read_states(path: str, option: str, args: argparse.Namespace, system, known: list[str] | None = None):
    """Initial states, one per row, from ``path``: ``(tensor (N, d), state names, row labels)``.

    A CSV/TSV/TXT with a header row is read by name with the column options: ``--state-columns`` (the columns of
    the system's states, in its order, then called by the system's names when it names them; default: every column
    but the experiment column), ``--experiment-column`` (optional: the rows' labels, else 0..N-1); a time column is
    refused (one state per row, not trajectories). ``known``: the states' names (the system's or the model's); a
    header holding them all is read by them, in the system's order, whatever the columns' order (a system that names
    its states: a header without them all is refused), and a
    single other column of names, not numbers (sample IDs), labels the rows when there is no experiment column; any
    other extra column is refused (a data file given by mistake, a time column of another name). Without a
    header, or from .npy/.npz, every column is a state, in the system's order. A text table's cells are those of
    :func:`~torchmisspec.cli._tables.text_rows` (a byte-order mark dropped, CSV quoting, rows of one length)."""
    import torch

    p = Path(path)
    if p.suffix not in (".csv", ".tsv", ".txt") or not p.is_file():
        table, _ = read_table(path, option.lstrip("-"), option)  # an array, or the error naming what is wrong
        names, labels, rows = None, None, table
    else:
        cells = text_rows(p, option)
        if not cells or (len(cells) == 1 and not any(is_number(c) for c in cells[0][1])):
            raise InputError(f"{option}: expected at least one row of states in {path!r}, got none")
        header = cells[0][1] if not any(is_number(c) for c in cells[0][1]) else None
        body = cells[1:] if header is not None else cells
        if header is None:
            names, columns, labels = None, list(range(len(body[0][1]))), None
        else:
            names, columns, labels = _header_columns(header, [r for _, r in body], path, option, args, system, known)
        rows = []
        for line, row in body:
            try:
                rows.append([float(row[c]) for c in columns])
            except ValueError:
                raise InputError(
                    f"{option}: expected a number in every state column of line {line} of {path!r}, got "
                    f"{','.join(row)!r}"
                ) from None
    y0 = torch.as_tensor(rows, dtype=torch.float64)
    y0 = y0.reshape(1, -1) if y0.dim() == 1 else y0
    if y0.dim() != 2 or y0.shape[-1] != system.state_dim:
        got = y0.shape[-1] if y0.dim() == 2 else tuple(y0.shape)
        raise InputError(
            f"{option}: expected {system.state_dim} states per row (system '{system.name}'), got {got} in {path!r}"
            + ("" if names is None else f" (columns {names}; set --state-columns)")
        )
    if not bool(torch.isfinite(y0).all()):
        raise InputError(f"{option}: expected finite states in every row of {path!r}, got NaN or infinite values")
    return y0, names, labels


def _header_columns(header: list[str], body: list[list[str]], path: str, option: str, args, system, known):
    """``(state names, their columns' positions, row labels or None)`` of a table of states with a ``header`` (see
    :func:`read_states`)."""
    if args.time_column in header:
        raise InputError(
            f"{option}: expected one state per row, but {path!r} has a time column {args.time_column!r}; "
            "drop it (or rename it if it is a state)"
        )
    named = list(getattr(system, "state_names", None) or [])
    wanted = _state_columns_for(args, system, named)  # in the system's order: its states, by its names
    known = known if known is not None or not named else named
    label_column = args.experiment_column
    if wanted is None and known is not None and all(c in header for c in known if c is not None):
        others = [c for c in header if c != args.experiment_column and c not in known]
        if known.count(None) == len(others) <= 1:  # one unnamed state at most: the one column left
            wanted = [others.pop() if c is None else c for c in known]
        elif None not in known and args.experiment_column not in header and len(others) == 1:
            # every state by its name and one column of names, not numbers (a lab's sample IDs): its labels
            ids = header.index(others[0])
            if not any(is_number(row[ids]) for row in body if ids < len(row)):
                wanted, label_column = list(known), others[0]
    if wanted is None and named and not all(c in header for c in named):
        raise InputError(
            f"{option}: expected columns named as the states of system '{system.name}' ({', '.join(named)}), "
            f"got {header} in {path!r}; rename them, or name them in the system's order with --state-columns"
        )
    if wanted is None:
        wanted = [c for c in header if c != args.experiment_column]
    missing = [c for c in wanted if c not in header]
    if missing:
        raise InputError(
            f"{option}: expected state columns {wanted}, missing {missing}; {path!r} has {header} (set --state-columns)"
        )
    labels = None
    if label_column and label_column in header:
        e = header.index(label_column)
        labels = [row[e] if e < len(row) else "" for row in body]
    names = named if named and state_columns(args) is not None else wanted
    return names, [header.index(c) for c in wanted], labels


def check_names(gp, names, system, option: str) -> list[str]:
    """The state names to write; the model's input names (the data's columns it was fitted on) must match."""
    model_names = getattr(gp, "input_names_", None)
    # the states among the correction's inputs (the others are controls, named by their own columns)
    states = (
        []
        if model_names is None
        else [(i, n) for i, n in zip(system.correction_inputs, model_names, strict=True) if i < system.state_dim]
    )
    if names is not None and model_names is not None:
        got = tuple(names[i] for i, _ in states)
        if got != tuple(n for _, n in states):
            raise InputError(
                f"{option}: the model's correction was fitted on states named {[n for _, n in states]}, but the "
                f"columns give {list(got)} in their place; name (or order) the columns as in the fitted data, or "
                "pass --state-columns"
            )
    if names is None and model_names is not None and getattr(system, "state_names", None) is None:
        names = [f"y{j}" for j in range(system.state_dim)]
        for i, n in states:
            names[i] = n
        return names
    return list(names) if names is not None else default_names(system)


def check_output(path: str, suffixes: tuple[str, ...], option: str = "--out") -> Path:
    """The output file: a known suffix, in a folder that exists and is writable (checked before any work)."""
    out = Path(path)
    if out.suffix not in suffixes:
        raise InputError(f"{option}: expected a {' or '.join(suffixes)} file name, got {path!r}")
    message = f"{option}: cannot write {path!r} (the folder must exist and be writable)"
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir() or out.is_dir():
        raise InputError(message)
    existed = out.exists()
    try:  # a real try: os.access says yes to root everywhere, /proc included
        with out.open("ab"):
            pass
    except OSError as exc:
        raise InputError(f"{message}: {exc.strerror or exc}") from None
    if not existed:
        out.unlink(missing_ok=True)
    return out


def describe_system(system) -> dict:
    """What a model file records of the system it corrects (checked when the model is used again)."""
    return {
        "name": system.name,
        "state_dim": int(system.state_dim),
        "correction_inputs": [int(i) for i in system.correction_inputs],
        "correction_outputs": [int(i) for i in system.correction_outputs],
    }


def load_model(path: str, system):
    """A saved CorrectionGP, checked against the system's correction inputs and outputs."""
    from ..gp import CorrectionGP

    gp = CorrectionGP.load(path)
    saved = getattr(gp, "system_", None)
    if saved is not None and saved != describe_system(system):
        raise InputError(
            f"--system: {path} corrects system {saved.get('name')!r} ({saved.get('state_dim')} states), but "
            f"'{system.name}' ({system.state_dim} states) was given; pass the system it was fitted with"
        )
    if gp.input_dim != system.input_dim or gp.output_dim != system.output_dim:
        raise InputError(
            f"--model: {path} holds a correction with {gp.input_dim} inputs and {gp.output_dim} outputs, but system "
            f"'{system.name}' declares {system.input_dim} and {system.output_dim}; pass the system it was fitted with"
        )
    return gp


@contextmanager
def written(path: Path):
    """Write ``path`` all at once: the body writes the yielded temporary file next to it (same suffix), which then
    replaces ``path``; an error or Ctrl-C on the way removes it, so no half-written output looks complete."""
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_csv(path: Path, header: list[str], rows) -> None:
    import csv

    with written(path) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)


def read_controls(path: str, args: argparse.Namespace, system, labels: list[str]):
    """The input profiles u(t) of the rows of ``--initial`` (their ``labels``) from a table ``path``: an
    ``--experiment-column`` naming each row's experiment (as in ``--initial``; without it, one profile for every row),
    the ``--time-column``, and one column per input named as the system's controls (or ``--input-columns``), each
    experiment's rows the profile's samples (``--input-kind``: piecewise constant or linear between them)."""
    import torch

    from ..data._tables import _TEXT_FORMATS, _read_table
    from ..signals import Controls

    p = Path(path)
    if p.suffix not in _TEXT_FORMATS or not p.is_file():
        raise InputError(f"--controls: expected an existing CSV/TSV/TXT table of input profiles, got {path!r}")
    header, body = _read_table(p)
    names = input_columns(args, system) or list(system.control_names)
    needed = [args.time_column, *names]
    missing = [c for c in needed if c not in header]
    if missing:
        raise InputError(
            f"--controls: expected columns {needed} (the time and the system's inputs; name them with --time-column "
            f"and --input-columns), missing {missing}; {path!r} has {header}"
        )
    by_label = args.experiment_column and args.experiment_column in header
    profiles: dict[str, list[list[float]]] = {}
    for line, row in body:
        label = row[header.index(args.experiment_column)] if by_label else ""
        try:
            values = [float(row[header.index(c)]) for c in needed]
        except ValueError:
            raise InputError(
                f"--controls: expected numbers in columns {needed} on line {line} of {path!r}, got "
                f"{[row[header.index(c)] for c in needed]}"
            ) from None
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"--controls: expected finite times and inputs on line {line} of {path!r}, got {values}")
        profiles.setdefault(label, []).append(values)
    wanted = labels if by_label else [""] * len(labels)
    absent = sorted({w for w in wanted if w not in profiles})
    if absent:
        raise InputError(
            f"--controls: expected a profile for every initial condition ({args.experiment_column!r} labels "
            f"{sorted(set(wanted))}), missing {absent} in {path!r}"
        )
    knots, values = [], []
    for w in wanted:
        rows = torch.tensor(sorted(profiles[w]), dtype=torch.float64)
        if bool((rows[1:, 0] == rows[:-1, 0]).any()):
            raise InputError(f"--controls: expected one row per time in the profile of {w or 'the experiments'!r}")
        knots.append(rows[:, 0])
        values.append(rows[:, 1:])
    return Controls(knots, values, kind=args.input_kind or "previous", names=names)
