"""Measured linear combinations of the states: :class:`Readout` (an observation matrix H).

An instrument often reads a combination of states rather than one: the total of free and bound protein, an
absorbance weighting two species by their extinction coefficients, reported cases as a fraction of the infected.
A :class:`Readout` names m such quantities and their weights, z = H y with H ``(m, d)``; its values in an experiment
(*readings*) sit beside the directly measured states in :class:`~torchmisspec.Trajectories`
(``Trajectories(times, states, readout=..., readings=...)``), NaN where a quantity was not read.

Readings cannot give derivatives of a single state, so a component seen only through a readout counts as not
measured (:attr:`Trajectories.measured <torchmisspec.Trajectories.measured>`), and the correction is learned through
the ODE, where the model's path is read out as H y and compared with the readings
(:mod:`torchmisspec.learning.refinement.partial`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence

import torch

from .._errors import InputError, ShapeError
from .._validation import as_tensor, check_real, check_to
from ._input import _check_distinct, _check_state_names, _named, _order_by_name

__all__ = ["Readout"]

_TERM = re.compile(r"\s*([+-]?)\s*(?:(\d+(?:\.\d*)?(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)\s*\*?\s*)?([^\s+\-*]+)\s*")


class Readout:
    """m measured linear combinations of the d states: reading i is ``sum_j matrix[i, j] y_j``.

    ``Readout(matrix, names, state_names=None)``:

    * ``matrix``: ``(m, d)`` finite weights, every row with a nonzero weight;
    * ``names``: the m quantities' names (the columns of a lab's table that hold them);
    * ``state_names``: the d states' names (for messages and :meth:`from_weights`; optional).

    :meth:`from_weights` builds one from ``{"total": {"free": 1, "bound": 1}}``, :meth:`parse` from the command
    line's ``"total = free + bound"``. Calling a readout on states ``(..., d)`` gives the readings ``(..., m)``.
    """

    def __init__(self, matrix, names: Sequence[str], *, state_names: Sequence[str] | None = None) -> None:
        H = as_tensor(matrix, "matrix")
        if not H.is_floating_point():
            H = H.to(torch.get_default_dtype())
        if H.dim() != 2 or H.shape[0] == 0 or H.shape[1] == 0:
            raise ShapeError(f"matrix: expected an (m, d) array of weights (one row per reading), got {tuple(H.shape)}")
        if not bool(torch.isfinite(H).all()):
            raise InputError("matrix: expected finite weights, got NaN or inf")
        empty = [i for i in range(H.shape[0]) if not bool((H[i] != 0).any())]
        if empty:
            raise InputError(
                f"matrix: expected a nonzero weight in every row (a reading of something), got rows {empty} all 0"
            )
        if isinstance(names, str) or not isinstance(names, Iterable):
            raise InputError(f"names: expected a list of {H.shape[0]} non-empty strings, got {names!r:.120}")
        if not all(isinstance(n, str) and n.strip() for n in names):
            raise InputError(f"names: expected a list of {H.shape[0]} non-empty strings, got {names!r:.120}")
        names = tuple(names)
        if len(names) != H.shape[0]:
            raise ShapeError(f"names: expected {H.shape[0]} names (one per row of matrix), got {len(names)}")
        _check_distinct(names, "readout names", "names")
        if state_names is not None:
            state_names = _check_state_names(state_names, H.shape[1])  # one per column of the matrix
            clash = [n for n in names if n in state_names]
            if clash:
                raise InputError(f"names: expected readings named apart from the states, got {clash} in both")
        self.matrix = H
        self.names = names
        self.state_names = state_names

    @classmethod
    def from_weights(cls, weights: Mapping[str, Mapping[str, float]], state_names: Sequence[str]) -> Readout:
        """``{reading: {state: weight, ...}, ...}`` over the states ``state_names`` (unnamed states weigh 0)."""
        if not isinstance(weights, Mapping) or not weights:
            raise InputError(
                f"weights: expected a mapping {{reading: {{state: weight}}}}, got {type(weights).__name__}"
            )
        state_names = _listed_states(state_names)
        H = torch.zeros(len(weights), len(state_names), dtype=torch.float64)
        for i, (name, row) in enumerate(weights.items()):
            if not isinstance(row, Mapping) or not row:
                raise InputError(f"weights[{name!r}]: expected a mapping {{state: weight}}, got {row!r:.80}")
            for state, w in row.items():
                if state not in state_names:
                    raise InputError(f"weights[{name!r}]: expected states among {list(state_names)}, got {state!r}")
                H[i, state_names.index(state)] += check_real(w, f"weights[{name!r}][{state!r}]")
        return cls(H, list(weights), state_names=state_names)

    @classmethod
    def parse(cls, definitions: Sequence[str], state_names: Sequence[str]) -> Readout:
        """Readings written as ``"name = w1*state1 + state2 - 0.5 state3"`` (one string per reading; a weight is a
        plain number, 1 when left out). Nothing is evaluated: each term is a number and a state's name."""
        state_names = _listed_states(state_names)
        if isinstance(definitions, str):
            definitions = [definitions]
        if not isinstance(definitions, Sequence) or not definitions or not all(isinstance(t, str) for t in definitions):
            raise InputError(
                "definitions: expected a list of strings 'name = weight*state + ...' (e.g. ['total = free + bound']), "
                f"got {definitions!r:.80}"
            )
        weights: dict[str, dict[str, float]] = {}
        for text in definitions:
            name, eq, expression = str(text).partition("=")
            name = name.strip()
            if not eq or not name or not expression.strip():
                raise InputError(
                    f"readout: expected 'name = weight*state + ...' (e.g. 'total = free + bound'), got {text!r}"
                )
            row: dict[str, float] = {}
            rest = expression.strip()
            position = 0
            while position < len(rest):
                match = _TERM.match(rest, position)
                if match is None or match.end() == position or (position > 0 and not match.group(1)):
                    raise InputError(
                        f"readout {name!r}: expected terms 'weight*state' joined by + or -, got {expression.strip()!r} "
                        f"(states: {', '.join(state_names)})"
                    )
                sign = -1.0 if match.group(1) == "-" else 1.0
                weight = float(match.group(2)) if match.group(2) else 1.0
                row[match.group(3)] = row.get(match.group(3), 0.0) + sign * weight
                position = match.end()
            if name in weights:
                raise InputError(f"readout: expected each reading defined once, got {name!r} twice")
            weights[name] = row
        return cls.from_weights(weights, state_names)

    @property
    def num_readings(self) -> int:
        """m, the number of quantities read."""
        return self.matrix.shape[0]

    @property
    def state_dim(self) -> int:
        """d, the number of states read from."""
        return self.matrix.shape[1]

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """The readings ``(..., m)`` of states ``(..., d)``: a real floating tensor (in the readout's state order,
        :attr:`state_names`)."""
        d = self.state_dim
        if not isinstance(states, torch.Tensor):
            raise InputError(
                f"states: expected a torch tensor of states (..., {d}), got {type(states).__name__}; pass "
                "torch.as_tensor(states, dtype=torch.float64)"
            )
        if not states.is_floating_point():  # integers would truncate the weights, complex lose its imaginary part
            raise InputError(
                f"states: expected real floating states, got dtype {states.dtype}; convert them (states.double()) "
                "or, for complex states, read their real and imaginary parts apart"
            )
        if states.dim() < 1 or states.shape[-1] != d:
            names = "" if self.state_names is None else f" ({', '.join(self.state_names)})"
            raise ShapeError(f"states: expected states (..., {d}){names}, got shape {tuple(states.shape)}")
        return states @ self.matrix.to(states).T

    def for_states(self, state_names: Sequence[str] | None, owner: str = "the trajectories") -> Readout:
        """This readout over states named ``state_names`` in that order: its weights' columns matched by name when it
        names its states in another order; itself when it or ``state_names`` names none (the defaults ``y0, y1,
        ...`` name none: the columns are then taken in order). Other names than its own are refused."""
        if state_names is not None:
            state_names = _check_state_names(state_names, self.state_dim)
        if self.state_names is None or not _named(state_names) or tuple(state_names) == self.state_names:
            return self
        want = tuple(state_names)
        order = _order_by_name(self.state_names, want)
        if order is None:
            raise InputError(
                f"readout: expected weights over the states {list(want)} (of {owner}), got a readout over "
                f"{list(self.state_names)} ({'; '.join(self.describe())}); build it over those states' names, e.g. "
                f"Readout.parse([...], {list(want)})"
            )
        return Readout(self.matrix[:, order], self.names, state_names=want)

    def to(self, *args, **kwargs) -> Readout:
        """This readout's weights on another device and/or in another real floating dtype."""
        check_to(args, kwargs, "Readout")
        return Readout(self.matrix.to(*args, **kwargs), self.names, state_names=self.state_names)

    def describe(self, state_names: Sequence[str] | None = None) -> list[str]:
        """Each reading as ``"name = w*state + ..."``."""
        if state_names is not None:
            state_names = _check_state_names(state_names, self.state_dim)
        names = state_names or self.state_names or tuple(f"y{j}" for j in range(self.state_dim))
        out = []
        for name, row in zip(self.names, self.matrix.tolist(), strict=True):
            terms = [(w, s) for w, s in zip(row, names, strict=True) if w != 0]
            text = " ".join(
                f"{'-' if w < 0 else '+'} {'' if abs(w) == 1 else f'{abs(w):g}*'}{s}" for w, s in terms
            ).removeprefix("+ ")
            out.append(f"{name} = {text}")
        return out

    def __eq__(self, other) -> bool:
        """The same readings with the same weights on the same states (matched by name when both name them)."""
        if not isinstance(other, Readout) or self.names != other.names or self.matrix.shape != other.matrix.shape:
            return False
        if self.state_names is not None and other.state_names is not None:
            if _order_by_name(other.state_names, self.state_names) is None:
                return False
            other = other.for_states(self.state_names)
        return bool((self.matrix.cpu().double() == other.matrix.cpu().double()).all())

    def __repr__(self) -> str:
        return f"Readout({'; '.join(self.describe())})"


