"""Private input checks shared by the public functions (raise, never assert)."""

from __future__ import annotations

import contextlib
import math
import numbers
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from ._errors import InputError, NumericalWarning, ShapeError, warn

DEFAULT_DTYPE = torch.float64


_REAL_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


def as_tensor(x, name: str, *, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Convert ``x`` to a real floating tensor (float64 unless it already is floating or ``dtype`` is given).

    Integers are converted; complex numbers, booleans, strings and objects are refused with :class:`InputError`
    (casting them would silently drop the imaginary part or invent numbers).
    """
    if not isinstance(x, torch.Tensor):
        if isinstance(x, (str, bytes)) or (isinstance(x, bool)):
            raise InputError(f"{name}: expected an array of real numbers, got {type(x).__name__} {x!r:.60}")
        try:
            arr = np.asarray(x)
        except (TypeError, ValueError, OverflowError) as exc:
            raise InputError(f"{name}: expected an array of real numbers, got {type(x).__name__} ({exc})") from exc
        if arr.dtype.kind not in "iuf":
            raise InputError(
                f"{name}: expected an array of real numbers, got {type(x).__name__} of dtype {arr.dtype} "
                f"(kind {arr.dtype.kind!r}: complex, boolean, text and object arrays are refused)"
            )
        try:
            x = torch.as_tensor(arr.astype(np.float64) if arr.dtype.kind in "iu" or arr.dtype == np.float16 else arr)
        except (TypeError, ValueError, RuntimeError) as exc:  # pragma: no cover - numpy numbers always convert
            raise InputError(f"{name}: expected an array of real numbers, got dtype {arr.dtype} ({exc})") from exc
        if dtype is None and not x.is_floating_point():
            x = x.to(DEFAULT_DTYPE)
        if dtype is None and x.dtype == torch.float32 and arr.dtype != np.float32:
            x = x.to(DEFAULT_DTYPE)
    if x.is_complex() or x.dtype == torch.bool:
        raise InputError(f"{name}: expected real numbers, got a tensor of dtype {x.dtype}")
    t = x
    if dtype is not None or not t.is_floating_point():
        t = t.to(dtype=dtype or DEFAULT_DTYPE)
    if device is not None:
        t = t.to(device)
    return t


def check_device(device, name: str = "device") -> torch.device:
    """``None`` (the CPU), a ``torch.device`` or its name (``"cpu"``, ``"cuda"``, ``"cuda:1"``), available here."""
    if device is None:
        return torch.device("cpu")
    if not isinstance(device, (str, torch.device)):
        raise InputError(
            f"{name}: expected a torch.device or a device name such as 'cpu' or 'cuda', got {device!r:.60} "
            f"({type(device).__name__})"
        )
    try:
        out = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise InputError(
            f"{name}: expected a device name such as 'cpu', 'cuda' or 'cuda:1', got {device!r:.60}"
        ) from None
    if out.type not in ("cpu", "cuda", "mps"):  # 'meta' holds no values; the others are not supported
        raise InputError(f"{name}: expected a device that holds values, 'cpu' or 'cuda', got {str(out)!r}")
    if out.type == "mps" and not torch.backends.mps.is_available():
        raise InputError(f"{name}: expected a device this machine has, got 'mps', which is not available; use 'cpu'")
    if out.type == "cuda" and not torch.cuda.is_available():
        raise InputError(
            f"{name}: expected a device this machine has, got {str(out)!r}: CUDA is not available; use 'cpu'"
        )
    if out.type == "cuda" and out.index is not None and out.index >= torch.cuda.device_count():
        raise InputError(f"{name}: expected one of the {torch.cuda.device_count()} CUDA devices, got {str(out)!r}")
    return out


def check_path(path, name: str = "path"):
    """A file name: a string or an ``os.PathLike`` (a number or ``None`` is refused before any file is touched)."""
    if isinstance(path, str) or isinstance(path, os.PathLike):
        return path
    raise InputError(f"{name}: expected a file name (str or pathlib.Path), got {path!r:.60} ({type(path).__name__})")


def check_writable(path, name: str = "path") -> Path:
    """A file name to write: a string or ``os.PathLike``, not a folder, in a folder that exists."""
    path = Path(check_path(path, name))
    if path.is_dir():
        raise InputError(f"{name}: expected a file name, got the folder {str(path)!r}")
    if not path.parent.is_dir():
        raise InputError(
            f"{name}: expected a file in an existing folder, got {str(path)!r} (no folder {str(path.parent)!r})"
        )
    return path


@contextlib.contextmanager
def writing(path, name: str = "path"):
    """Around the write of ``path``: a failure of the file system (no permission, a full disk, a read-only or
    special folder) becomes an :class:`InputError` naming the file, not the OSError of the writer."""
    try:
        yield
    except OSError as exc:
        raise InputError(f"{name}: expected a file that can be written, got {str(path)!r} ({unreadable(exc)})") from exc
    except RuntimeError as exc:  # torch.save reports a file it cannot open as a RuntimeError
        if "open file failed" not in str(exc) and "No such file" not in str(exc):
            raise
        raise InputError(f"{name}: expected a file that can be written, got {str(path)!r} ({unreadable(exc)})") from exc


def unreadable(exc: BaseException) -> str:
    """Why a file could not be read, for a message: the error's type and first line, without a reader's advice to
    load it unsafely (torch and numpy suggest turning off their safe modes; a file is never unpickled here)."""
    text = str(exc).splitlines()[0] if str(exc) else ""
    if "pickle" in text.lower() or "weights_only" in text:
        return f"{type(exc).__name__}: it holds pickled Python objects or is not such a file; nothing is unpickled"
    return f"{type(exc).__name__}: {text[:160]}" if text else type(exc).__name__


def check_finite(t: torch.Tensor, name: str) -> torch.Tensor:
    """Raise :class:`InputError` naming the first NaN/inf entry of ``t``."""
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        n_bad = int(bad.sum())
        raise InputError(
            f"{name}: expected finite values, got {n_bad} NaN/inf entr{'y' if n_bad == 1 else 'ies'} "
            f"(first at index {idx}: {t[idx].item()})"
        )
    return t


def check_ndim(t: torch.Tensor, ndim: int | Sequence[int], name: str, shape_doc: str) -> torch.Tensor:
    allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
    if t.dim() not in allowed:
        raise ShapeError(f"{name}: expected shape {shape_doc}, got {tuple(t.shape)}")
    return t


def check_last_dim(x, size: int, name: str, what: str, *, masks: bool = False) -> torch.Tensor:
    """``x (..., size)`` as a real floating tensor (arrays and lists converted), or refused naming ``what`` the last
    axis holds (e.g. ``"the correction inputs of system 's'"``); with ``masks`` a tensor of any dtype (a boolean
    mask of the same layout) is taken as it is."""
    x = x if masks and isinstance(x, torch.Tensor) else as_tensor(x, name)
    if x.dim() < 1 or x.shape[-1] != size:
        raise ShapeError(f"{name}: expected a last dimension of size {size} ({what}), got shape {tuple(x.shape)}")
    return x


def check_broadcasts(t: torch.Tensor, shape: Sequence[int], name: str) -> torch.Tensor:
    """``t`` when it broadcasts to ``shape`` without growing it (one value, or one per row), else a ShapeError."""
    try:
        fits = torch.broadcast_shapes(t.shape, tuple(shape)) == tuple(shape)
    except RuntimeError:
        fits = False
    if not fits:
        raise ShapeError(f"{name}: expected one value or values of shape {tuple(shape)}, got shape {tuple(t.shape)}")
    return t


def check_increasing(times: torch.Tensor, name: str = "times") -> torch.Tensor:
    """Times along the last axis must be strictly increasing."""
    if times.shape[-1] >= 2:
        dt = times[..., 1:] - times[..., :-1]
        bad = dt <= 0
        if bool(bad.any()):
            idx = tuple(int(i) for i in bad.nonzero()[0])
            j = idx[-1]
            where = f"row {idx[0]}, " if times.dim() == 2 else ""
            raise InputError(
                f"{name}: expected strictly increasing values, got {times[idx[:-1] + (j,)].item()} followed by "
                f"{times[idx[:-1] + (j + 1,)].item()} ({where}positions {j} and {j + 1}); sort the times and drop "
                "repeats"
            )
    return times


def check_indices(indices, size: int, name: str, *, distinct: bool = True) -> tuple[int, ...]:
    """Indices into a vector of length ``size``: integers (not bools, not floats), in range, no repeats unless
    ``distinct`` is false. ``None`` means all."""
    if indices is None:
        return tuple(range(size))
    try:
        items = list(indices.reshape(-1).tolist() if isinstance(indices, torch.Tensor) else indices)
    except TypeError as exc:
        raise InputError(f"{name}: expected a sequence of integers, got {indices!r}") from exc
    if any(isinstance(i, bool) or not isinstance(i, numbers.Integral) for i in items):
        bad = next(i for i in items if isinstance(i, bool) or not isinstance(i, numbers.Integral))
        raise InputError(
            f"{name}: expected a sequence of integers, got {bad!r} ({type(bad).__name__}) in {items!r:.100}"
        )
    out = tuple(int(i) for i in items)
    if len(out) == 0:
        raise InputError(f"{name}: expected at least one index, got an empty sequence")
    for i in out:
        if not 0 <= i < size:
            raise InputError(f"{name}: expected indices in [0, {size - 1}], got {i} in {list(out)}")
    if distinct and len(set(out)) != len(out):
        raise InputError(f"{name}: expected distinct indices, got repeats in {list(out)}")
    return out


def check_names(names, count: int | None, name: str, *, default: str | None = None) -> tuple[str, ...] | None:
    """``count`` distinct non-empty strings (one string alone is a list of one; ``count=None``: at least one);
    ``None`` gives ``default0, default1, ...`` (or ``None`` without a default prefix)."""
    if names is None:
        return None if default is None or count is None else tuple(f"{default}{j}" for j in range(count))
    many = "one or more" if count is None else count
    if not isinstance(names, (str, Iterable)) or isinstance(names, (bytes, torch.Tensor, np.ndarray)):
        raise InputError(
            f"{name}: expected a list of {many} non-empty strings, got {names!r:.80} ({type(names).__name__})"
        )
    items = [names] if isinstance(names, str) else list(names)
    wrong = not items if count is None else len(items) != count
    if wrong or not all(isinstance(n, str) and n.strip() for n in items):
        raise ShapeError(f"{name}: expected {many} non-empty strings (one per component), got {names!r:.200}")
    if len(set(items)) != len(items):
        raise InputError(f"{name}: expected distinct names, got {items}")
    return tuple(items)


_POSITION = re.compile(r"[yu]\d+")  # the default names y0, y1, ... / u0, u1, ...: positions, not names


def check_input_names(gp, names, owner: str) -> None:
    """Refuse a model fitted on correction inputs named ``gp.input_names_`` (as :func:`~torchmisspec.fit_correction`
    records them) where the inputs are ``names`` (e.g. ``system.input_names()``) and some pair of names differs: the
    model would read one input as another. Default names (``y0``, ``u0``: positions) and unknown names pass."""
    fitted = getattr(gp, "input_names_", None)
    if fitted is None or names is None or len(fitted) != len(names):
        return
    clash = [(a, b) for a, b in zip(fitted, names, strict=True) if a != b and not (_POSITION.fullmatch(a) or
                                                                                  _POSITION.fullmatch(b))]  # fmt: skip
    if clash:
        order = "the same names in another order" if sorted(fitted) == sorted(names) else "other names"
        raise InputError(
            f"gp: expected a model of the correction inputs {list(names)} of {owner}, got one fitted on "
            f"{list(fitted)} ({order}): it would read {clash[0][1]!r} as {clash[0][0]!r}; fit it on this system's "
            f"data, or build the system with correction_inputs={list(fitted)}"
        )


class NotATensor:
    """A container of experiments (with ``__len__`` and ``__getitem__``) that torch must not take for a nested
    sequence: each item is again such a container, so a tensor indexed with one (``x[(rows, controls)]``, e.g. a
    Campaign's ``ask`` result taken for indices) recursed without end inside torch and crashed the interpreter.
    torch hands any operation given one to this ``__torch_function__``, which refuses it."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", str(func))
        raise InputError(
            f"{name}: expected tensors (or indices), got a {cls.__name__}, which holds experiments; use its "
            "fields (e.g. .states, .values) or index it by experiment instead"
        )


def check_selection(
    index, count: int, name: str = "index", what: str = "experiments", *, empty: bool = False
) -> list[int]:
    """The positions ``index`` picks among ``count`` items (``what``): an integer (negative from the end), a slice, a
    sequence, array or tensor of integers (repeats allowed), or a boolean mask of length ``count``; at least one
    unless ``empty``.
    Anything else (floats, strings, ``None``, positions out of range) is refused: indexing a tensor with it raised
    torch's errors, or read an object with ``__getitem__`` as nested indices (a segmentation fault)."""
    if isinstance(index, slice):
        try:
            picked = list(range(count)[index])
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"{name}: expected a slice of integers of the {count} {what}, got {index!r} ({exc})"
            ) from None
    else:
        items = _selection_items(index, name, what)
        if items and all(isinstance(i, (bool, np.bool_)) for i in items):
            if len(items) != count:
                raise ShapeError(
                    f"{name}: expected a boolean mask of length {count} (one per {what[:-1]}), got {len(items)}"
                )
            picked = [k for k, keep in enumerate(items) if keep]
        else:
            bad = [i for i in items if isinstance(i, (bool, np.bool_)) or not isinstance(i, numbers.Integral)]
            if bad or any(not -count <= i < count for i in items):
                shown = bad[0] if bad else next(i for i in items if not -count <= i < count)
                raise InputError(
                    f"{name}: expected positions among the {count} {what} (integers in [{-count}, {count - 1}]) or a "
                    f"boolean mask, got {shown!r:.60} ({type(shown).__name__}) in {index!r:.80}"
                )
            picked = [int(i) % count for i in items]
    if not picked and not empty:
        raise InputError(f"{name}: expected a selection of at least one of the {count} {what}, got {index!r:.80}")
    return picked


