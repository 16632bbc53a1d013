"""Deprecated: the demo moved to :mod:`torchmisspec.paper.demo`, ``uniform_in_box`` to
:func:`torchmisspec.design.candidates.uniform_box`. Importing this module warns (DeprecationWarning)."""

from __future__ import annotations

import warnings

from .design.candidates import uniform_box as uniform_in_box
from .paper.demo import DemoResult, linear_demo

warnings.warn(
    "torchmisspec.experiments is deprecated: use torchmisspec.paper.demo (DemoResult, linear_demo) and "
    "torchmisspec.design.candidates.uniform_box (instead of uniform_in_box)",
    DeprecationWarning,
    stacklevel=2,
)

__all__ = ["DemoResult", "linear_demo", "uniform_in_box"]
