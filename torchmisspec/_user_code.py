"""The user's code: importing what a command-line spec names (``module:function`` or ``path/to/file.py:function``),
and calling a system's G or F (:func:`call_user`): an exception raised inside it is reported at the user's file and
line, a value of the wrong type or shape as a :class:`ShapeError`.

Only :func:`~torchmisspec.systems.load_system` imports, for a spec the user passed: importing a module runs its
code, which is what such a spec asks for.
"""

from __future__ import annotations

import torch

from ._errors import InputError, ShapeError, TorchMisspecError
from ._validation import check_arity

__all__ = ["import_module", "one_line", "where", "call_user", "checked_output", "check_signatures"]

#: torch's out-of-memory error (a RuntimeError): not the user's code's fault, passed on unchanged by call_user
_OUT_OF_MEMORY = getattr(torch, "OutOfMemoryError", torch.cuda.OutOfMemoryError)


def import_module(module_name: str, spec: str):
    """Import a dotted module name, or a ``.py`` file by path (registered under a private name)."""
    import hashlib
    import importlib
    import importlib.util
    import sys
    from pathlib import Path

    try:
        if module_name.endswith(".py"):
            path = Path(module_name)
            if not path.is_file():
                raise InputError(f"system {spec!r}: expected an existing Python file, got {module_name!r}")
            path = path.resolve()
            name = "_torchmisspec_user_" + hashlib.sha1(str(path).encode()).hexdigest()[:12]
            loader_spec = importlib.util.spec_from_file_location(name, path)
            if loader_spec is None or loader_spec.loader is None:
                raise InputError(f"system {spec!r}: expected a Python file, got {module_name!r}")
            module = importlib.util.module_from_spec(loader_spec)
            sys.modules[name] = module  # so dataclasses and pickling inside the module find it
            try:
                loader_spec.loader.exec_module(module)
            except BaseException:
                sys.modules.pop(name, None)
                raise
            return module
        return importlib.import_module(module_name)
    except InputError:
        raise
    except Exception as exc:
        at = where(exc)
        raise InputError(
            f"system {spec!r}: expected an importable module {module_name!r}, got {one_line(exc)} when importing it"
            + (f" (at {at})" if at else "")
        ) from exc


def one_line(exc: BaseException) -> str:
    """``Type: message`` on one line, at most 300 characters (for one-line command-line errors)."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= 300 else text[:297] + "..."


def where(exc: BaseException) -> str | None:
    """``path:line, in function`` of the deepest frame of ``exc``'s traceback outside torchmisspec, torch, numpy and
    Python's standard library: the user's line that raised it (or called the library call that did); ``None`` when there
    is no such frame."""
    import os
    import sysconfig

    import numpy

    here = os.path.abspath(__file__)  # torchmisspec/_user_code.py
    library = tuple(os.path.dirname(os.path.abspath(path)) + os.sep for path in (torch.__file__, numpy.__file__, here))
    stdlib = os.path.abspath(sysconfig.get_paths()["stdlib"]) + os.sep
    found, tb = None, exc.__traceback__
    while tb is not None:
        code = tb.tb_frame.f_code
        path = os.path.abspath(code.co_filename)
        python = path.startswith(stdlib) and "site-packages" not in path  # importlib, functools, ...
        if not (code.co_filename.startswith("<frozen") or python or path.startswith(library)):
            found = f"{code.co_filename}:{tb.tb_lineno}, in {code.co_name}"
        tb = tb.tb_next
    return found


def call_user(function, x: torch.Tensor, what: str):
    """``function(x)``; a function that is not vectorised (it converts a batch of states to one number, or indexes
    states as a single vector) fails here with a message that says so instead of torch's own, and any other error
    raised inside the user's function (a NameError, torch refusing an operation) as a package error naming the
    user's file and line. The package's own errors, and running out of memory, pass unchanged."""
    try:
        return function(x)
    except (TorchMisspecError, MemoryError, _OUT_OF_MEMORY):
        raise
    except Exception as exc:
        if "only one element tensors" in str(exc) or "a Tensor with" in str(exc) and "to a Scalar" in str(exc):
            raise ShapeError(
                f"{what} must work on a batch of states: it is called with a tensor of shape {tuple(x.shape)} "
                f"(states (..., d)), and failed ({type(exc).__name__}: {exc}). Write it with tensor operations on the "
                "last axis, e.g. y[..., 0] instead of float(y[0]), and torch.stack([...], dim=-1) for the result"
            ) from exc
        at = where(exc)
        raise InputError(
            f"{what} raised {one_line(exc)}" + (f" (at {at})" if at else "") + f" when called on states of shape "
            f"{tuple(x.shape)}; the error is in the system's own code: fix it there"
        ) from exc


def checked_output(out, shape: torch.Size, what: str, x: torch.Tensor) -> torch.Tensor:
    """``out``, the user's function's value at ``x``, when it is a tensor of ``shape``; else a :class:`ShapeError`."""
    if not isinstance(out, torch.Tensor):
        raise ShapeError(
            f"{what} returned a {type(out).__module__}.{type(out).__name__} for states of shape {tuple(x.shape)}; "
            f"expected a torch.Tensor of shape {tuple(shape)}, got {type(out).__name__} (build it with torch "
            "operations on the input tensor, e.g. torch.stack([...], dim=-1), not NumPy)"
        )
    if out.shape != shape:
        got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ShapeError(
            f"{what} returned shape {got} for inputs of shape {tuple(x.shape)}; expected {tuple(shape)}, got {got} "
            "(check the callable's output: one value per state component it acts on)"
        )
    return out


def check_signatures(system) -> None:
    """A :class:`~torchmisspec.MisspecifiedSystem`'s G and F can be called as the package will call them: ``G(y)``,
    ``G(y, theta)``, ``G(t, y, u)`` or ``G(t, y, u, theta)`` as the system declares, ``F(x)`` (checked where the
    system is built, not deep inside a solve)."""
    args = (["y"] if system.autonomous else ["t", "y", "u"]) + ([] if system.parameters is None else ["theta"])
    why = (
        "an autonomous system: no controls, not time_dependent"
        if system.autonomous
        else f"num_controls={system.num_controls}" + (", time_dependent=True" if system.time_dependent else "")
    )
    why += "" if system.parameters is None else f", uncertain parameters {list(system.parameters.names)} last"
    check_arity(
        system.known,
        len(args),
        "known",
        f"G({', '.join(args)}) for system '{system.name}' ({why})",
        "change G's signature, or declare what it takes: num_controls=m or time_dependent=True for G(t, y, u), "
        "parameters={...} for theta last",
    )
    if system.correction is not None:
        check_arity(system.correction, 1, "correction", f"F(x) for system '{system.name}' (its inputs x, (..., d_in))")
