"""Deprecated: the paper's studies moved to :mod:`torchmisspec.paper.studies`, the candidate grid to
:func:`torchmisspec.design.candidates.grid`. Importing this module warns (DeprecationWarning)."""

from __future__ import annotations

import torch

from .design.candidates import grid as _grid
from .paper import _warn_moved
from .paper.studies import StudyResult, gravity_study, linear_study

__all__ = ["StudyResult", "grid_candidates", "linear_study", "gravity_study"]

_warn_moved(
    "torchmisspec.studies",
    "torchmisspec.paper.studies (StudyResult, linear_study, gravity_study) and "
    "torchmisspec.design.candidates.grid (instead of grid_candidates)",
)


def grid_candidates(domain, size: int = 13, *, dtype=torch.float64) -> torch.Tensor:
    """Deprecated: :func:`torchmisspec.design.candidates.grid` (``size`` required there): ``(size**n, n)``."""
    return _grid(domain, size, dtype=dtype)
