"""Deprecated: the demo moved to :mod:`torchmisspec.paper.demo`, ``uniform_in_box`` to
:func:`torchmisspec.design.candidates.uniform_box`. Importing this module warns (DeprecationWarning)."""

from __future__ import annotations

from .design.candidates import uniform_box as uniform_in_box
from .paper import _warn_moved
from .paper.demo import DemoResult, linear_demo

__all__ = ["DemoResult", "linear_demo", "uniform_in_box"]

_warn_moved(
    "torchmisspec.experiments",
    "torchmisspec.paper.demo (DemoResult, linear_demo) and "
    "torchmisspec.design.candidates.uniform_box (instead of uniform_in_box)",
)