def _selection_items(index, name: str, what: str) -> list:
    """The items of an index that is not a slice (a scalar integer: one item)."""
    if isinstance(index, np.ndarray):
        index = torch.from_numpy(index) if index.dtype.kind in "biu" else index.tolist()
    if isinstance(index, torch.Tensor):
        if index.dtype != torch.bool and (index.is_floating_point() or index.is_complex()) or index.dim() > 1:
            raise InputError(
                f"{name}: expected integer positions or a boolean mask of the {what}, got a tensor of dtype "
                f"{index.dtype} and shape {tuple(index.shape)}"
            )
        return index.detach().cpu().reshape(-1).tolist()  # a bool tensor gives Python bools
    if isinstance(index, numbers.Integral) and not isinstance(index, (bool, np.bool_)):
        return [index]
    if isinstance(index, (list, tuple, range)):
        return list(index)
    raise InputError(
        f"{name}: expected an integer, a slice, a list of integers or a boolean mask of the {what}, got "
        f"{index!r:.60} ({type(index).__name__})"
    )


def check_to(args: tuple, kwargs: dict, owner: str) -> None:
    """Refuse arguments of ``owner.to(...)`` that torch would not take, or that name a dtype other than a real
    floating one (the package's values are real numbers: an integer dtype would be silently kept as float)."""
    try:
        probe = torch.empty(0, dtype=DEFAULT_DTYPE).to(*args, **kwargs)
    except (RuntimeError, TypeError, ValueError, AssertionError) as exc:
        raise InputError(
            f"{owner}.to: expected a device ('cpu', 'cuda') and/or a real floating dtype (torch.float32, "
            f"torch.float64), got {', '.join([repr(a) for a in args] + [f'{k}={v!r}' for k, v in kwargs.items()])} "
            f"({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__})"
        ) from None
    if probe.dtype not in _REAL_DTYPES:
        raise InputError(
            f"{owner}.to: expected a real floating dtype (torch.float32, torch.float64), got {probe.dtype}"
        )
    check_device(probe.device, f"{owner}.to")  # a device that holds values ('meta' does not)


