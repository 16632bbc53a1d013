"""Trajectories: observed or simulated states of K experiments, and :func:`simulate`.

``Trajectories(times, states)`` holds ``states (K, T, d)`` sampled at ``times (T,)`` shared by all experiments or
``(K, T)`` one grid per experiment (irregular spacing allowed, strictly increasing along each row). It wraps user
data as well as simulations and saves to / loads from ``.npz`` and CSV.
"""

from __future__ import annotations

import csv
import numbers
import zipfile
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

    # ----------------------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write to ``path``: ``.npz`` (times, states) or ``.csv`` (experiment, time, y0, ..., y{d-1})."""
        path = Path(path)
        if path.suffix == ".npz":
            np.savez(path, times=self.times.detach().cpu().numpy(), states=self.states.detach().cpu().numpy())
        elif path.suffix == ".csv":
            grid = self.time_grid.detach().cpu().numpy()
            states = self.states.detach().cpu().numpy()
            with path.open("w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["experiment", "time"] + [f"y{i}" for i in range(self.state_dim)])
                for k in range(self.num_experiments):
                    for j in range(self.num_times):
                        w.writerow([k, repr(float(grid[k, j]))] + [repr(float(v)) for v in states[k, j]])
        else:
            raise InputError(f"path: expected a .npz or .csv file name, got {str(path)!r}")
        return path

    @classmethod
    def load(cls, path: str | Path) -> Trajectories:
        """Read a file written by :meth:`save` (or a CSV with the same columns, rows in any order).

        ``.npz`` files are read without pickle (no code can run); a missing, corrupt or malformed file raises
        :class:`InputError` naming the file and what was expected.
        """
        path = Path(path)
        if path.suffix not in (".npz", ".csv"):
            raise InputError(f"path: expected a .npz or .csv file name, got {str(path)!r}")
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
        try:
            with path.open(newline="", encoding="utf-8") as fh:
                rows = [row for row in csv.reader(fh) if row]
        except (UnicodeDecodeError, csv.Error, OSError) as exc:
            raise InputError(f"{path}: expected a UTF-8 text CSV file, but it could not be read ({exc})") from exc
        header, body = (rows[0], rows[1:]) if rows else ([], [])
        if header[:2] != ["experiment", "time"] or len(header) < 3:
            raise InputError(f"{path}: expected a header 'experiment,time,y0,...', got {','.join(header)!r:.200}")
        if not body:
            raise InputError(f"{path}: expected at least one data row after the header, got none")
        widths = {len(row) for row in body}
        if widths != {len(header)}:
            bad = next(i for i, row in enumerate(body) if len(row) != len(header))
            raise ShapeError(
                f"{path}: expected {len(header)} columns in every row (as in the header), got {len(body[bad])} in "
                f"data row {bad + 1}"
            )
        try:
            arr = np.asarray(body, dtype=np.float64)
        except ValueError as exc:
            raise InputError(f"{path}: expected {len(header)} numeric columns in every row ({exc})") from exc
        exp_ids = np.unique(arr[:, 0])
        per = [arr[arr[:, 0] == e] for e in exp_ids]
        counts = {len(p) for p in per}
        if len(counts) != 1:
            raise ShapeError(f"{path}: expected the same number of rows per experiment, got {sorted(counts)}")
        per = [p[np.argsort(p[:, 1], kind="stable")] for p in per]
        times = np.stack([p[:, 1] for p in per])
        states = np.stack([p[:, 2:] for p in per])
        if np.all(times == times[:1]):
            times = times[0]
        return cls(torch.from_numpy(times), torch.from_numpy(states))


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
