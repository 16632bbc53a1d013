"""What every command shares: the data options, reading tables and model files, checking output paths."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from .._errors import InputError

__all__ = ["add_data_options", "add_system_option", "check_output", "load_model", "parse_times", "read_observations"]


def add_system_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--system",
        required=True,
        help="the known model: a built-in name (paper_linear, paper_gravity) or 'module:function' / "
        "'path/to/file.py:function', a function returning a torchmisspec.MisspecifiedSystem (its code is run)",
    )


def add_data_options(parser: argparse.ArgumentParser, *, required: bool, help: str) -> None:
    """``--data`` and the columns of a lab's table, the same for every command."""
    parser.add_argument("--data", required=required, help=help)
    parser.add_argument("--time-column", default="time", help="name of the time column (default: %(default)s)")
    parser.add_argument(
        "--experiment-column",
        default="experiment",
        help="name of the column labelling the experiments (default: %(default)s; when the file has no such column, "
        "or with '', all rows are one experiment)",
    )
    parser.add_argument(
        "--state-columns", help="comma separated state column names, in order (default: every other column)"
    )


def state_columns(args: argparse.Namespace) -> list[str] | None:
    if getattr(args, "state_columns", None) is None:
        return None
    names = [c.strip() for c in args.state_columns.split(",")]
    if not all(names):
        raise InputError(f"--state-columns: expected comma separated column names, got {args.state_columns!r}")
    return names


def read_observations(args: argparse.Namespace):
    """The ``Trajectories`` of ``--data`` with the column options."""
    from ..data import Trajectories

    return Trajectories.load(
        args.data,
        time_column=args.time_column,
        experiment_column=args.experiment_column or None,  # '' = no experiment column: one experiment
        state_columns=state_columns(args),
    )


def state_names(args: argparse.Namespace, d: int) -> list[str]:
    """The state names for outputs: ``--state-columns``, else the data file's header, else ``y0 .. y{d-1}``."""
    names = state_columns(args)
    if names is None and getattr(args, "data", None) and Path(args.data).suffix in (".csv", ".tsv", ".txt"):
        try:
            with open(args.data, encoding="utf-8") as fh:
                header = fh.readline().strip()
            sep = "\t" if "\t" in header else ","
            cols = [c.strip() for c in header.split(sep)]
            skip = {args.time_column, args.experiment_column}
            names = [c for c in cols if c and c not in skip]
        except (OSError, UnicodeDecodeError):
            names = None
    if names is None or len(names) != d:
        names = [f"y{j}" for j in range(d)]
    return names


def parse_times(text: str):
    """``start:stop:count`` (equally spaced) or a comma list of times."""
    import torch

    message = f"--times: expected 'start:stop:count' with count >= 1 or a comma list of numbers, got {text!r}"
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


def read_table(path: str, what: str):
    """A numeric array from .npz (array ``what`` or the only one), .npy, or CSV/TSV/TXT (an optional header row),
    and the header's column names (``None`` without one). Nothing is unpickled; unreadable, non-UTF-8 or
    non-numeric files raise :class:`InputError`."""
    import zipfile

    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what}: file {path!r} does not exist")
    if p.suffix not in (".csv", ".tsv", ".txt", ".npz", ".npy"):
        raise InputError(f"{what}: expected a .csv, .tsv, .txt, .npz or .npy file, got {path!r}")
    header = None
    try:
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as data:
                if what in data.files:
                    arr = data[what]
                elif len(data.files) == 1:
                    arr = data[data.files[0]]
                else:
                    raise InputError(f"{path}: expected an array named {what!r} (or a single array), got {data.files}")
        elif p.suffix == ".npy":
            arr = np.load(p, allow_pickle=False)
        else:
            lines = [ln for ln in p.read_text(encoding="utf-8").splitlines() if ln.strip()]
            sep = "\t" if lines and "\t" in lines[0] else ","
            if lines:
                try:
                    float(lines[0].replace(sep, " ").split()[0])
                except ValueError:
                    header = [c.strip() for c in lines[0].split(sep)]
                    lines = lines[1:]  # a header row
            arr = np.array([[float(v) for v in ln.replace(sep, " ").split()] for ln in lines], dtype=np.float64)
    except InputError:
        raise
    except (ValueError, OSError, EOFError, UnicodeDecodeError, zipfile.BadZipFile) as exc:
        raise InputError(
            f"{what}: expected a numeric table in {path!r} (UTF-8 text, or .npy/.npz without pickled objects), but it "
            f"could not be read ({type(exc).__name__}: {str(exc)[:160]})"
        ) from exc
    if arr.dtype.kind not in "iuf" or arr.size == 0:
        raise InputError(
            f"{what}: expected a non-empty array of real numbers in {path!r}, got dtype {arr.dtype}, shape {arr.shape}"
        )
    return arr, header


def check_output(path: str, suffixes: tuple[str, ...], option: str = "--out") -> Path:
    """The output file: a known suffix, in a folder that exists and is writable (checked before any work)."""
    out = Path(path)
    if out.suffix not in suffixes:
        raise InputError(f"{option}: expected a {' or '.join(suffixes)} file name, got {path!r}")
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir() or not os.access(folder, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        raise InputError(f"{option}: cannot write {path!r} (the folder must exist and be writable)")
    return out


def load_model(path: str, system):
    """A saved CorrectionGP, checked against the system's correction inputs and outputs."""
    from ..gp import CorrectionGP

    gp = CorrectionGP.load(path)
    if gp.input_dim != system.input_dim or gp.output_dim != system.output_dim:
        raise InputError(
            f"--model: {path} holds a correction with {gp.input_dim} inputs and {gp.output_dim} outputs, but system "
            f"'{system.name}' declares {system.input_dim} and {system.output_dim}; pass the system it was fitted with"
        )
    return gp


def write_csv(path: Path, header: list[str], rows) -> None:
    import csv

    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