def check_generator(generator, device: torch.device) -> torch.Generator | None:
    """``None`` or a ``torch.Generator`` on the type of ``device`` the draws are made on."""
    if generator is None:
        return None
    if not isinstance(generator, torch.Generator):
        raise InputError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    if generator.device.type != device.type:
        raise InputError(
            f"generator: expected a generator on the draws' device ({device}), got one on {generator.device}"
        )
    return generator


def check_callable(function, name: str, form: str):
    """``function`` when it is callable; otherwise an :class:`InputError` naming the expected ``form``
    (e.g. ``"F(x) mapping points (M, n) to (M, m)"``)."""
    if not callable(function):
        raise InputError(f"{name}: expected a callable {form}, got {function!r:.60} ({type(function).__name__})")
    return function


def check_arity(function, count: int, name: str, form: str, fix: str = "") -> None:
    """Refuse a callable that cannot be called with ``count`` positional arguments, as the package will call it;
    ``form`` (e.g. ``"G(y, theta)"``) names that call in the message, ``fix`` ends it. ``*args`` and defaults are
    accepted, a ``functools.partial`` is checked for what it leaves, an ``nn.Module`` by its ``forward``; a callable
    whose signature cannot be read (a builtin) is not checked."""
    import inspect

    target = function.forward if isinstance(function, torch.nn.Module) else function
    try:
        signature = inspect.signature(target)
    except (TypeError, ValueError):  # no signature to read: the first call tells
        return
    try:
        signature.bind(*range(count))
    except TypeError:
        raise InputError(
            f"{name}: expected a callable {form}, called with {count} positional argument{'s' if count != 1 else ''}, "
            f"got a callable taking {signature}" + (f"; {fix}" if fix else "")
        ) from None


