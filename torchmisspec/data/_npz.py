"""Trajectories in ``.npz`` archives, every field kept (see :meth:`Trajectories.save
<torchmisspec.data.Trajectories.save>`), and the safe reading of ``.npz`` / ``.npy`` files the command line shares."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch

from .._errors import InputError, ShapeError
from .._validation import as_tensor, unreadable, writing
from ..signals import KINDS, Controls
from ._readout import Readout

#: What reading a damaged or foreign file can raise (a truncated member, bad compressed data, an encrypted or
#: unsupported zip entry, a pickled object refused).
_UNREADABLE = (
    OSError,
    ValueError,
    EOFError,
    KeyError,
    RuntimeError,
    NotImplementedError,
    zipfile.BadZipFile,
    zlib.error,
)

_STORED_DTYPES = {
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float32": torch.float32,
    "float64": torch.float64,
}


def _why(exc: BaseException) -> str:
    """Why a file could not be read: numpy's own words, unless they advise loading it unsafely (then
    :func:`~torchmisspec._validation.unreadable`'s)."""
    text = str(exc).splitlines()[0] if str(exc) else ""
    if any(advice in text for advice in ("unsafe", "allow_pickle=True", "pickle.load", "weights_only")):
        return unreadable(exc)
    return f"{type(exc).__name__}: {text[:160]}" if text else type(exc).__name__


