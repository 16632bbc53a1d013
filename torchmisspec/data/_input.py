"""The checks of what ``Trajectories(times, states)`` is given: per-experiment (possibly ragged) lists, state names,
and times at which nothing was observed."""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import numpy as np
import torch

from .._errors import InputError, ShapeError
from .._validation import as_tensor, states_and_times


def _is_number(x) -> bool:
    return isinstance(x, numbers.Number) or (isinstance(x, (torch.Tensor, np.ndarray)) and x.ndim == 0)


def _describe_lengths(lengths: Sequence[int]) -> str:
    lo, hi = min(lengths), max(lengths)
    return f"{lo}" if lo == hi else f"{lo}..{hi}"


def _default_names(d: int) -> tuple[str, ...]:
    return tuple(f"y{i}" for i in range(d))


def _named(names) -> bool:
    """Whether ``names`` name states: given, and not the defaults ``y0, y1, ...`` that stand for no names."""
    return names is not None and tuple(names) != _default_names(len(names))


def _order_by_name(have: Sequence[str], want: Sequence[str]) -> list[int] | None:
    """The positions ``p`` with ``have[p[i]] == want[i]`` when ``want`` reorders ``have``; ``None`` otherwise."""
    have, want = list(have), list(want)
    if len(have) != len(want) or set(have) != set(want) or len(set(want)) != len(want):
        return None
    return [have.index(n) for n in want]


def check_named_as(state_names: Sequence[str], names: Sequence[str] | None, owner: str) -> None:
    """Refuse trajectories whose states ``state_names`` are named otherwise than ``names`` (``owner``'s, e.g. a
    system's): in another order, or other names. Names that are only the defaults ``y0, y1, ...`` (none given) on
    either side are positions, and pass."""
    if not _named(names) or not _named(state_names) or tuple(state_names) == tuple(names):
        return
    have, want = list(state_names), list(names)
    if _order_by_name(have, want) is not None:
        raise InputError(
            f"trajectories: expected the states in the order of {owner} {want}, got {have} (the same names in another "
            f"order); reorder the columns by name: trajectories.reordered({want})"
        )
    raise InputError(
        f"trajectories: expected states named as the states of {owner} {want}, got {have}; if the columns are those "
        f"states in that order, rename them (trajectories.with_state_names({want})), else load the right columns"
    )


def _check_distinct(names: Sequence[str], what: str, where: str) -> None:
    repeated = sorted({n for n in names if list(names).count(n) > 1})
    if repeated:
        raise InputError(f"{where}: expected distinct {what}, got {repeated} more than once (in {list(names)})")


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


def _check_apart(state_names: Sequence[str], controls, readout) -> None:
    """The states, the controls and the readings each named apart from the others (a table has one column each)."""
    control_names = () if controls is None else tuple(controls.names)
    reading_names = () if readout is None else tuple(readout.names)
    for what, names, others, other in (
        ("controls", control_names, state_names, "states"),
        ("readout", reading_names, state_names, "states"),
        ("readout", reading_names, control_names, "controls"),
    ):
        clash = [n for n in names if n in others]
        if clash:
            kind = "controls" if what == "controls" else "readings"
            raise InputError(
                f"{what}: expected {kind} named apart from the {other}, got {clash} in both ({other} {list(others)}, "
                f"{kind} {list(names)}); rename one of them"
            )


def _drop_empty_rows(states, times):
    """Drop the times at which nothing was observed (an experiment with no observed value at all is refused)."""
    per = list(states) if isinstance(states, tuple) else list(states.unbind(0))
    for k, y in enumerate(per):
        if not bool(torch.isfinite(y).any()):
            raise InputError(
                f"states: expected at least one observed value in every experiment, got none in experiment {k} (all "
                f"{y.numel()} entries missing); drop that experiment"
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
                f"times: expected experiments of equal length for one shared (T,) array, got lengths {lengths}; pass a "
                "list with one time array per experiment"
            )
        stacked, shared = states_and_times(torch.stack(states), shared, missing=True)
        return stacked, shared
    if len(set(lengths)) == 1:
        return torch.stack(states), torch.stack(times_list)
    return tuple(states), tuple(times_list)