def check_positive_int(value, name: str, *, minimum: int = 1, maximum: int = 2**62) -> int:
    """An integer in ``[minimum, maximum]`` (bools, floats and other types are refused; numpy/torch integers are
    accepted). The default maximum keeps every count within torch's 64-bit sizes."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        if isinstance(value, torch.Tensor) and value.dim() == 0 and not value.is_floating_point():
            value = int(value)
        else:
            raise InputError(f"{name}: expected an integer >= {minimum}, got {value!r:.60} ({type(value).__name__})")
    value = int(value)
    if value < minimum:
        raise InputError(f"{name}: expected an integer >= {minimum}, got {value}")
    if value > maximum:
        digits = str(value)
        shown = digits if len(digits) <= 24 else f"{digits[:6]}... ({len(digits)} digits)"
        raise InputError(f"{name}: expected an integer <= {maximum}, got {shown}")
    return value


def check_real(value, name: str, *, minimum: float | None = None, positive: bool = False) -> float:
    """A finite real number (a Python/numpy number or a 0-d real tensor), ``> 0`` with ``positive`` (and at least
    the smallest normal float64 then), ``>= minimum`` when given. Bools, strings and complex numbers are refused."""
    what = (
        "a positive finite number"
        if positive
        else "a finite number" + (f" >= {minimum}" if minimum is not None else "")
    )
    if isinstance(value, torch.Tensor) and value.dim() == 0 and not value.is_complex() and value.dtype != torch.bool:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{name}: expected {what}, got {value!r:.60} ({type(value).__name__})")
    try:
        out = float(value)
    except OverflowError:  # an int beyond the float range
        raise InputError(f"{name}: expected {what}, got an integer of {len(str(value))} digits") from None
    if not math.isfinite(out) or (positive and out < _TINY) or (minimum is not None and out < minimum):
        raise InputError(f"{name}: expected {what}, got {value!r:.60}")
    return out


_TINY = torch.finfo(torch.float64).tiny


def check_domain(domain, name: str = "domain", *, dim: int | None = None) -> tuple[tuple[float, float], ...]:
    """A box as a tuple of ``(lo, hi)`` float pairs with finite ``lo < hi``; ``dim`` intervals when given."""
    try:
        arr = as_tensor(domain, name, dtype=torch.float64)
    except InputError as exc:
        raise InputError(f"{name}: expected a sequence of (lo, hi) pairs of real numbers, got {domain!r:.100}") from exc
    if arr.dim() != 2 or arr.shape[-1] != 2:
        raise InputError(
            f"{name}: expected a sequence of (lo, hi) pairs, got shape {tuple(arr.shape)}: {domain!r:.100}"
        )
    box = tuple((float(lo), float(hi)) for lo, hi in arr.tolist())
    if not box or any(not (math.isfinite(lo) and math.isfinite(hi) and lo < hi) for lo, hi in box):
        raise InputError(f"{name}: expected at least one interval with finite lo < hi, got {box}")
    if dim is not None and len(box) != dim:
        raise ShapeError(f"{name}: expected {dim} intervals (lo, hi), got {len(box)}: {box}")
    return box


def check_times(times, name: str = "times", *, per_row: bool = False, dtype=None, device=None) -> torch.Tensor:
    """Observation times: ``(T,)`` (or ``(K, T)`` with ``per_row``), at least one, finite, strictly increasing."""
    given = as_tensor(times, name, device=device)  # at the precision given, for the checks below
    check_ndim(given, (1, 2) if per_row else 1, name, "(T,) or (K, T)" if per_row else "(T,)")
    if given.shape[-1] < 1:
        raise ShapeError(f"{name}: expected at least one time, got shape {tuple(given.shape)}")
    check_finite(given, name)
    check_increasing(given, name)
    t = given if dtype is None else given.to(dtype)
    if t.dtype != given.dtype and given.shape[-1] >= 2:
        # the times follow the states' dtype: say so when that loses them, instead of blaming the user's times
        step = float((given[..., 1:] - given[..., :-1]).min())
        lost = float((t.to(given.dtype) - given).abs().max())
        ordered = bool((t[..., 1:] > t[..., :-1]).all())
        if not ordered or lost > 1e-3 * step:
            what = (
                f"{name}: expected times that {str(t.dtype).removeprefix('torch.')} (the states' dtype) can resolve, "
                f"got a rounding of up to {lost:.3g} against a smallest step of {step:.3g}; pass the states "
                f"as {str(given.dtype).removeprefix('torch.')}, or shift the times to start near 0"
            )
            if not ordered:
                raise InputError(what + " (rounded, some are no longer increasing: got repeated times)")
            warn(what, NumericalWarning)
    return t


def states_and_times(states, times, *, states_name: str = "states", times_name: str = "times", missing: bool = False):
    """Validate ``states (K, T, d)`` and ``times (T,)`` or ``(K, T)``: shapes agree, finite, strictly increasing.

    With ``missing=True`` NaN states are allowed (missing entries); infinite ones never are. States that look
    transposed, ``(K, d, T)`` with T times, are named as such rather than blamed on the times. The times follow the
    states' dtype and device. Returns ``(states, times)`` with the times as given ((T,) or (K, T)).
    """
    states = check_ndim(as_tensor(states, states_name), 3, states_name, "(K, T, d)")
    times = check_times(times, times_name, per_row=True, dtype=states.dtype, device=states.device)
    K, T, d = states.shape
    if times.shape[-1] != T or (times.dim() == 2 and times.shape[0] != K):
        if states.shape[-1] == times.shape[-1] and (times.dim() == 1 or times.shape[0] == K):
            raise ShapeError(
                f"{states_name}: expected shape (K, T, d) = (experiments, times, state components), got "
                f"{tuple(states.shape)}, whose last axis matches the {times.shape[-1]} times: the states look like "
                f"(K, d, T); pass {states_name}.transpose(1, 2) (NumPy: .transpose(0, 2, 1))"
            )
        raise ShapeError(
            f"{times_name}: expected shape ({T},) or ({K}, {T}) to match {states_name} {tuple(states.shape)}, "
            f"got {tuple(times.shape)}"
        )
    if missing:
        check_not_infinite(states, states_name)
    else:
        check_finite(states, states_name)
    return states, times


def check_not_infinite(t: torch.Tensor, name: str) -> torch.Tensor:
    """Raise :class:`InputError` naming the first infinite entry of ``t`` (NaN, a missing value, is allowed)."""
    bad = torch.isinf(t)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        n_bad = int(bad.sum())
        raise InputError(
            f"{name}: expected finite values or NaN for a missing entry, got {n_bad} infinite entr"
            f"{'y' if n_bad == 1 else 'ies'} (first at index {idx}: {t[idx].item()})"
        )
    return t


class _NoBar:
    """Stands in for a tqdm bar when progress is off: every method does nothing."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, *args, **kwargs) -> None:
        pass

    def set_description(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> _NoBar:
        return self

    def __exit__(self, *exc) -> None:
        pass


def check_flag(value, name: str, *, none: bool = False) -> bool | None:
    """``True`` or ``False`` (or ``None`` when ``none``): no truthy strings or numbers quietly taken as a switch."""
    if isinstance(value, bool) or (none and value is None):
        return value
    if isinstance(value, (np.bool_,)) or (
        isinstance(value, torch.Tensor) and value.dtype == torch.bool and value.numel() == 1
    ):
        return bool(value)
    allowed = "True, False or None" if none else "True or False"
    raise InputError(f"{name}: expected {allowed}, got {value!r:.60} ({type(value).__name__})")


def progress_bar(enabled: bool, total: int, desc: str, unit: str = "it"):
    """A tqdm progress bar, or an object with the same methods that does nothing when ``enabled`` is false.

    Use it as a context manager (``with progress_bar(...) as bar:``) or call ``close()``; no ``None`` checks needed.
    tqdm is imported only when a bar is shown.
    """
    if not check_flag(enabled, "progress"):
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=False)
