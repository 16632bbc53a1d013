"""Deprecated: the paper's figures moved to :mod:`torchmisspec.paper.figures`. Importing this module warns
(DeprecationWarning); every name re-exported here is the one of the new module."""

from __future__ import annotations

import warnings

from .paper.figures import (
    FIGURES,
    GRAVITY_PRIOR,
    LINEAR_PRIOR,
    NOISE_STD,
    figure_1,
    figure_2,
    figure_3,
    figure_4,
    figure_5,
    figure_6,
    figure_7,
    figure_8,
    reproduce,
)

warnings.warn(
    "torchmisspec.reproduce is deprecated: use torchmisspec.paper.figures (same names)",
    DeprecationWarning,
    stacklevel=2,
)

__all__ = [
    "FIGURES",
    "LINEAR_PRIOR",
    "GRAVITY_PRIOR",
    "NOISE_STD",
    "figure_1",
    "figure_2",
    "figure_3",
    "figure_4",
    "figure_5",
    "figure_6",
    "figure_7",
    "figure_8",
    "reproduce",
]
