"""Exception hierarchy of torchmisspec.

Every error raised on purpose by the package derives from :class:`TorchMisspecError`, so a caller can catch
the whole family with one ``except``. Errors about bad input, failed fits or
failed factorizations also derive from ``ValueError``;
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
    "LinearAlgebraError",
    "TorchMisspecWarning",
    "NumericalWarning",
]


class TorchMisspecError(Exception):
    """Base class of every error raised by torchmisspec."""


class InputError(TorchMisspecError, ValueError):
    """A public argument has a bad value: NaN or inf, non-increasing times, bad indices, bad options."""


class ShapeError(InputError):
    """A tensor has the wrong shape or does not match the system / another tensor."""


class FittingError(TorchMisspecError, ValueError):
    """Fitting the correction model failed (bad data for the model, optimiser breakdown)."""


class LinearAlgebraError(TorchMisspecError, ValueError):
    """A matrix computation failed: non-finite entries, or a factorization that failed even with jitter.

    Raised wherever a covariance is factorized (fitting, prediction, design); the fit re-raises it as a
    :class:`FittingError` that names the hyperparameters in use.
    """


class NotPositiveDefiniteError(LinearAlgebraError):
    """A covariance matrix could not be factorized, even after adding jitter."""


class NotFittedError(TorchMisspecError, RuntimeError):
    """A model was asked for a posterior before ``fit`` was called."""


class IntegrationError(TorchMisspecError, RuntimeError):
    """An ODE solve produced non-finite states or the solver gave up (the trajectory blew up)."""


class BudgetError(InputError):
    """An experimental-design budget cannot be met by the candidate set or its capacities."""


class TorchMisspecWarning(UserWarning):
    """Base class of every warning issued by torchmisspec."""


class NumericalWarning(TorchMisspecWarning):
    """A numerical fix was applied (jitter added to a covariance diagonal) or a result may be inaccurate."""


def clipped(text: str, limit: int = 300) -> str:
    """``text`` cut to at most about ``limit`` characters at the end of a sentence or clause (``". "``, ``"; "``,
    ``": "``) with " ..." after it, not mid-word: a quoted message inside another (a solver's failure in a warning)
    stays readable (on a Soybean trial the solver's advice ended "shorten the time span, sta")."""
    if len(text) <= limit:
        return text
    head = text[:limit]
    cut = max(head.rfind(mark) for mark in (". ", "; ", ": ")) + 1  # keeping the mark
    if cut < limit // 4:  # no clause end late enough: at the last word
        cut = head.rfind(" ")
    return (head[:cut] if cut > 0 else head).rstrip() + " ..."


def warn(message: str, category: type[Warning] = NumericalWarning) -> None:
    """Issue a warning attributed to the first caller outside torchmisspec (the user's line, wherever inside the
    package the problem was found)."""
    import os
    import sys
    import warnings

    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(0), 1
    while frame is not None and (
        os.path.abspath(frame.f_code.co_filename).startswith(package)
        or os.path.basename(frame.f_code.co_filename) in ("contextlib.py", "functools.py")  # decorators' wrappers
    ):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
