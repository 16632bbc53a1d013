"""The :class:`Trajectories` container (see :mod:`torchmisspec.data`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch

from .._errors import InputError, ShapeError
from .._validation import NotATensor, as_tensor, check_selection, check_to, states_and_times
from ..signals import Controls
from . import _tables
from ._input import (
    _check_apart,
    _check_state_names,
    _default_names,
    _describe_lengths,
    _drop_empty_rows,
    _is_number,
    _order_by_name,
    _per_experiment,
)
from ._join import concatenate
from ._missing import fill
from ._readout import Readout, check_readout, joined

#: A component observed fewer times than this in an experiment is *not measured* there (too few values for a
#: derivative estimate: every estimator needs 3); its few values still enter the fit through the ODE.
MIN_MEASURED = 3


@dataclass(frozen=True)
class Trajectories(NotATensor):
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
    table read by :meth:`load`); :attr:`observed` is the mask of the others. Times can never be missing, and infinite
    values are refused. A component an experiment never observes (or observes fewer than
    :data:`MIN_MEASURED` times, too few for a derivative, unless at each of the experiment's own times: an
    experiment of two rows, both observed, measures it) is *not measured* there (:attr:`measured`): partial
    measurements, e.g. biomass measured and substrate not; :func:`~torchmisspec.fit_correction` learns through the
    ODE then (see :mod:`torchmisspec.learning.refinement.partial`), estimating what was not measured. An experiment must
    observe something. A time at which no component was observed carries no data and is dropped (so masking a whole row
    is the same as deleting it; the experiment may then become shorter than the others, i.e. ragged). The
    package's functions use only observed entries: the derivative estimators fit each component from its own
    observed times, :func:`~torchmisspec.correction_samples` fills what a sample's G(y) and inputs need from the
    estimator's fit, and the comparisons with the data (cross-validation, :func:`~torchmisspec.fit_trajectories`,
    band calibration) skip missing entries. :meth:`filled` and :attr:`initial_conditions` estimate missing entries.

    Attributes:
        times: ``(T,)``, ``(K, T)``, or a tuple of K ``(T_k,)`` tensors (ragged).
        states: ``(K, T, d)``, or a tuple of K ``(T_k, d)`` tensors (ragged); NaN where an entry is missing.
        state_names: the names of the d state components (the table's column names for :meth:`load`; default
            ``y0, ..., y{d-1}``); kept by indexing, :meth:`to`, :meth:`save` and :meth:`load`.
        controls: the experiments' known input signals u(t), a :class:`~torchmisspec.signals.Controls` with one
            profile per experiment (``None``: the system has none), named apart from the states; kept by indexing,
            :meth:`to`, :meth:`save` and :meth:`load` (a table's ``control_columns``).
        initial_states: ``(K, d)`` estimates of every experiment's state at its first time, used by
            :attr:`initial_conditions` instead of the first observed states (``None``: those). Set by the fit of
            partly measured data (:meth:`with_initial_states`), where a component that is not measured has no
            first value of its own; kept by indexing, :meth:`to` and an ``.npz`` archive (a text table refuses them).
        readout: measured linear combinations of the states, a :class:`~torchmisspec.data.Readout` (an observation
            matrix H ``(m, d)``; ``None``: only the states themselves are measured). When both it and
            :attr:`state_names` name the states, its weights are matched to them by name (other names are refused).
        readings: the readout's values, laid out as :attr:`states` with m columns (``(K, T, m)`` or a tuple of
            ``(T_k, m)``), NaN where a quantity was not read; a time at which only readings were taken is kept. A
            state read only through the readout is not :attr:`measured`: the fit learns through the ODE then.
    """

    times: torch.Tensor | tuple[torch.Tensor, ...]
    states: torch.Tensor | tuple[torch.Tensor, ...]
    state_names: tuple[str, ...] | None = None
    controls: Controls | None = None
    initial_states: torch.Tensor | None = None
    readout: Readout | None = None
    readings: torch.Tensor | tuple[torch.Tensor, ...] | None = None

    def __post_init__(self) -> None:
        m = check_readout(self.readout, self.readings)
        given = self.states if m == 0 else joined(self.states, self.readings)
        if isinstance(given, (list, tuple)):
            states, times = _per_experiment(given, self.times)
        else:
            if isinstance(self.times, (list, tuple)) and self.times and not _is_number(self.times[0]):
                raise InputError(
                    "times: expected a list of per-experiment state arrays with a list of per-experiment time "
                    "arrays, got "
                    f"states as one {type(self.states).__name__}"
                )
            states, times = states_and_times(given, self.times, missing=True)
        if len(states) == 0 or states[0].shape[0] == 0:
            raise ShapeError(
                "states: expected at least one experiment with at least one time, got shape "
                f"{tuple(states.shape) if isinstance(states, torch.Tensor) else tuple(states[0].shape)}"
            )
        d = states[0].shape[-1] - m
        names = _check_state_names(self.state_names, d)
        states, times = _drop_empty_rows(states, times)
        if m:  # the states and the readings, split again after the checks and the dropped rows
            if self.readout.state_dim != d:
                raise ShapeError(
                    f"readout: expected weights over the {d} states (an (m, {d}) matrix), got {self.readout.state_dim} "
                    "columns"
                )
            split = [(y[..., :d], y[..., d:]) for y in states] if isinstance(states, tuple) else None
            readings = tuple(r for _, r in split) if split else states[..., d:]
            states = tuple(y for y, _ in split) if split else states[..., :d]
            object.__setattr__(self, "readings", readings)
            readout = self.readout.for_states(names)  # its weights matched to the states by name, when both name them
            object.__setattr__(self, "readout", readout.to(dtype=states[0].dtype, device=states[0].device))
        if self.controls is not None:
            if not isinstance(self.controls, Controls):
                raise InputError(
                    f"controls: expected a torchmisspec.signals.Controls (one profile per experiment) or None, got "
                    f"{type(self.controls).__name__}"
                )
            K = len(states) if isinstance(states, tuple) else states.shape[0]
            if self.controls.num_experiments != K:
                raise ShapeError(
                    f"controls: expected profiles of the {K} experiments, got {self.controls.num_experiments}"
                )
            object.__setattr__(self, "controls", self.controls.to(dtype=states[0].dtype, device=states[0].device))
        _check_apart(names, self.controls, self.readout)  # a table holds one column of each name
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "state_names", names)
        if self.initial_states is not None:
            K = len(states) if isinstance(states, tuple) else states.shape[0]
            y0 = as_tensor(self.initial_states, "initial_states", dtype=states[0].dtype, device=states[0].device)
            if y0.shape != (K, d) or not bool(torch.isfinite(y0).all()):
                raise ShapeError(
                    f"initial_states: expected finite ({K}, {d}) states (one per experiment), got "
                    f"{'shape ' + str(tuple(y0.shape)) if y0.shape != (K, d) else 'non-finite values'}"
                )
            object.__setattr__(self, "initial_states", y0)

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
        return self.with_states(fill(states, times, torch.isfinite(states) & mask.unsqueeze(-1)))

    def with_states(self, states: torch.Tensor) -> Trajectories:
        """These experiments (times, names, controls, initial states, readings) with new state values: ``(K, T, d)``
        laid out as :meth:`padded` (ragged data: the entries past each experiment's length are ignored)."""
        if not self.is_ragged:
            return dataclasses.replace(self, states=states)
        rows = [states[k, :n] for k, n in enumerate(self.lengths)]
        return dataclasses.replace(self, times=list(self.times), states=rows, readings=self._listed_readings())

    def _listed_readings(self):
        return None if self.readings is None or not self.is_ragged else list(self.readings)

    @property
    def observed_dim(self) -> int:
        """d + m: the states and the readings (:attr:`readout`) of every row, as :meth:`observed_values` lays them."""
        return self.state_dim + (0 if self.readout is None else self.readout.num_readings)

    def observed_values(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(values (K, T_max, d + m), mask (K, T_max))``: the states and the readings side by side, padded as
        :meth:`padded` (NaN where an entry was not observed); what the model's path, read by :meth:`observe`, is
        compared with."""
        _, states, mask = self.padded()
        if self.readout is None:
            return states, mask
        readings = self.readings
        if self.is_ragged:
            T = states.shape[1]
            readings = torch.stack([torch.cat([r, r[-1:].expand(T - len(r), -1)]) for r in readings])
        return torch.cat([states, readings], dim=-1), mask

    def observe(self, states: torch.Tensor) -> torch.Tensor:
        """``(..., d + m)``: states ``(..., d)`` and their readings (:attr:`readout`), as :meth:`observed_values`."""
        if self.readout is None:
            return states
        return torch.cat([states, self.readout(states)], dim=-1)

    def with_readout(self, readout: Readout | None, readings=None) -> Trajectories:
        """These trajectories with ``readout`` (``None``: none), its values ``readings`` laid out as :attr:`states`
        (default: the readout of the states themselves, e.g. of a simulation, before its states are masked)."""
        check_readout(readout, readings if readout is None else ())  # a Readout or None; readings need one
        if readout is not None:
            readout = readout.for_states(self.state_names)  # its weights on these states by name, when both name them
        if readout is not None and readings is None:
            readings = tuple(readout(y) for y in self.states) if self.is_ragged else readout(self.states)
        if self.is_ragged and readings is not None:
            readings = list(readings)
        return dataclasses.replace(
            self,
            times=list(self.times) if self.is_ragged else self.times,
            states=list(self.states) if self.is_ragged else self.states,
            readout=readout,
            readings=readings,
        )

    @property
    def measured(self) -> torch.Tensor:
        """``(K, d)`` boolean: whether experiment k measures component j (at least :data:`MIN_MEASURED` observed
        values, or a value at each of its times when it has fewer, e.g. a culture measured twice; see the class
        notes on partial measurements)."""
        _, states, mask = self.padded()
        seen = (torch.isfinite(states) & mask.unsqueeze(-1)).sum(1)
        every = seen == mask.sum(1, keepdim=True)
        return (seen >= MIN_MEASURED) | (every & (seen >= 2))

    @property
    def is_partial(self) -> bool:
        """Whether some experiment does not measure some component (:attr:`measured`)."""
        return not bool(self.measured.all())

    def with_initial_states(self, initial_states: torch.Tensor | None) -> Trajectories:
        """These trajectories with :attr:`initial_states` set (``None``: cleared)."""
        return dataclasses.replace(self, initial_states=initial_states)

    def reordered(self, state_names: Sequence[str]) -> Trajectories:
        """These trajectories with their state components in the order ``state_names``, a reordering of
        :attr:`state_names` (e.g. ``observed.reordered(system.state_names)``): the states, the initial states and
        the readout's weights follow their names."""
        want = _check_state_names(state_names, self.state_dim)
        order = _order_by_name(self.state_names, want)
        if order is None:
            raise InputError(
                f"state_names: expected a reordering of the state names {list(self.state_names)}, got {list(want)}"
            )
        readout = self.readout
        if readout is not None:  # its columns follow the states (a readout over named states: named as they are)
            named = None if readout.state_names is None else want
            readout = Readout(readout.matrix[:, order], readout.names, state_names=named)
        return self._renamed(want, order, readout)

    def with_state_names(self, state_names: Sequence[str]) -> Trajectories:
        """These trajectories with their state components renamed ``state_names``, in their order (the columns are
        the same; a readout over named states is renamed with them)."""
        names = _check_state_names(state_names, self.state_dim)
        readout = self.readout
        if readout is not None and readout.state_names is not None:
            readout = Readout(readout.matrix, readout.names, state_names=names)
        return self._renamed(names, list(range(self.state_dim)), readout)

    def _renamed(self, names: tuple[str, ...], order: list[int], readout) -> Trajectories:
        states = [y[:, order] for y in self.states] if self.is_ragged else self.states[..., order]
        return dataclasses.replace(
            self,
            times=list(self.times) if self.is_ragged else self.times,
            states=states,
            state_names=names,
            initial_states=None if self.initial_states is None else self.initial_states[:, order],
            readout=readout,
            readings=self._listed_readings() if self.is_ragged else self.readings,
        )

    @property
    def initial_conditions(self) -> torch.Tensor:
        """``(K, d)``: every experiment's first observed state (missing entries estimated as by :meth:`filled`), or
        :attr:`initial_states` when set. NaN where a component is never observed in an experiment and no initial
        states are set."""
        if self.initial_states is not None:
            return self.initial_states
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

    def flat_times(self) -> torch.Tensor:
        """``(N,)``: the time of every observed state, aligned with :meth:`flat_states`."""
        if self.is_ragged:
            return torch.cat(self.times)
        return self.time_grid.reshape(-1)

    def flat_controls(self) -> torch.Tensor | None:
        """``(N, m)``: the controls at every observed state, aligned with :meth:`flat_states` (``None`` without)."""
        values = self.control_values()
        if values is None:
            return None
        return torch.cat(values) if self.is_ragged else values.reshape(-1, values.shape[-1])

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
                    controls=None if self.controls is None else self.controls[idx],
                    initial_states=None if self.initial_states is None else self.initial_states[idx],
                    readout=self.readout,
                    readings=None if self.readings is None else torch.stack([self.readings[k] for k in idx]),
                ),
            )
            for _, idx in sorted(groups.items())
        ]

    def __len__(self) -> int:
        return self.num_experiments

    def __iter__(self):
        """Each experiment as a Trajectories of one (indexing refuses positions out of range: no IndexError ends
        the iteration)."""
        return (self[k] for k in range(self.num_experiments))

    def __getitem__(self, index) -> Trajectories:
        """A subset of experiments (int, slice, index list or boolean mask; at least one experiment)."""
        picked = check_selection(index, self.num_experiments)
        kept = dict(
            state_names=self.state_names,
            controls=None if self.controls is None else self.controls[picked],
            initial_states=None if self.initial_states is None else self.initial_states[picked],
            readout=self.readout,
        )
        if self.is_ragged:
            readings = None if self.readings is None else [self.readings[k] for k in picked]
            return Trajectories(
                [self.times[k] for k in picked], [self.states[k] for k in picked], readings=readings, **kept
            )
        times = self.times if self.times.dim() == 1 else self.times[picked]
        readings = None if self.readings is None else self.readings[picked]
        return Trajectories(times, self.states[picked], readings=readings, **kept)

    @classmethod
    def concatenate(cls, parts: Sequence[Trajectories]) -> Trajectories:
        """The experiments of ``parts`` (Trajectories over the same states, readout and kind of inputs), in order, as
        one (ragged when their lengths differ; the first part's dtype and device). States are matched by name (a part
        with the same names in another order is reordered); a part whose states are unnamed (``y0, y1, ...``) takes
        the others' names in order. Estimated initial states are kept only when every part has them."""
        return concatenate(cls, parts)

    def to(self, *args, **kwargs) -> Trajectories:
        """These trajectories on another device and/or in another real floating dtype (every field moved)."""
        check_to(args, kwargs, "Trajectories")

        def moved(x):
            if x is None:
                return None
            return [v.to(*args, **kwargs) for v in x] if isinstance(x, tuple) else x.to(*args, **kwargs)

        return Trajectories(
            moved(self.times),
            moved(self.states),
            state_names=self.state_names,
            controls=None if self.controls is None else self.controls.to(*args, **kwargs),
            initial_states=moved(self.initial_states),
            readout=None if self.readout is None else self.readout.to(*args, **kwargs),
            readings=moved(self.readings),
        )

    def control_values(self) -> torch.Tensor | tuple[torch.Tensor, ...] | None:
        """The controls at the observation times: ``(K, T, m)``, a tuple of ``(T_k, m)`` (ragged), or ``None``."""
        if self.controls is None:
            return None
        times, _, _ = self.padded()
        values = self.controls.at(times)
        if self.is_ragged:
            return tuple(values[k, :n] for k, n in enumerate(self.lengths))
        return values

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
        if missing:  # partial measurements: say which components some experiment does not measure
            absent = (~self.measured).sum(0).tolist()
            K = self.num_experiments
            parts = [f"{n} in {a} of {K}" for n, a in zip(self.state_names, absent, strict=True) if a]
            gaps += f", not measured: {'; '.join(parts)}" if parts else ""
        controls = "" if self.controls is None else f", controls {', '.join(self.controls.names)}"
        if self.readout is not None:
            controls += f", readings {'; '.join(self.readout.describe(self.state_names))}"
        return (
            f"Trajectories(K={self.num_experiments} experiment{'s' * (self.num_experiments != 1)}, "
            f"{count} on [{lo:.6g}, {hi:.6g}] ({grid}), "
            f"d={self.state_dim}{names}{gaps}{controls}, {str(self.dtype).removeprefix('torch.')}{device})"
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
        """Write to ``path``: an ``.npz`` archive, which keeps every field, or a text table with a header row.

        ``.npz``: the times, states (NaN where missing), :attr:`state_names`, the dtype, the controls (every
        profile's knots and values, their names and kind), the readout (weights, names, the states it reads) with
        its readings, and the initial states; ragged data as the concatenated rows and the lengths. :meth:`load`
        gives back every field as it was. Nothing in it needs unpickling; the column names are a table's, ignored
        here.

        Text tables: ``.csv`` (comma separated), ``.tsv`` (tab separated) or ``.txt`` (space separated), one row
        per experiment and time, columns ``experiment_column, time_column, *state_columns`` (state columns
        :attr:`state_names` by default; experiments numbered 0..K-1), then the readout's columns (its readings) and
        the controls' columns (each profile sampled at every row: the observation times and its knots). Values are
        written with full precision, so :meth:`load` with the same column names (or the defaults), the
        ``control_columns`` and the ``readout``, reads back the same times, states, readings and profiles (as
        float64). A missing entry is written as an empty cell (``NaN`` in a ``.txt`` table, whose cells are separated
        by spaces). A table cannot record what is not a column, so it refuses controls that are not piecewise
        constant (``kind="linear"``: read back as piecewise constant) and :attr:`initial_states`: save those to
        ``.npz``. Controls given as a function u(t) cannot be saved in any format (sample them first).
        """
        return _tables.write(
            self, path, time_column=time_column, experiment_column=experiment_column, state_columns=state_columns
        )

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        time_column: str = "time",
        experiment_column: str | None = "experiment",
        state_columns: Sequence[str] | None = None,
        control_columns: Sequence[str] | None = None,
        control_kind: str | None = None,
        readout: Readout | None = None,
    ) -> Trajectories:
        """Read trajectories from an ``.npz`` archive (as :meth:`save` writes) or a text table with a header row.

        An ``.npz`` archive (arrays ``times`` and ``states``, and the other fields :meth:`save` stores) gives back
        every field it holds; the column arguments are ignored for it. Text tables are UTF-8 ``.csv`` (comma
        separated), ``.tsv`` (tab separated) or ``.txt`` (whitespace separated), one row per experiment and time,
        columns in any order and rows in any order.

        Args:
            path: the file.
            time_column: name of the time column.
            experiment_column: name of the column labelling the experiments (numbers, sorted numerically, or any
                text, in order of first appearance). When the file has no such column (or ``None``), all rows are
                one experiment; a name other than the default that is not in the file is an error.
            state_columns: names of the state columns, in the order of the state components (default: every
                other column, in file order). They become :attr:`state_names`.
            control_columns: names of the columns holding the known input signals u(t) (a text table's only): each
                experiment's rows are the samples of its profile (:class:`~torchmisspec.signals.Controls`), known at
                every row, also where no state was measured (a dose given between measurements).
            control_kind: how a table's profiles run between their samples: ``"previous"`` (piecewise constant, the
                default) or ``"linear"``. An archive records its own kind; another one given here is refused.
            readout: measured combinations of the states (a text table's only; an ``.npz`` archive stores its
                own): the columns named by ``readout.names`` hold its :attr:`readings`. The states are
                ``state_columns`` (default ``readout.state_names``; a readout over named states is matched to them
                by name); a state with no column in the file was not measured on its own (all missing), as when
                only a combination of it is read.

        A state cell that is empty or reads ``NaN``, ``NA`` or ``N/A`` (any case) is a missing entry (see the class
        docstring); a missing time or experiment label is an error, and so is an experiment with no value at all in
        some state column. Each experiment's rows are sorted by time. The times come back shared ``(T,)`` when every
        experiment has the same grid, ``(K, T)`` when the experiments have equal lengths, and ragged (one tensor per
        experiment) when their lengths differ.

        Nothing is unpickled and no code can run. Raises :class:`InputError` for a missing, unreadable, non-UTF-8
        or malformed file (an ``.npz`` name on a single ``np.save`` array included), missing or duplicate columns,
        non-numeric or infinite cells, missing times or labels, or repeated (experiment, time) rows, and
        :class:`ShapeError` for rows of the wrong width, each naming what was expected and what the file holds.
        """
        columns = dict(time_column=time_column, experiment_column=experiment_column, state_columns=state_columns)
        reader = _tables.read if readout is None else partial(_tables.read_with_readout, readout=readout)
        return cls(**reader(path, control_columns=control_columns, control_kind=control_kind, **columns))
