"""The ODE solver's settings for the corrected model: :class:`Solver`, one small frozen option object in the spirit of
diffrax's (``PIDController``, ``SaveAt``), so that the five settings of a solve travel together instead of as five
keywords on every call of :meth:`CorrectedODE.predict <torchmisspec.CorrectedODE.predict>` and
:meth:`CorrectedODE.posterior <torchmisspec.CorrectedODE.posterior>` (and through :meth:`CorrectedODE.calibrate
<torchmisspec.CorrectedODE.calibrate>` to the held-out posteriors)."""

from __future__ import annotations

import dataclasses

from .._errors import InputError
from .._ode import PREDICTION_TOLERANCES, check_solver_settings

__all__ = ["Solver"]


@dataclasses.dataclass(frozen=True)
class Solver:
    """How the corrected model is integrated (torchdiffeq, one batched solve).

    Every setting is checked when the object is made, so a bad one is refused where it is written, not at the first
    solve. ``Solver()`` is the package's default for predictions.

    Args:
        method: torchdiffeq method (``"dopri5"`` by default; only its adaptive Runge-Kutta methods keep a forecast
            that fails part-way).
        rtol: relative tolerance in (0, 1) (default: the package's prediction tolerance, 1e-7; see
            :mod:`torchmisspec._ode`).
        atol: absolute tolerance in (0, 1), in units of each state component's own scale (default 1e-9; likewise).
        max_steps: most solver steps (``None``: 10,000); beyond it :class:`~torchmisspec.IntegrationError` names the
            initial conditions that stalled the solve.
        options: further torchdiffeq solver options, a dict such as ``{"step_size": 0.01}`` for a fixed-step
            method, or ``None`` (a copy is kept).

    Example::

        model.predict(y0, times, solver=tms.Solver(rtol=1e-9, atol=1e-11))
    """

    method: str = "dopri5"
    rtol: float = PREDICTION_TOLERANCES[0]
    atol: float = PREDICTION_TOLERANCES[1]
    max_steps: int | None = None
    options: dict | None = None

    def __post_init__(self) -> None:
        check_solver_settings(self.method, self.rtol, self.atol, self.options, self.max_steps)
        if self.options is not None:  # the caller's dict may change later; this object does not
            object.__setattr__(self, "options", dict(self.options))

    def keywords(self) -> dict:
        """The settings as the keywords of the package's batched solve (:func:`torchmisspec._ode.solve`)."""
        return dict(method=self.method, rtol=self.rtol, atol=self.atol, options=self.options, max_steps=self.max_steps)


def as_solver(solver) -> Solver:
    """``solver`` checked: a :class:`Solver`, or ``Solver()`` for ``None``; anything else is refused with the fix."""
    if solver is None:
        return Solver()
    if isinstance(solver, Solver):
        return solver
    fix = "torchmisspec.Solver(**settings)" if isinstance(solver, dict) else "torchmisspec.Solver(rtol=..., atol=...)"
    raise InputError(
        f"solver: expected a torchmisspec.Solver (the solver's method, rtol, atol, max_steps and options) or None, got "
        f"{solver!r:.60} ({type(solver).__name__}); pass solver={fix}"
    )
