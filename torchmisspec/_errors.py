"""Exception hierarchy of torchmisspec.

Every error raised on purpose by the package derives from :class:`TorchMisspecError`, so a caller can catch
the whole family with one ``except``. Errors about bad input or failed fits also derive from ``ValueError``;
errors found while running (a diverging ODE, a model used before it is fitted) derive from ``RuntimeError``.
"""

from __future__ import annotations

__all__ = [
    "TorchMisspecError",
    "InputError",
    "ShapeError",
    "FittingError",
    "NotPositiveDefiniteError",
    "NotFittedError",
    "IntegrationError",
    "BudgetError",
]


class TorchMisspecError(Exception):
    """Base class of every error raised by torchmisspec."""


class InputError(TorchMisspecError, ValueError):
    """A public argument has a bad value: NaN or inf, non-increasing times, bad indices, bad options."""


class ShapeError(InputError):
    """A tensor has the wrong shape or does not match the system / another tensor."""


class FittingError(TorchMisspecError, ValueError):
    """Fitting the correction model failed (bad data for the model, optimiser breakdown)."""


class NotPositiveDefiniteError(FittingError):
    """A covariance matrix could not be factorized, even after adding jitter."""


class NotFittedError(TorchMisspecError, RuntimeError):
    """A model was asked for a posterior before ``fit`` was called."""


class IntegrationError(TorchMisspecError, RuntimeError):
    """An ODE solve produced non-finite states or the solver gave up (the trajectory blew up)."""


class BudgetError(InputError):
    """An experimental-design budget cannot be met by the candidate set or its capacities."""