def _listed_states(state_names) -> tuple[str, ...]:
    """The states' names a readout is written over: a list of distinct non-empty strings."""
    if isinstance(state_names, str) or not isinstance(state_names, Sequence) or not state_names:
        raise InputError(f"state_names: expected a list of the states' names, got {state_names!r:.80}")
    return _check_state_names(state_names, len(state_names))


def check_readout(readout, readings) -> int:
    """The number of readings m (0 without a readout); a readout needs its values and the values a readout."""
    if readout is None and readings is None:
        return 0
    if readout is None:
        raise InputError(
            "readings: expected a readout saying what they measure (readout=Readout(matrix, names)), got none"
        )
    if not isinstance(readout, Readout):
        raise InputError(f"readout: expected a torchmisspec.data.Readout or None, got {type(readout).__name__}")
    if readings is None:
        raise InputError(
            f"readings: expected the values of the readout ({', '.join(readout.names)}), laid out as the states with "
            f"{readout.num_readings} columns, got None (trajectories.with_readout(readout) reads them off the states)"
        )
    return readout.num_readings


def joined(states, readings):
    """The states and the readings side by side (one array per experiment for lists), for the checks of both."""
    if isinstance(states, (list, tuple)) != isinstance(readings, (list, tuple)):
        raise InputError(
            "readings: expected the same layout as the states (one array for equal lengths, a list of per-experiment "
            f"arrays for ragged data), got states as {type(states).__name__} and readings as {type(readings).__name__}"
        )
    if isinstance(states, (list, tuple)):
        if len(states) != len(readings):
            raise ShapeError(f"readings: expected {len(states)} arrays (one per experiment), got {len(readings)}")
        pairs = [
            (as_tensor(y, f"states[{k}]"), as_tensor(r, f"readings[{k}]"))
            for k, (y, r) in enumerate(zip(states, readings, strict=True))
        ]
        for k, (y, r) in enumerate(pairs):
            if y.dim() != 2 or r.dim() != 2 or y.shape[0] != r.shape[0]:
                raise ShapeError(
                    f"readings[{k}]: expected ({y.shape[0]}, m) values (a row per time of states[{k}]), got shape "
                    f"{tuple(r.shape)}"
                )
        return [torch.cat([y, r.to(y)], dim=-1) for y, r in pairs]
    y, r = as_tensor(states, "states"), as_tensor(readings, "readings")
    if y.dim() < 2 or r.shape[:-1] != y.shape[:-1]:
        raise ShapeError(
            f"readings: expected {(*y.shape[:-1], 'm')} values (a row per row of states), got shape {tuple(r.shape)}"
        )
    return torch.cat([y, r.to(y)], dim=-1)
