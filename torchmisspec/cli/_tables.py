"""The command line's small tables: the cells of a text table (initial states, candidates, times, region labels), a
numeric array from a table or a NumPy file, and ``--times``."""

from __future__ import annotations

import csv
from pathlib import Path

from .._errors import InputError

__all__ = ["TABLE_SUFFIXES", "is_number", "parse_times", "read_table", "text_rows"]

#: The files a table option reads: text tables and NumPy arrays.
TABLE_SUFFIXES = (".csv", ".tsv", ".txt", ".npz", ".npy")


def is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def text_rows(path: Path, option: str) -> list[tuple[int, list[str]]]:
    """The non-blank rows of a UTF-8 text table, ``(line number, cells)``, read as :meth:`Trajectories.load
    <torchmisspec.data.Trajectories.load>` reads one: a byte-order mark dropped, CSV quoting understood, cells
    stripped; ``.csv`` comma separated, ``.tsv`` tab separated, ``.txt`` separated by spaces (or by the tabs or
    commas of its first row). A column empty in every row (a trailing separator) is dropped; a row with another
    number of cells than the first is refused."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(
            f"{option}: expected a UTF-8 text table in {str(path)!r}, but it could not be read "
            f"({type(exc).__name__}: {str(exc)[:160]})"
        ) from exc
    first = next((line for line in lines if line.strip()), "")
    if path.suffix == ".tsv" or ("\t" in first and "," not in first):
        delimiter = "\t"
    elif path.suffix == ".txt" and "," not in first:
        delimiter = None
    else:
        delimiter = ","
    if delimiter is None:
        rows = [(i, line.split()) for i, line in enumerate(lines, start=1)]
    else:
        try:
            reader = csv.reader(lines, delimiter=delimiter)
            rows = [(reader.line_num, row) for row in reader]
        except csv.Error as exc:
            raise InputError(
                f"{option}: expected a table in {str(path)!r}, got one that could not be read ({exc})"
            ) from exc
    rows = [(i, [cell.strip() for cell in row]) for i, row in rows if any(cell.strip() for cell in row)]
    if not rows:
        return rows
    width = len(rows[0][1])
    bad = next(((i, row) for i, row in rows if len(row) != width), None)
    if bad is not None:
        raise InputError(
            f"{option}: expected {width} cells in every row (as in the first), got {len(bad[1])} on line {bad[0]} of "
            f"{str(path)!r} ({','.join(bad[1])!r}); give every row the same columns"
        )
    empty = [j for j in range(width) if not any(row[j] for _, row in rows)]
    return [(i, [c for j, c in enumerate(row) if j not in empty]) for i, row in rows] if empty else rows


def read_table(path: str, what: str, option: str | None = None):
    """A numeric array from .npz (array ``what`` or the only one), .npy, or CSV/TSV/TXT (an optional header row),
    and the header's column names (``None`` without one). Nothing is unpickled; unreadable, non-UTF-8 or
    non-numeric files raise :class:`InputError`."""
    import numpy as np

    from ..data._npz import npy_array, npz_arrays

    label = option or what  # the option named in messages (``what`` is also the .npz array's name)

    p = Path(path)
    if not p.is_file():
        raise InputError(
            f"{label}: expected an existing file, got {path!r}, which "
            + ("is a folder" if p.is_dir() else "does not exist")
        )
    if p.suffix not in TABLE_SUFFIXES:
        raise InputError(f"{label}: expected a .csv, .tsv, .txt, .npz or .npy file, got {path!r}")
    header = None
    if p.suffix == ".npz":
        arrays = npz_arrays(p, label)  # a damaged archive, or one array np.save'd under an .npz name: refused
        if what not in arrays and len(arrays) != 1:
            raise InputError(
                f"{label}: expected an array named {what!r} (or a single array) in {path}, got {sorted(arrays)}"
            )
        arr = arrays[what] if what in arrays else next(iter(arrays.values()))
    elif p.suffix == ".npy":
        arr = npy_array(p, label)
    else:
        rows = [row for _, row in text_rows(p, label)]
        if rows and not is_number(rows[0][0]):
            header, rows = rows[0], rows[1:]  # a header row
        try:
            arr = np.array([[float(v) for v in row] for row in rows], dtype=np.float64)
        except ValueError as exc:
            raise InputError(
                f"{label}: expected a numeric table in {path!r} (UTF-8 text, or .npy/.npz without pickled objects), "
                f"but it could not be read ({type(exc).__name__}: {str(exc)[:160]})"
            ) from exc
    if arr.dtype.kind not in "iuf" or arr.size == 0:
        raise InputError(
            f"{label}: expected a non-empty array of real numbers in {path!r}, got dtype {arr.dtype}, shape {arr.shape}"
        )
    return arr, header


def parse_times(text: str, option: str = "--times"):
    """``start:stop:count`` (equally spaced), a comma list of times, or a file of times (one column); ``option``
    names the option in messages."""
    import torch

    message = f"{option}: expected 'start:stop:count' with count >= 1, a comma list of numbers or a file of times, "
    message += f"got {text!r}"
    if Path(text).suffix in TABLE_SUFFIXES:
        if not Path(text).exists():
            raise InputError(f"{option}: expected an existing file of times, got {text!r}, which does not exist")
        table, _ = read_table(text, "times", option)
        if table.ndim == 2 and table.shape[1] != 1:
            raise InputError(f"{option}: expected one column of times in {text!r}, got {table.shape[1]} columns")
        return torch.as_tensor(table.reshape(-1), dtype=torch.float64)
    try:
        if ":" in text:
            start, stop, count = text.split(":")
            count = int(count)
            if count < 1:
                raise InputError(message)
            return torch.linspace(float(start), float(stop), count, dtype=torch.float64)
        return torch.tensor([float(v) for v in text.split(",")], dtype=torch.float64)
    except ValueError as exc:
        raise InputError(message) from exc
