"""Experiments put together and compared: :func:`concatenate` (the experiments of several
:class:`~torchmisspec.Trajectories`, in order: :meth:`Trajectories.concatenate
<torchmisspec.Trajectories.concatenate>`) and :func:`known_experiments` (which of some experiments are already among
others: a campaign counts each experiment once)."""

from __future__ import annotations

import torch

from .._errors import InputError
from ..signals import Controls
from ._input import _default_names


def concatenate(cls, parts):
    """The experiments of ``parts`` as one ``cls`` (:meth:`Trajectories.concatenate
    <torchmisspec.Trajectories.concatenate>`)."""
    if not isinstance(parts, (list, tuple)) or not parts or not all(isinstance(p, cls) for p in parts):
        got = type(parts).__name__ if not isinstance(parts, (list, tuple)) else [type(p).__name__ for p in parts]
        raise InputError(f"parts: expected a non-empty list of Trajectories, got {got}")
    parts = aligned(parts)
    first = parts[0]
    every = [e for p in parts for e in p.experiments()]
    readings = None if first.readout is None else [r for p in parts for r in readings_of(p)]
    y0 = None
    if all(p.initial_states is not None for p in parts):
        y0 = torch.cat([p.initial_states for p in parts])
    return cls(
        [t for t, _ in every], [y for _, y in every], state_names=first.state_names,
        controls=joined_controls(parts), initial_states=y0, readout=first.readout, readings=readings,
    )  # fmt: skip


def aligned(parts) -> list:
    """``parts`` (a non-empty list of :class:`~torchmisspec.Trajectories` over the same states, readout and kind of
    inputs) in the first part's dtype and device, over one set of state names: a part with the same names in another
    order is reordered; a part whose states are unnamed (``y0, y1, ...``) takes the others' names in order; other
    names, another readout, or inputs in some parts only are refused."""
    dd = {"dtype": parts[0].dtype, "device": parts[0].device}
    names = next((p.state_names for p in parts if not _unnamed(p)), parts[0].state_names)
    parts = [_named(p.to(**dd), names, k) for k, p in enumerate(parts)]
    for k, p in enumerate(parts[1:], start=1):
        _check_alike(parts[0], p, k)
    return parts


def joined_controls(parts) -> Controls | None:
    """The input profiles of every experiment of the aligned ``parts`` (``None`` without inputs)."""
    return None if parts[0].controls is None else _controls([p.controls for p in parts])


def known_experiments(trajectories, known) -> list[bool]:
    """For each experiment of ``trajectories``, whether ``known`` (a :class:`~torchmisspec.Trajectories` or ``None``)
    holds one with the same times, the same states (the same entries missing) and the same readings."""
    if known is None:
        return [False] * trajectories.num_experiments
    trajectories = _named(trajectories, known.state_names, 1)  # compared state by state
    held = [_key(known, k) for k in range(known.num_experiments)]
    return [any(_same(_key(trajectories, k), h) for h in held) for k in range(trajectories.num_experiments)]


def _unnamed(traj) -> bool:
    return traj.state_names == _default_names(traj.state_dim)


def _named(traj, names: tuple[str, ...], k: int):
    """``traj`` over the states ``names``: as it is, reordered by name, or (its states unnamed: ``y0, y1, ...``)
    named in order; states named otherwise are refused."""
    if traj.state_names == names:
        return traj
    if sorted(traj.state_names) == sorted(names):
        return traj.reordered(names)
    if _unnamed(traj):
        return traj.with_state_names(names)
    raise InputError(
        f"parts[{k}]: expected the states {list(names)} (in any order, or unnamed), got {list(traj.state_names)}: "
        "rename them (Trajectories.with_state_names)"
    )


def _check_alike(first, other, k: int) -> None:
    if (other.readout is None) != (first.readout is None) or (
        first.readout is not None and not torch.equal(first.readout.matrix, other.readout.to(first.dtype).matrix)
    ):
        raise InputError(f"parts[{k}]: expected the readout of parts[0] ({first.readout!r}), got {other.readout!r}")
    if (other.controls is None) != (first.controls is None):
        has = "with" if first.controls is not None else "without"
        raise InputError(f"parts[{k}]: expected experiments {has} input profiles, as parts[0], got the other kind")


def readings_of(p) -> list[torch.Tensor]:
    """Each experiment's readings ``(T_k, m)`` of ``p`` (which has a readout)."""
    return list(p.readings) if isinstance(p.readings, tuple) else list(p.readings.unbind(0))


def _controls(profiles: list[Controls]) -> Controls:
    first = profiles[0]
    if any(c.is_function for c in profiles):
        raise InputError("controls: expected input profiles as samples to put together, got a function u(t)")
    if any(c.kind != first.kind or tuple(c.names) != tuple(first.names) for c in profiles):
        raise InputError(
            f"controls: expected profiles of one kind and names ({first.kind!r}, {list(first.names)}), got "
            f"{[(c.kind, list(c.names)) for c in profiles]}"
        )
    pairs = [pair for c in profiles for pair in c.profiles()]
    return Controls([t for t, _ in pairs], [v for _, v in pairs], kind=first.kind, names=first.names)


def _key(traj, k: int) -> tuple:
    t, y = traj.experiments()[k]
    r = None if traj.readings is None else readings_of(traj)[k]
    return t.detach().cpu().double(), y.detach().cpu().double(), None if r is None else r.detach().cpu().double()


def _same(a: tuple, b: tuple) -> bool:
    return all(_equal(x, y) for x, y in zip(a, b, strict=True))


def _equal(x, y) -> bool:
    if x is None or y is None:
        return x is None and y is None
    if x.shape != y.shape:
        return False
    nan = torch.isnan(x)
    return bool(torch.equal(nan, torch.isnan(y)) and torch.equal(x[~nan], y[~nan]))
