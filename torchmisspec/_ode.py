"""Private batched ODE solve shared by :func:`simulate` and :class:`CorrectedODE`.

Many initial conditions are integrated in one torchdiffeq call, also when each has its own time grid ``(B, T)``.
With an adaptive Runge-Kutta method (dopri5, the default) on a long grid, the outputs that fall inside each solver
step are interpolated at once, and on per-row grids only each row's own times are evaluated (:func:`_integrate`):
torchdiffeq's ``odeint`` evaluates every output time one by one in Python, and per-row grids would need the union of
all of them (up to B T times) for every row, O(B^2 T) memory and time for ragged irregular data. The steps and the
numbers are ``odeint``'s. Non-finite states or a solver that gives up raise :class:`IntegrationError`.

**Tolerance policy** (one rule for every solve in the package, dopri5 by default):

* :data:`SIMULATION_TOLERANCES` ``rtol=1e-10, atol=1e-12`` for simulations of a *given* model - the true system
  (:func:`~torchmisspec.simulate`), the known model's proxy trajectories (:mod:`torchmisspec.design`) and the true
  trajectories of a design - so that solver error never limits an accuracy check or a comparison of designs;
* :data:`PREDICTION_TOLERANCES` ``rtol=1e-7, atol=1e-9`` for the corrected model
  (:meth:`~torchmisspec.CorrectedODE.predict`), whose own error (F_hat - F) is orders of magnitude larger: tighter
  tolerances would cost steps without changing what is predicted;
* :data:`FITTING_TOLERANCES` ``rtol=1e-5, atol=1e-7`` for the solves inside a fit through the ODE
  (:func:`~torchmisspec.fit_trajectories`, the held-out predictions of :func:`~torchmisspec.fit_correction`'s
  cross-validation), whose misfits compare with measured states: a relative solver error of 1e-5 is far below any
  measurement noise, and the fits are 2.5-4x faster than at the prediction tolerances with the same result
  (pendulum and Lotka-Volterra with 1 % state noise: the same test error to three digits).

Every public function that solves takes ``rtol``/``atol`` keywords (each in (0, 1)) to override its default. ``atol``
is in units of each state component's own scale (:func:`state_scales`: the power of ten nearest its root mean square
over the initial states): states of order 1 are solved with ``atol`` itself, states in 1e-3 with ``atol * 1e-3``, so
that a change of units (mg and g, counts in thousands) scales the solution exactly instead of loosening the solve of
small states (issue 40: the predictions of a model fitted on states of 1e-3 differed from those of the same model in
other units by 1e-6 relative, from the absolute tolerance alone). Where the fit compares logarithms (relative
noise), a component's scale is at most the power of ten of its smallest measured value (``solve``'s ``floor``): a
drug's depot measured at 1e-6 of its dose was solved with an absolute error of 1e-6, its logarithm off by 0.1-1.6
at the fitting tolerances, more than its 5 % noise (issue 43's design study).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torchdiffeq import odeint

try:  # torchdiffeq's own input handling and solvers, for the vectorised output of _integrate (odeint otherwise)
    from torchdiffeq._impl.misc import _check_inputs
    from torchdiffeq._impl.odeint import SOLVERS
    from torchdiffeq._impl.rk_common import RKAdaptiveStepsizeODESolver
except ImportError:  # pragma: no cover - another torchdiffeq layout
    SOLVERS = None

from ._errors import InputError, IntegrationError, ShapeError, TorchMisspecError
from ._validation import as_tensor, check_finite, check_ndim, check_positive_int, check_real, check_times

#: (rtol, atol) of simulations of a given model: the truth, the proxies (see the module docstring)
SIMULATION_TOLERANCES = (1e-10, 1e-12)
#: (rtol, atol) of the corrected model's predictions (see the module docstring)
PREDICTION_TOLERANCES = (1e-7, 1e-9)
#: (rtol, atol) of the solves inside fits through the ODE (see the module docstring)
FITTING_TOLERANCES = (1e-5, 1e-7)


def initial_conditions_and_times(
    y0, times, state_dim: int, check_states, *, dtype=None, device=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate ``y0 (B, d)`` (or ``(d,)``) and ``times (T,)`` or ``(B, T)`` for a batched solve."""
    y0 = as_tensor(y0, "y0", dtype=dtype, device=device)
    if y0.dim() == 1:
        y0 = y0.unsqueeze(0)
    check_ndim(y0, 2, "y0", f"(B, {state_dim})")
    if y0.shape[0] < 1:
        raise ShapeError(f"y0: expected at least one initial condition, got shape {tuple(y0.shape)}")
    check_states(y0, "y0")
    check_finite(y0, "y0")
    times = check_times(times, "times", per_row=True, dtype=y0.dtype, device=y0.device)
    if times.dim() == 2 and times.shape[0] != y0.shape[0]:
        raise ShapeError(f"times: expected ({y0.shape[0]}, T) to match y0 {tuple(y0.shape)}, got {tuple(times.shape)}")
    return y0, times


