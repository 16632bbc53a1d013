"""Deprecated: the paper's figures moved to :mod:`torchmisspec.paper.figures` (same names). Importing this module
warns (DeprecationWarning)."""

from __future__ import annotations

from .paper import _warn_moved
from .paper import figures as _figures
from .paper.figures import *  # noqa: F403  (every public name of the new module: the same objects)

__all__ = _figures.__all__

_warn_moved("torchmisspec.reproduce", "torchmisspec.paper.figures (same names)")