def npz_arrays(path: str | Path, where: str) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` archive, nothing unpickled; :class:`InputError` (``where``: the option or argument
    named) for a file that is not such an archive: damaged, a single ``np.save`` array, members that are not arrays."""
    what = f"{where}: expected an .npz archive of named numeric arrays (np.savez; no pickled objects) in {str(path)!r}"
    try:
        data = np.load(path, allow_pickle=False)
    except _UNREADABLE as exc:
        raise InputError(f"{what}, got a file that could not be read as one ({_why(exc)})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputError(
            f"{what}, got a single array (np.save's .npy format), not an .npz archive; save it with "
            "np.savez(path, name=array), or name the file .npy where one array is accepted"
        )
    try:
        with data:
            arrays = {key: data[key] for key in data.files}
    except _UNREADABLE as exc:
        raise InputError(f"{what}, got a file that could not be read as one ({_why(exc)})") from exc
    odd = [key for key, value in arrays.items() if not isinstance(value, np.ndarray)]
    if odd:
        raise InputError(f"{what}, got members {odd} that could not be read as one (they are not NumPy arrays)")
    return arrays


def npy_array(path: str | Path, where: str) -> np.ndarray:
    """The array of an ``.npy`` file, nothing unpickled (:class:`InputError` otherwise, as :func:`npz_arrays`)."""
    what = f"{where}: expected an .npy array (np.save; no pickled objects) in {str(path)!r}"
    try:
        data = np.load(path, allow_pickle=False)
    except _UNREADABLE as exc:
        raise InputError(f"{what}, got a file that could not be read as one ({_why(exc)})") from exc
    if not isinstance(data, np.ndarray):
        data.close()
        raise InputError(f"{what}, got an .npz archive (np.savez) under an .npy name; name it .npz")
    return data


def _numpy(t: torch.Tensor) -> np.ndarray:
    """A tensor as numpy (bfloat16, which numpy lacks, as float32: exact)."""
    t = t.detach().cpu()
    return (t.float() if t.dtype == torch.bfloat16 else t).numpy()


def _strings(names) -> np.ndarray:
    return np.asarray(list(names), dtype=np.str_)


def write_npz(trajectories, path: Path) -> Path:
    """Every field of ``trajectories`` as arrays (ragged data concatenated, with the lengths: no object arrays)."""
    ragged = trajectories.is_ragged
    arrays = {
        "times": _numpy(torch.cat(trajectories.times) if ragged else trajectories.times),
        "states": _numpy(trajectories.flat_states() if ragged else trajectories.states),
        "state_names": _strings(trajectories.state_names),
        "dtype": np.asarray(str(trajectories.dtype).removeprefix("torch.")),  # restored by read_npz
    }
    if ragged:
        arrays["lengths"] = np.asarray(trajectories.lengths, dtype=np.int64)
    readout = trajectories.readout
    if readout is not None:  # the readout's weights and names, and its values laid out as the states
        readings = torch.cat(trajectories.readings) if ragged else trajectories.readings
        arrays.update(readout_matrix=_numpy(readout.matrix), readout_names=_strings(readout.names))
        arrays["readings"] = _numpy(readings)
        if readout.state_names is not None:
            arrays["readout_state_names"] = _strings(readout.state_names)
    controls = trajectories.controls
    if controls is not None:  # padded samples with every profile's length, the names and the kind
        arrays.update(
            control_knots=_numpy(controls.knots),
            control_values=_numpy(controls.values),
            control_lengths=np.asarray(controls.lengths.tolist(), dtype=np.int64),
            control_names=_strings(controls.names),
            control_kind=np.asarray(controls.kind),
        )
    if trajectories.initial_states is not None:
        arrays["initial_states"] = _numpy(trajectories.initial_states)
    with writing(path):
        np.savez(path, **arrays)
    return path


def read_npz(path: Path, control_kind: str | None) -> dict:
    """The fields of :class:`Trajectories` from an archive :func:`write_npz` wrote (older ones hold fewer)."""
    data = npz_arrays(path, "path")
    missing = {"times", "states"} - set(data)
    if missing:
        raise InputError(
            f"{path}: expected arrays 'times' and 'states', got {sorted(data)} (missing {sorted(missing)})"
        )
    names = data.get("state_names")
    if names is not None:
        names = _names(path, "state_names", names)
    dtype = _stored_dtype(path, data.get("dtype"))
    lengths = data.get("lengths")
    if lengths is not None:
        times, states = _split_ragged(path, data["times"], data["states"], lengths)
    else:
        times, states = as_tensor(data["times"], f"{path}: times"), as_tensor(data["states"], f"{path}: states")
    readout = _npz_readout(path, data, lengths)
    initial = data.get("initial_states")
    fields = dict(
        times=times,
        states=states,
        state_names=names,
        controls=_npz_controls(path, data, control_kind),
        initial_states=None if initial is None else as_tensor(initial, f"{path}: initial_states"),
        readout=None if readout is None else readout[0],
        readings=None if readout is None else readout[1],
    )
    if dtype is not None:  # the dtype the trajectories were saved in
        for key in ("times", "states", "readings", "initial_states"):
            fields[key] = _cast(fields[key], dtype)
    return fields


def _names(path: Path, key: str, names: np.ndarray) -> list[str]:
    if names.dtype.kind != "U" or names.ndim != 1:
        raise InputError(f"{path}: expected {key!r} to be a 1-D array of strings, got {names!r:.80}")
    return names.tolist()


def _stored_dtype(path: Path, stored) -> torch.dtype | None:
    """The dtype an archive records (``None`` for older files: float64, or the arrays' own)."""
    if stored is None:
        return None
    name = str(stored)
    if stored.ndim != 0 or name not in _STORED_DTYPES:
        raise InputError(f"{path}: expected 'dtype' to name one of {sorted(_STORED_DTYPES)}, got {name!r:.40}")
    return _STORED_DTYPES[name]


def _cast(x, dtype: torch.dtype):
    if x is None:
        return None
    return [v.to(dtype) for v in x] if isinstance(x, (list, tuple)) else x.to(dtype)


def _split_ragged(path: Path, times: np.ndarray, states: np.ndarray, lengths: np.ndarray) -> tuple[list, list]:
    """Per-experiment lists from a ragged archive (concatenated times and states plus the lengths)."""
    lengths = _lengths(path, "lengths", lengths)
    if times.ndim != 1 or states.ndim != 2 or len(times) != len(states) or len(times) != int(lengths.sum()):
        raise ShapeError(
            f"{path}: expected ragged arrays times (N,) and states (N, d) with N = sum(lengths) = "
            f"{int(lengths.sum())}, got times {times.shape} and states {states.shape}"
        )
    cuts = np.cumsum(lengths)[:-1]
    times_list = [as_tensor(t, f"{path}: times") for t in np.split(times, cuts)]
    states_list = [as_tensor(y, f"{path}: states") for y in np.split(states, cuts)]
    return times_list, states_list


def _lengths(path: Path, key: str, lengths: np.ndarray) -> np.ndarray:
    if lengths.dtype.kind not in "iu" or lengths.ndim != 1 or lengths.size == 0 or (lengths < 1).any():
        raise InputError(f"{path}: expected {key!r} to be a 1-D array of positive integers, got {lengths!r:.80}")
    return lengths


def _npz_readout(path: Path, data: dict, lengths):
    """``(Readout, readings)`` from an archive's readout arrays (``None`` without them)."""
    keys = {"readout_matrix", "readout_names", "readings"}
    if not keys & set(data):
        return None
    if not keys <= set(data):
        raise InputError(
            f"{path}: expected the arrays readout_matrix, readout_names and readings together, got "
            f"{sorted(keys & set(data))}"
        )
    names = _names(path, "readout_names", data["readout_names"])
    # older archives name no readout states: the trajectories' own, as they were saved
    over = data.get("readout_state_names", data.get("state_names"))
    over = None if over is None else _names(path, "readout_state_names", over)
    readout = Readout(as_tensor(data["readout_matrix"], f"{path}: readout_matrix"), names, state_names=over)
    readings = as_tensor(data["readings"], f"{path}: readings")
    if lengths is not None:
        if readings.dim() != 2 or readings.shape[0] != int(np.asarray(lengths).sum()):
            raise ShapeError(f"{path}: expected readings (N, m) with N = sum(lengths), got {tuple(readings.shape)}")
        readings = list(readings.split(np.asarray(lengths).tolist()))
    return readout, readings


def _npz_controls(path: Path, data: dict, control_kind: str | None) -> Controls | None:
    """The :class:`Controls` an archive holds (``None`` without); ``control_kind``, when given, must be theirs."""
    keys = {"control_knots", "control_values", "control_lengths", "control_names", "control_kind"}
    if not keys & set(data):
        return None
    if not keys <= set(data):
        raise InputError(f"{path}: expected the arrays {sorted(keys)} together, got {sorted(keys & set(data))}")
    kind = str(data["control_kind"])
    if data["control_kind"].ndim != 0 or kind not in KINDS:
        raise InputError(f"{path}: expected 'control_kind' to be one of {KINDS}, got {kind!r:.40}")
    if control_kind is not None and control_kind != kind:
        raise InputError(
            f"control_kind: expected the archive's own kind {kind!r} (an .npz archive records how its controls run "
            f"between their samples), got {control_kind!r}; leave control_kind out"
        )
    knots = as_tensor(data["control_knots"], f"{path}: control_knots")
    values = as_tensor(data["control_values"], f"{path}: control_values")
    lengths = _lengths(path, "control_lengths", data["control_lengths"])
    if knots.dim() != 2 or values.dim() != 3 or knots.shape != values.shape[:2] or len(lengths) != len(knots):
        raise ShapeError(
            f"{path}: expected control_knots (K, S), control_values (K, S, m) and control_lengths (K,), got "
            f"{tuple(knots.shape)}, {tuple(values.shape)} and {lengths.shape}"
        )
    if int(lengths.max()) > knots.shape[1]:
        raise ShapeError(f"{path}: expected control_lengths of at most {knots.shape[1]}, got {lengths.tolist()}")
    n = lengths.tolist()
    names = _names(path, "control_names", data["control_names"])
    knots_list = [knots[k, : n[k]] for k in range(len(n))]
    return Controls(knots_list, [values[k, : n[k]] for k in range(len(n))], kind=kind, names=names)