#: default most solver steps of one batched solve (raise it with ``max_steps=``); the paper's problems need < 100
DEFAULT_MAX_STEPS = 10_000
#: right-hand-side evaluations allowed per step (dopri5 uses 6 per accepted or rejected step, plus the start)
EVALS_PER_STEP = 7
_FLOAT_DTYPES = (torch.float32, torch.float64)
#: a fit's trial step (one it rejects when its solve fails) may take at most this many times the solver steps of the
#: current point's solve (:func:`trial_budget`): a step towards values whose paths need far more steps (they oscillate
#: wildly or blow up) is rejected at that cost instead of being integrated to the step limit (on the lynx data four
#: such trial steps of the known model's fit took 4.7 s each, 19 of the fit's 48 s)
TRIAL_STEPS_FACTOR = 4
#: ... and at least this many steps
TRIAL_MIN_STEPS = 200


def trial_budget(steps: float, cap: int | None = None) -> int:
    """The step limit of a trial step's solve whose current point's solve took ``steps`` solver steps:
    :data:`TRIAL_STEPS_FACTOR` times as many (at least :data:`TRIAL_MIN_STEPS`, at most ``cap``, default
    :data:`DEFAULT_MAX_STEPS`)."""
    cap = DEFAULT_MAX_STEPS if cap is None else cap
    return int(min(cap, max(TRIAL_MIN_STEPS, TRIAL_STEPS_FACTOR * steps)))


#: torchdiffeq's adaptive solvers that take ``jump_t`` (discontinuities of the field they never step across)
_JUMPING = ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun")


#: a solve is stalled when 100 steps advance time by less than this fraction of the time span
_STALL_FRACTION = 1e-6
_STALL_WINDOW = 100 * EVALS_PER_STEP


class _StepLimit(Exception):
    """Raised inside the right-hand side when the evaluation budget is spent (stops torchdiffeq at once)."""


class _Stalled(Exception):
    """Raised inside the right-hand side when time has stopped advancing (a singularity or a chattering state)."""


