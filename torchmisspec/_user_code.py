"""Importing the user's code a command-line spec names (``module:function`` or ``path/to/file.py:function``).

Only :func:`~torchmisspec.systems.load_system` calls it, for a spec the user passed: importing a module runs its
code, which is what such a spec asks for.
"""

from __future__ import annotations

from ._errors import InputError

__all__ = ["import_module", "one_line"]


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
        raise InputError(
            f"system {spec!r}: expected an importable module {module_name!r}, got {one_line(exc)} when importing it"
        ) from exc


def one_line(exc: BaseException) -> str:
    """``Type: message`` on one line, at most 300 characters (for one-line command-line errors)."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= 300 else text[:297] + "..."