class _Autonomous(torch.nn.Module):
    """Wrap an autonomous field f(y) as torchdiffeq's func(t, y): counts evaluations, enforces the step budget,
    checks the field's output shape and remembers the last state (for the error message)."""

    def __init__(
        self,
        field: Callable[[torch.Tensor], torch.Tensor],
        max_evals: int,
        what: str,
        span: float,
        offsets: torch.Tensor | None = None,
        box: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> None:
        super().__init__()
        self.field = field
        self.box = box  # (lo, hi): a row whose state leaves the box stops (its derivative is 0 from then on)
        # with a box checked at the accepted steps (:meth:`stop_outside`): the rows stopped, and the wider box
        # beyond which a stage's state gets derivative 0 (a guard: the field is never evaluated far outside)
        self.stopped = None
        self.guard = None
        self.offsets = offsets  # a timed field: every row's own time is the solver's time plus its offset
        self.nfe = 0
        self.max_evals = max_evals
        self.what = what
        self.min_advance = _STALL_FRACTION * span
        self.window_t = None
        self.last_t = None
        self.last_y = None
        self.last_f = None
        self.failed = False  # whether the field itself raised

    def forward(self, t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        self.nfe += 1
        if self.nfe > self.max_evals:
            raise _StepLimit
        if self.nfe % _STALL_WINDOW == 0:  # progress check: has time advanced over the last 100 steps?
            now = float(t)
            if self.window_t is not None and now - self.window_t < self.min_advance:
                raise _Stalled
            self.window_t = now
        try:
            f = self.field(y) if self.offsets is None else self.field(t + self.offsets, y)
        except Exception:
            self.failed = True  # the field's own error, not the solver's: solve passes it on unchanged
            raise
        if not isinstance(f, torch.Tensor) or f.shape != y.shape:
            shape = tuple(f.shape) if isinstance(f, torch.Tensor) else type(f).__name__
            raise ShapeError(
                f"{self.what}: the right-hand side must return one derivative per state, shape {tuple(y.shape)}, "
                f"got {shape}; check that G (and F) map states (..., d) to (..., d)"
            )
        if self.box is not None:
            lo, hi = self.box if self.guard is None else self.guard
            out = ((y < lo) | (y > hi)).any(-1, keepdim=True)
            if self.stopped is not None:
                out = out | self.stopped.unsqueeze(-1)
            f = torch.where(out, torch.zeros((), dtype=f.dtype, device=f.device), f)
        self.last_t, self.last_y, self.last_f = t, y, f
        return f

    def stop_outside(self, state):
        """After a step of the solver (its state ``state``): the rows whose accepted state is outside the box stop
        from there (derivative 0, their last derivative too), so that no later step straddles a jump of the field
        (a row stopped at a stage's state outside the box makes the solver shrink its steps to the crossing)."""
        new = ((state.y1 < self.box[0]) | (state.y1 > self.box[1])).any(-1) & ~self.stopped
        if not bool(new.any()):
            return state
        self.stopped = self.stopped | new
        return state._replace(f1=torch.where(new.unsqueeze(-1), torch.zeros((), dtype=state.f1.dtype), state.f1))


def _worst(y: torch.Tensor, f: torch.Tensor, k: int = 5, box=None) -> list[int]:
    """Indices of the initial conditions whose state or derivative is non-finite or largest (most suspect first);
    with ``box``, among the rows still inside it (a row stopped outside it is not what holds the solve back)."""
    size, order = _sizes(y, f, box)
    return order[: min(k, order.numel())].tolist()


def _sizes(y: torch.Tensor, f: torch.Tensor, box=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Every row's largest norm of state and derivative (inf where not finite), and the rows by it, largest first
    (with ``box``, only those inside it where any is)."""
    size = torch.linalg.vector_norm(f.detach().nan_to_num(float("inf"), float("inf"), float("inf")), dim=-1)
    size = torch.maximum(size, torch.linalg.vector_norm(y.detach().nan_to_num(float("inf")), dim=-1))
    order = torch.argsort(size, descending=True)
    if box is not None:
        inside = ~((y.detach() < box[0]) | (y.detach() > box[1])).any(-1)
        if bool(inside.any()):
            order = order[inside[order]]
    return size, order


def _culprits(func, box) -> tuple[list[int], list[int]]:
    """Where a solve gave up: :func:`_worst`'s rows, and the suspects among them: those whose state or derivative is
    at least a tenth of the largest (a row far smaller is not what holds the solve back)."""
    if func.last_y is None:
        return [], []
    worst = _worst(func.last_y, func.last_f, box=box)
    size = _sizes(func.last_y, func.last_f)[0]
    top = float(size[worst[0]]) if worst else 0.0
    return worst, [i for i in worst if float(size[i]) >= 0.1 * top]


def _with_rows(
    rows: list[int],
    exc: IntegrationError,
    states: torch.Tensor | None = None,
    nfe: int = 0,
    suspects: list[int] | None = None,
) -> IntegrationError:
    """``exc`` carrying ``rows``: the batch rows most likely at fault (largest state or derivative where the solver
    gave up), for callers that isolate them; ``states``: with ``solve(partial=True)``, the solution ``(B, T, d)`` up
    to where the solve failed (NaN after; ``None`` where none could be kept); ``nfe``: the right-hand-side
    evaluations the failed solve spent; ``suspects``: those of ``rows`` far larger than the others (all of them by
    default)."""
    exc.rows = list(rows)
    exc.suspects = list(rows) if suspects is None else list(suspects)
    exc.states = states
    exc.nfe = nfe
    return exc


#: output times from which a solve interpolates each step's outputs at once (below, torchdiffeq's loop is as fast)
_VECTOR_OUTPUTS = 64


def _solver(func, y0: torch.Tensor, grid: torch.Tensor, method: str, rtol: float, atol: float, options):
    """torchdiffeq's adaptive Runge-Kutta solver set up as ``odeint`` sets it up (its own input handling), started
    at ``grid[0]``; ``None`` where ``odeint`` itself must run (another method, another torchdiffeq layout)."""
    if SOLVERS is None:  # pragma: no cover - another torchdiffeq layout
        return None
    shapes, f, y, t, rtol, atol, method, options, _, reversed_ = _check_inputs(
        func, y0, grid, rtol, atol, method, options, None, SOLVERS
    )
    solver = SOLVERS[method](func=f, y0=y, rtol=rtol, atol=atol, **options)
    if shapes is not None or reversed_ or not isinstance(solver, RKAdaptiveStepsizeODESolver):
        return None
    solver._before_integrate(t.to(solver.dtype))
    return solver


def _outputs(
    solver,
    y0: torch.Tensor,
    points: torch.Tensor,
    rows: torch.Tensor | None = None,
    fill: float | None = None,
    on_step=None,
) -> torch.Tensor:
    """The solution at the sorted times ``points (M,)`` (the first is the start): every row's ``(M, B, d)``, or with
    ``rows (M,)`` row ``rows[m]``'s at ``points[m]``, ``(M, d)``. The outputs inside each step are evaluated together
    from the step's interpolating polynomial (torchdiffeq's ``_interp_evaluate``, its arithmetic and its steps, which
    do not depend on the output times: the same numbers as ``odeint``). With ``fill`` (NaN), the outputs not reached
    when the solve raises are ``fill`` in the buffer the exception carries (``exc.outputs``). ``on_step(state)``,
    when given, sees (and may change) the solver's state after every step."""
    points = points.to(solver.dtype)
    n = points.numel()
    shape = (n, *y0.shape) if rows is None else (n, y0.shape[-1])
    if fill is None:
        return _fill_outputs(solver, y0, points, rows, torch.empty(shape, dtype=y0.dtype, device=y0.device), on_step)
    out = torch.full(shape, fill, dtype=y0.dtype, device=y0.device)
    try:
        return _fill_outputs(solver, y0, points, rows, out, on_step)
    except BaseException as exc:  # the outputs reached so far go with the exception (re-raised as it is)
        exc.outputs = out
        raise


def _fill_outputs(solver, y0: torch.Tensor, points: torch.Tensor, rows, out: torch.Tensor, on_step) -> torch.Tensor:
    """:func:`_outputs` into ``out``."""
    n = points.numel()
    i = int(torch.searchsorted(points, points[0], right=True))  # the outputs at the start: the initial states
    out[:i] = y0 if rows is None else y0[rows[:i]]
    shape = (-1, *([1] * y0.dim())) if rows is None else (-1, 1)
    while i < n:
        state = solver.rk_state
        if points[i] > state.t1:  # torchdiffeq's _advance: step until the next output time is inside the step
            solver.rk_state = solver._adaptive_step(state)
            if on_step is not None:
                solver.rk_state = on_step(solver.rk_state)
            continue
        j = max(int(torch.searchsorted(points, state.t1, right=True)), i + 1)  # outputs i .. j - 1 in this step
        x = ((points[i:j] - state.t0) / (state.t1 - state.t0)).to(y0.dtype).reshape(shape)
        c = state.interp_coeff if rows is None else [coefficient[rows[i:j]] for coefficient in state.interp_coeff]
        total, power = c[0] + x * c[1], x
        for coefficient in c[2:]:
            power = power * x
            total = total + power * coefficient
        out[i:j] = total
        i = j
    return out


def widened_box(points: torch.Tensor, widths: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)`` ``(d,)``: the box of ``points (N, d)`` widened by ``widths`` times its width on each side (a width
    of at least a tenth of the component's size where the points do not vary): where a solve may stop a row that
    leaves it (``box=`` of :func:`solve`; the design's proxies, the posterior's draws, the held-out predictions of
    cross-validation). NaN entries are not points; a component without any is unbounded."""
    seen = ~torch.isnan(points)
    lo = torch.where(seen, points, torch.full_like(points, math.inf)).min(0).values
    hi = torch.where(seen, points, torch.full_like(points, -math.inf)).max(0).values
    some = seen.any(0)
    lo, hi = torch.where(some, lo, torch.zeros_like(lo)), torch.where(some, hi, torch.zeros_like(hi))
    width = (hi - lo).clamp_min(0.1 * torch.maximum(lo.abs(), hi.abs())).clamp_min(1e-9)
    unbounded = torch.full_like(lo, math.inf)
    return torch.where(some, lo - widths * width, -unbounded), torch.where(some, hi + widths * width, unbounded)


def power_of_ten(values: torch.Tensor) -> float:
    """The power of ten nearest the root mean square of the finite entries of ``values`` (1 when there are none or
    they are all 0)."""
    v = values[torch.isfinite(values)]
    rms = float(v.double().pow(2).mean().sqrt()) if v.numel() else 0.0
    if not (math.isfinite(rms) and rms > 0):
        return 1.0
    return 10.0 ** round(math.log10(rms))


def state_scales(y0: torch.Tensor, floor: torch.Tensor | None = None) -> torch.Tensor | None:
    """``(d,)``: each component's :func:`power_of_ten` over the initial states ``y0 (B, d)``, at most that of its
    ``floor`` ``(d,)`` where finite and positive (the smallest magnitude the solve must resolve; ``None``: none)
    (``None`` when they are all 1: the solve then uses the tolerances as given, bit for bit)."""
    flat = y0.detach().reshape(-1, y0.shape[-1])
    scales = [power_of_ten(flat[:, j]) for j in range(flat.shape[-1])]
    if floor is not None:
        low = [float(v) for v in floor.detach().reshape(-1).tolist()]
        scales = [
            min(s, power_of_ten(torch.tensor([v]))) if math.isfinite(v) and v > 0 else s
            for s, v in zip(scales, low, strict=True)
        ]
    if all(s == 1.0 for s in scales):
        return None
    return torch.tensor(scales, dtype=y0.dtype, device=y0.device)


def _integrate(
    func, y0: torch.Tensor, times: torch.Tensor, method: str, rtol: float, atol: float, options, partial=False
):
    """The solution ``(B, T, d)`` at ``times`` (``(T,)``, or ``(B, T)`` each row's own, relative to the start 0),
    one batched solve. With an adaptive Runge-Kutta method on a long grid each step's outputs are interpolated at
    once, and on per-row grids only each row's own (:func:`_outputs`); otherwise ``odeint`` on the sorted union of
    the grids, each row's times gathered from it (B times the outputs, and torchdiffeq's loop over every one).
    With ``partial``, an adaptive Runge-Kutta method interpolates the outputs itself on any grid (the same numbers)
    and an exception raised during the solve carries ``exc.partial``: the solution ``(B, T, d)`` up to the last
    output reached, NaN after."""
    ragged = times.dim() == 2
    grid, inverse = torch.unique(times.reshape(-1), sorted=True, return_inverse=True) if ragged else (times, None)
    vector = grid.numel() >= _VECTOR_OUTPUTS or partial
    solver = _solver(func, y0, grid, method, rtol, atol, options) if vector else None
    on_step = func.stop_outside if solver is not None and getattr(func, "stopped", None) is not None else None
    if solver is None:
        if isinstance(func, _Autonomous):  # odeint's steps: the box applies to every stage's state
            func.stopped = func.guard = None
        sol = odeint(func, y0, grid, method=method, rtol=rtol, atol=atol, options=options).transpose(0, 1)
        if not ragged:
            return sol
        return torch.gather(sol, 1, inverse.reshape(times.shape).unsqueeze(-1).expand(-1, -1, sol.shape[-1]))
    fill = math.nan if partial else None
    if not ragged:
        try:
            return _outputs(solver, y0, grid, fill=fill, on_step=on_step).transpose(0, 1)
        except BaseException as exc:
            if hasattr(exc, "outputs"):
                exc.partial = exc.outputs.transpose(0, 1)
            raise
    flat = times.reshape(-1)
    order = torch.argsort(flat, stable=True)

    def placed(values: torch.Tensor) -> torch.Tensor:
        out = torch.empty((flat.numel(), y0.shape[-1]), dtype=y0.dtype, device=y0.device)
        out[order] = values
        return out.reshape(*times.shape, y0.shape[-1])

    try:
        owner = torch.div(order, times.shape[1], rounding_mode="floor")
        return placed(_outputs(solver, y0, flat[order], owner, fill, on_step))
    except BaseException as exc:
        if hasattr(exc, "outputs"):
            exc.partial = placed(exc.outputs)
        raise


def check_solver_settings(method, rtol, atol, options, max_steps) -> tuple[float, float, int]:
    """``(rtol, atol, max_steps)`` checked (``max_steps`` :data:`DEFAULT_MAX_STEPS` for ``None``), with ``method`` and
    ``options`` checked too: one check for :func:`solve` and :class:`~torchmisspec.Solver`, so that bad settings are
    refused with the same message wherever they are given."""
    max_steps = DEFAULT_MAX_STEPS if max_steps is None else check_positive_int(max_steps, "max_steps")
    rtol, atol = check_real(rtol, "rtol", positive=True), check_real(atol, "atol", positive=True)
    for name, value in (("rtol", rtol), ("atol", atol)):  # atol is in units of each state's scale
        if value >= 1.0:
            raise InputError(
                f"{name}: expected a tolerance below 1 (an error as large as the state itself accepts any path; the "
                f"defaults are of order 1e-7), got {value:g}"
            )
    if not isinstance(method, str):
        raise InputError(f"method: expected a torchdiffeq method name such as 'dopri5', got {method!r:.60}")
    if options is not None and not (isinstance(options, dict) and all(isinstance(k, str) for k in options)):
        raise InputError(
            f"options: expected a dict of torchdiffeq solver options (e.g. {{'step_size': 0.01}}) or None, got "
            f"{options!r:.60} ({type(options).__name__})"
        )
    return rtol, atol, max_steps


def solve(
    field: Callable[[torch.Tensor], torch.Tensor],
    y0: torch.Tensor,
    times: torch.Tensor,
    *,
    method: str = "dopri5",
    rtol: float = PREDICTION_TOLERANCES[0],
    atol: float = PREDICTION_TOLERANCES[1],
    options: dict | None = None,
    max_steps: int | None = None,
    what: str = "ODE",
    label: Callable[[int], str] | None = None,
    timed: bool = False,
    jumps: torch.Tensor | None = None,
    box: tuple[torch.Tensor, torch.Tensor] | None = None,
    partial: bool = False,
    floor: torch.Tensor | None = None,
) -> tuple[torch.Tensor, int]:
    """Integrate dy/dt = field(y) from ``y0 (B, d)`` given at ``times[..., 0]``.

    Args:
        field: ``field(y (B, d)) -> (B, d)``; with ``timed=True``, ``field(t (B,), y (B, d))``, ``t`` every row's
            own time (rows on their own grids are integrated together, each shifted by its start time).
        jumps: with ``timed=True``, times where the field jumps (a piecewise-constant control): the adaptive
            solvers never step across one (torchdiffeq's ``jump_t``).
        times: ``(T,)`` shared by all, or ``(B, T)`` one grid per initial condition; each row starts at the
            time of its initial condition. Rows may start at different times.
        max_steps: most solver steps (default :data:`DEFAULT_MAX_STEPS`); the solve stops with
            :class:`IntegrationError` beyond it (counted as right-hand-side evaluations, so it holds for every
            method and under ``python -O``).
        label: names batch row i in error messages (e.g. ``"sample 3 of initial condition 7"``); default: the
            row index.
        box: ``(lo, hi)`` bounds ``(d,)``: a row whose state leaves them stops there (its derivative is set to 0),
            so that a trajectory that blows up does not hold back the batch's steps; its states from then on lie
            outside the box (the caller finds such rows there).
        partial: keep what the solve computed: an :class:`IntegrationError` raised while integrating carries
            ``exc.states``, the solution ``(B, T, d)`` up to the last output time reached (and, for rows whose
            solution turns non-finite, up to their last finite output), NaN after; ``None`` where the method
            cannot keep it (a method other than torchdiffeq's adaptive Runge-Kutta ones). Every
            :class:`IntegrationError` of the solve carries ``exc.rows`` (the likeliest culprits) and ``exc.nfe``.
        floor: ``(d,)`` the smallest magnitude of each component the solve must resolve to about ``rtol`` (NaN or 0:
            none): its ``atol`` scale is then at most that magnitude's power of ten (:func:`state_scales`). What a
            relative noise model compares are logarithms, so a value of 1e-6 measured beside a dose of 5 must be
            solved to a few digits too (:meth:`~torchmisspec.noise.NoiseModel.resolution`).

    Returns:
        states ``(B, T, d)`` and the number of right-hand-side evaluations.
    """
    rtol, atol, max_steps = check_solver_settings(method, rtol, atol, options, max_steps)
    if y0.dtype not in _FLOAT_DTYPES:
        raise InputError(
            f"{what}: expected float32 or float64 states, got {y0.dtype} (half precision cannot meet the solver's "
            "tolerances); convert with .double()"
        )
    scales = state_scales(y0, floor)
    atol = atol if scales is None else atol * scales  # in units of each state's scale (module docstring)

    grid, rel, offsets = _shifted_grid(times, y0.shape[0])
    func = _Autonomous(field, max_steps * EVALS_PER_STEP, what, 0.0, offsets.detach() if timed else None, box)
    if box is not None and partial:  # the box checked at the accepted steps (_Autonomous.stop_outside)
        width = box[1] - box[0]
        func.stopped = torch.zeros(y0.shape[0], dtype=torch.bool, device=y0.device)
        func.guard = (box[0] - 10.0 * width, box[1] + 10.0 * width)
    if timed and jumps is not None and method in _JUMPING:
        options = _with_jumps(options, jumps, offsets, grid)
    func.min_advance = _STALL_FRACTION * float(grid[-1] - grid[0])
    _check_start(field, func, y0, grid, offsets, timed, label)
    settings = dict(method=method, rtol=rtol, atol=atol, options=options)
    sol = _integrate_explained(func, y0, rel, settings, partial, box=box, label=label, max_steps=max_steps)
    finite = torch.isfinite(sol).all(dim=-1).all(dim=-1)
    if not bool(finite.all()):
        bad = (~finite).nonzero().flatten().tolist()
        reached = torch.isfinite(sol).all(dim=-1).cumprod(dim=-1).bool()  # (B, T): up to each row's last finite
        raise _with_rows(
            bad,
            IntegrationError(
                f"{what}: the solution is not finite for {len(bad)} of {sol.shape[0]} initial condition(s) "
                f"({_row_names(bad, label)}); the trajectory blows up within the time span"
            ),
            torch.where(reached.unsqueeze(-1), sol, math.nan) if partial else None,
            func.nfe,
        )
    return sol, func.nfe


def _row_names(rows: list[int], label) -> str:
    """The first ten of ``rows`` for an error message: by ``label(i)`` where given, else as indices."""
    more = " ..." if len(rows) > 10 else ""
    if label is None:
        return f"indices {rows[:10]}{more}"
    return "; ".join(label(i) for i in rows[:10]) + more


def _shifted_grid(times: torch.Tensor, batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(grid, rel, offsets)``: the solver's grid, every row's times relative to the solve's start, and each row's
    start time. Per-row grids ``(B, T)`` are shifted to start at 0, so that one solve serves every row (a timed
    field gets each row's own time back) and each row is read at its own times (:func:`_integrate`)."""
    if times.dim() == 1:
        return times, times, times.new_zeros(batch)
    rel = times - times[:, :1]
    return torch.stack([rel.min(), rel.max()]), rel, times[:, 0]  # the span


def _with_jumps(options, jumps: torch.Tensor, offsets: torch.Tensor, grid: torch.Tensor):
    """``options`` with torchdiffeq's ``jump_t``: the field's jumps inside the span on the solver's (shifted) time,
    so that an adaptive solver never steps across one."""
    inner = jumps.to(grid).reshape(1, -1) - offsets.detach().to(grid).reshape(-1, 1)
    inner = torch.unique(inner[(inner > grid[0]) & (inner < grid[-1])])
    return {**(options or {}), "jump_t": inner} if inner.numel() else options


def _check_start(field, func: _Autonomous, y0, grid, offsets, timed: bool, label) -> None:
    """Refuse a field of the wrong shape or not finite at the initial conditions, before any step: the message then
    names the initial conditions, not a step of the solver."""
    with torch.no_grad():
        f0 = field(grid[0] + offsets, y0) if timed else field(y0)
    if not isinstance(f0, torch.Tensor) or f0.shape != y0.shape:
        func(grid[0], y0)  # raises the shape error
    if not bool(torch.isfinite(f0).all()):
        bad = (~torch.isfinite(f0).all(-1)).nonzero().flatten().tolist()
        raise IntegrationError(
            f"{func.what}: the right-hand side is not finite at {len(bad)} initial condition(s) "
            f"({_row_names(bad, label)}); the model has a singularity there (check G and F)"
        )


def _integrate_explained(func: _Autonomous, y0, rel, settings: dict, partial: bool, *, box, label, max_steps: int):
    """:func:`_integrate`, with the solver's failures raised as :class:`IntegrationError` saying what happened, where,
    and which initial conditions are likeliest at fault (on ``exc.rows``), and a refusal of the solver's settings as
    :class:`InputError`; an error of the field itself passes unchanged."""
    what, span = func.what, f"[{float(rel.min()):.4g}, {float(rel.max()):.4g}]"
    try:
        return _integrate(func, y0, rel, **settings, partial=partial)
    except (_StepLimit, _Stalled, AssertionError) as exc:
        if isinstance(exc, AssertionError) and func.failed:  # an assertion inside the field (G, F), not the solver's
            raise
        worst, suspects = _culprits(func, box)
        names = _row_names(worst, label)
        if isinstance(exc, _StepLimit):
            message = (
                f"{what}: the solver took more than {max_steps} steps (the budget is counted in right-hand-side "
                f"evaluations, {EVALS_PER_STEP} per step, so that it binds every method: {func.nfe - 1} of them) and "
                f"stopped at t = {float(func.last_t):.4g} of {span}. The problem is stiff there or a trajectory blows "
                f"up; the initial conditions with the largest state or derivative at that point: {names}. Check "
                "those initial conditions, shorten the time span, or raise max_steps=... (solver=Solver(max_steps=...) "
                "for the corrected model; a stiff problem needs many explicit steps)"
            )
        elif isinstance(exc, _Stalled):
            message = (
                f"{what}: the solver stalled at t = {float(func.last_t):.6g} of {span}: 100 steps advanced time by "
                f"less than {_STALL_FRACTION:g} of the span, so a trajectory blows up there, or reaches a singularity "
                f"of the model or a state where the field changes abruptly; the initial conditions with the largest "
                f"state or derivative there: {names}. Check the model near those states, or shorten the time span"
            )
        else:  # torchdiffeq signals step-size underflow and non-finite states with assertions
            t = "" if func.last_t is None else f" at t = {float(func.last_t):.4g} of {span}"
            message = (
                f"{what}: the solver gave up{t} ({str(exc)[:120]}); the initial conditions with the largest state or "
                f"derivative there: {names}. A trajectory probably blows up or reaches a singularity of the "
                "model: shorten the time span, start closer to the data, or check the model"
            )
        error = _with_rows(worst, IntegrationError(message), getattr(exc, "partial", None), func.nfe, suspects)
        raise error from (exc if isinstance(exc, AssertionError) else None)
    except TorchMisspecError:  # the field's checks (G of the wrong shape, an error in the user's G): as they are
        raise
    except ValueError as exc:  # an unknown method or option
        if func.failed:  # raised inside the field (G, F): not a refusal of the solver's settings
            raise
        raise InputError(f"{what}: expected solver settings torchdiffeq accepts, got a refusal: {exc}") from exc
