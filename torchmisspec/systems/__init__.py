"""Misspecified dynamical systems dy/dt = G(y) + F(y) and the paper's two set-ups.

A :class:`MisspecifiedSystem` carries the known right-hand side G, the state dimension, and (for simulation and
benchmarks only) the true correction F. F may act on some state components (``correction_outputs``) and depend on
others (``correction_inputs``), as in the gravity set-up of paper §5.3 where F maps positions to accelerations.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterable, Sequence

import torch

from .._errors import InputError, ShapeError, TorchMisspecError
from .._user_code import call_user, check_signatures, checked_output, import_module, one_line, where
from .._validation import (
    as_tensor,
    check_broadcasts,
    check_domain,
    check_finite,
    check_indices,
    check_last_dim,
    check_names,
    check_positive_int,
)
from ..parameters import check_priors
from ..signals import Controls
from ._fields import LinearField, PointMassGravity, QuadraticField, ZeroField
from ._rows import rows_of

__all__ = [
    "MisspecifiedSystem",
    "LinearField",
    "QuadraticField",
    "PointMassGravity",
    "paper_linear",
    "paper_gravity",
    "PAPER_GRAVITY_KNOWN_MASS",
    "data_driven",
    "ZeroField",
    "get_system",
    "load_system",
    "SYSTEMS",
]


class MisspecifiedSystem:
    """An ODE dy/dt = G(y) + F(x) whose G is known and whose F is the correction to learn.

    x are the *correction inputs*: some state components and, for a system with controls, some of the known input
    signals u(t) of the experiments (a dilution rate, a dose; :class:`~torchmisspec.signals.Controls`).

    Args:
        known: G. For an autonomous system without controls (the default), ``G(y)`` maps states ``(..., d)`` to
            ``(..., d)``. With ``num_controls > 0`` or ``time_dependent=True`` it is ``G(t, y, u)``: times
            ``(...)`` (broadcast against the states' leading dimensions, possibly a scalar), states ``(..., d)`` and
            controls ``(..., m)`` (``m = 0``: an empty last axis) to ``(..., d)``.
        state_dim: d.
        correction: the true F (simulation and benchmarks only); maps ``(..., len(correction_inputs))`` to
            ``(..., len(correction_outputs))``. ``None`` for a system whose true correction is unknown.
        correction_inputs: what F depends on (default: every state component): indices into the states followed by
            the controls (``0 .. d - 1`` the states, ``d .. d + m - 1`` the controls), or their names
            (``state_names`` / ``control_names``).
        correction_outputs: the state components F acts on, by index or by name (default: all).
        num_controls: m, the number of known input signals of every experiment (default 0).
        control_names: the m controls' names (default ``u0, u1, ...``), distinct from the states' names.
        time_dependent: G depends on time itself (then it is called ``G(t, y, u)``).
        parameters: G's uncertain parameters, ``{name: (value, scale)}``, a Gaussian prior each (mean, standard
            deviation): G then takes them last, ``G(y, theta)`` or ``G(t, y, u, theta)``, ``theta`` a tensor ``(k,)``
            in this order; :func:`~torchmisspec.fit_correction` learns them with F (see
            :mod:`torchmisspec.parameters`); elsewhere G uses ``theta``, the prior mean until :meth:`at` fixes it.
        domain: optional box ``(lo, hi)`` per correction input, the region D where the correction is assessed.
        known_matrix: optional ``(d, d)`` matrix A when G(y) = A y, so proxies can use ``matrix_exp``.
        name: a label for printing.
        state_names: optional names of the d state components (e.g. ``["S", "I", "R"]``); what
            :func:`~torchmisspec.fit_correction` calls the correction's inputs when the data carry none.

    G and F must be vectorised: called with states ``(..., d)`` (any leading batch dimensions) they return a torch
    tensor ``(..., d)`` (F: ``(..., d_out)``), e.g. built with ``y[..., 0]`` and ``torch.stack(..., dim=-1)``.
    The first batched call checks this (against the same callable on one state) and names what is wrong. G's
    signature is checked here against the form this system calls it with (``G(y)``, ``G(y, theta)``,
    ``G(t, y, u)``, ``G(t, y, u, theta)``; F's against ``F(x)``), and an exception raised inside G or F is reported
    as an :class:`~torchmisspec.InputError` naming the user's file and line (the original chained to it).
    """

    def __init__(
        self,
        known: Callable[[torch.Tensor], torch.Tensor],
        state_dim: int,
        *,
        correction: Callable[[torch.Tensor], torch.Tensor] | None = None,
        correction_inputs: Sequence[int] | None = None,
        correction_outputs: Sequence[int] | None = None,
        domain: Sequence[Sequence[float]] | None = None,
        known_matrix: torch.Tensor | None = None,
        name: str = "system",
        state_names: Sequence[str] | None = None,
        num_controls: int = 0,
        control_names: Sequence[str] | None = None,
        time_dependent: bool = False,
        parameters=None,
    ) -> None:
        if not callable(known):
            raise InputError(f"known: expected a callable G(y), got {type(known).__name__}")
        if correction is not None and not callable(correction):
            raise InputError(f"correction: expected a callable F or None, got {type(correction).__name__}")
        state_dim = check_positive_int(state_dim, "state_dim")
        self.known = known
        self.state_dim = state_dim
        self.correction = correction
        self.num_controls = check_positive_int(num_controls, "num_controls", minimum=0)
        if not isinstance(time_dependent, bool):
            raise InputError(f"time_dependent: expected True or False, got {time_dependent!r}")
        self.time_dependent = time_dependent
        self.control_names = check_names(control_names, self.num_controls, "control_names", default="u")
        self.state_names = check_names(state_names, state_dim, "state_names")
        clash = [n for n in self.control_names if n in (self.state_names or ())]
        if clash:
            raise InputError(
                f"control_names: expected names apart from the states' (state and control names must be distinct: a "
                "name picks one state or one control), "
                f"got {clash} among the states {list(self.state_names)} and the controls {list(self.control_names)}; "
                "rename the control(s) or the state(s)"
            )
        correction_inputs = self._resolve(correction_inputs)
        self.correction_inputs = check_indices(
            tuple(range(state_dim)) if correction_inputs is None else correction_inputs,
            state_dim + self.num_controls,
            "correction_inputs" if self.num_controls == 0 else "correction_inputs (the states, then the controls)",
        )
        outputs = correction_outputs
        if (
            outputs is not None
            and not isinstance(outputs, (str, torch.Tensor))
            and isinstance(outputs, Iterable)
            and any(isinstance(i, str) for i in outputs)
        ):
            names = list(self.state_names or ())
            unknown = [i for i in outputs if isinstance(i, str) and i not in names]
            if unknown:
                raise InputError(f"correction_outputs: expected state names among {names}, or indices, got {unknown}")
            outputs = [names.index(i) if isinstance(i, str) else i for i in outputs]
        self.correction_outputs = check_indices(outputs, state_dim, "correction_outputs")
        if domain is not None:
            domain = check_domain(domain, "domain (one (lo, hi) per correction input)", dim=len(self.correction_inputs))
        self.domain = domain
        if known_matrix is not None:
            known_matrix = check_finite(as_tensor(known_matrix, "known_matrix", dtype=torch.float64), "known_matrix")
            if known_matrix.shape != (state_dim, state_dim):
                raise ShapeError(
                    f"known_matrix: expected shape ({state_dim}, {state_dim}), got {tuple(known_matrix.shape)}"
                )
        self.known_matrix = known_matrix
        self.name = name
        self.parameters = check_priors(parameters)
        check_signatures(self)
        self.theta = None if self.parameters is None else self.parameters.mean  # the value G is called with
        self._vectorised = {"G": False, "F": False}  # the first batched call of each is checked

    def _resolve(self, items):
        """``correction_inputs`` given by name: their positions among the states, then the controls."""
        if items is None or isinstance(items, torch.Tensor):
            return items
        if isinstance(items, (str, bytes)) or not isinstance(items, Iterable):
            raise InputError(
                f"correction_inputs / correction_outputs: expected a list of state (or control) indices or names, "
                f"got {items!r:.60} ({type(items).__name__})"
            )
        if not any(isinstance(i, str) for i in items):
            return items
        known = list(self.state_names or ()) + [None] * (self.state_dim - len(self.state_names or ()))
        known += list(self.control_names)
        out = []
        for i in items:
            if isinstance(i, str):
                if i not in known:
                    raise InputError(
                        f"correction_inputs: expected state or control names among {[k for k in known if k]}, or "
                        f"indices, got {i!r}"
                    )
                out.append(known.index(i))
            else:
                out.append(i)
        return out

    # ----------------------------------------------------------------------------------------------------------
    @property
    def autonomous(self) -> bool:
        """Whether G is G(y) (no controls, no time); otherwise it is called G(t, y, u)."""
        return self.num_controls == 0 and not self.time_dependent

    @property
    def uses_controls(self) -> bool:
        """Whether F depends on a control (then every evaluation of F needs the experiments' controls)."""
        return any(i >= self.state_dim for i in self.correction_inputs)

    @property
    def has_correction(self) -> bool:
        """Whether the true correction F is known (simulation / benchmark systems)."""
        return self.correction is not None

    @property
    def input_dim(self) -> int:
        return len(self.correction_inputs)

    @property
    def output_dim(self) -> int:
        return len(self.correction_outputs)

    def check_states(self, y: torch.Tensor, name: str = "states") -> torch.Tensor:
        """States ``(..., d)`` of this system as a real floating tensor (arrays and lists converted), or refused."""
        y = as_tensor(y, name)
        if y.dim() < 1 or y.shape[-1] != self.state_dim:
            raise ShapeError(
                f"{name}: expected a last dimension of size state_dim={self.state_dim} for system "
                f"'{self.name}', got shape {tuple(y.shape)}"
            )
        return y

    def select_inputs(self, y: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """The correction's inputs ``(..., d_in)`` from states ``(..., d)`` and, when F depends on controls, the
        controls ``(..., m)`` at the same times."""
        y = self.check_states(y, "y")
        u = None if u is None else as_tensor(u, "u")
        if self.correction_inputs == tuple(range(self.state_dim)):
            return y
        if not self.uses_controls:
            return y[..., list(self.correction_inputs)]
        if u is None or u.shape[:-1] != y.shape[:-1] or u.shape[-1] != self.num_controls:
            got = None if u is None else tuple(u.shape)
            raise ShapeError(
                f"system '{self.name}': F depends on the controls; expected controls of shape "
                f"{tuple(y.shape[:-1]) + (self.num_controls,)} with the states {tuple(y.shape)}, got {got}. Pass "
                "each experiment's controls (Trajectories(..., controls=...), predict(..., controls=...))"
            )
        return torch.cat([y, u.to(y)], dim=-1)[..., list(self.correction_inputs)]

    def select_outputs(self, v: torch.Tensor) -> torch.Tensor:
        """The correction's output components ``(..., d_out)`` of a full vector field ``(..., d)``."""
        v = check_last_dim(v, self.state_dim, "v", f"the states of system '{self.name}'", masks=True)
        if self.correction_outputs == tuple(range(self.state_dim)):
            return v
        return v[..., list(self.correction_outputs)]

    def embed(self, f: torch.Tensor) -> torch.Tensor:
        """Place a correction ``(..., d_out)`` on its output components of a zero ``(..., d)`` field."""
        f = check_last_dim(f, self.output_dim, "f", f"the correction outputs of system '{self.name}'", masks=True)
        if self.correction_outputs == tuple(range(self.state_dim)):
            return f
        out = f.new_zeros(f.shape[:-1] + (self.state_dim,))
        out[..., list(self.correction_outputs)] = f
        return out

    def state_names_for(self, trajectories=None) -> tuple[str, ...] | None:
        """The states' names: ``trajectories.state_names`` when they are not the defaults ``y0, y1, ...``, else this
        system's ``state_names``; ``None`` when neither names them."""
        names = getattr(trajectories, "state_names", None)
        if names is None or tuple(names) == tuple(f"y{i}" for i in range(len(names))):
            names = self.state_names
        return None if names is None or len(names) != self.state_dim else tuple(names)

    def input_names(self, trajectories=None) -> tuple[str, ...] | None:
        """The names of the correction's inputs: the states' from ``trajectories.state_names`` when they are not the
        defaults ``y0, y1, ...``, else from this system's ``state_names`` (``None`` when neither has names); the
        controls' from the trajectories' controls, else from ``control_names``."""
        names = self.state_names_for(trajectories)
        if names is None:
            return None
        controls = getattr(trajectories, "controls", None)
        every = tuple(names) + (self.control_names if controls is None else tuple(controls.names))
        return tuple(every[i] for i in self.correction_inputs)

    def check_controls(self, controls, batch: int, name: str = "controls"):
        """``controls`` for a batch of ``batch`` experiments: a :class:`~torchmisspec.signals.Controls` with one
        profile each when this system has controls, ``None`` when it has none (each refused otherwise)."""
        batch = check_positive_int(batch, "batch")
        if self.num_controls == 0:
            if controls is not None:
                raise InputError(
                    f"{name}: expected None, as system '{self.name}' has no controls (num_controls=0), got "
                    f"{type(controls).__name__}; "
                    "declare them with MisspecifiedSystem(..., num_controls=m)"
                )
            return None
        if not isinstance(controls, Controls):
            raise InputError(
                f"{name}: system '{self.name}' has {self.num_controls} control(s) {list(self.control_names)}; expected "
                f"a torchmisspec.signals.Controls with one profile per experiment, got {type(controls).__name__}"
            )
        if controls.num_controls != self.num_controls or controls.num_experiments != batch:
            raise ShapeError(
                f"{name}: expected {batch} profile(s) of {self.num_controls} control(s), got "
                f"{controls.num_experiments} "
                f"of {controls.num_controls}"
            )
        named = [n for n in (controls.names, self.control_names) if n != tuple(f"u{j}" for j in range(len(n)))]
        if len(named) == 2 and tuple(controls.names) != tuple(self.control_names):  # both named, otherwise
            order = "the same names in another order" if set(controls.names) == set(self.control_names) else "others"
            raise InputError(
                f"{name}: expected the controls of system '{self.name}' {list(self.control_names)}, in that order, got "
                f"{list(controls.names)} ({order}); build the Controls with its values' last axis in the system's "
                "order and names=... as the system's (a control read as another would be silently wrong)"
            )
        return controls

    def solver_field(self, rhs, controls=None) -> tuple:
        """``(field, timed, jumps)`` for the package's solve: ``rhs(y, t, u)`` (states ``(B, d)``, times ``(B,)`` or
        ``None``, controls ``(B, m)`` or ``None``) as the solver's field; an autonomous system's is ``field(y)``,
        any other's ``field(t, y)`` with the controls of ``controls`` at every row's time, and the profiles' jumps."""
        if self.autonomous:
            return (lambda y: rhs(y, None, None)), False, None

        def field(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            return rhs(y, t, None if controls is None else controls.at(t))

        return field, True, None if controls is None else controls.jumps

    def true_correction(self, x: torch.Tensor) -> torch.Tensor:
        """F at correction inputs ``x (..., d_in)``; raises if this system has no true correction."""
        if self.correction is None:
            raise InputError(
                f"system '{self.name}' has no true correction F; pass correction=... to MisspecifiedSystem "
                "(only simulation and benchmark systems have one)"
            )
        what = f"system '{self.name}': F"
        x = check_last_dim(x, self.input_dim, "x", f"the correction inputs of system '{self.name}'")
        return self._call("F", self.correction, x, x.shape[:-1] + (self.output_dim,), what)

    def known_rhs(self, y: torch.Tensor, t=None, u: torch.Tensor | None = None) -> torch.Tensor:
        """G for states ``(..., d)``, with its output shape checked (a G that returns the wrong shape would be
        broadcast silently by the sums that follow): ``G(y)`` for an autonomous system, else ``G(t, y, u)`` with the
        times ``t`` (a scalar or ``(...)``) and controls ``u (..., m)`` at those states (checked to be given)."""
        what = f"system '{self.name}': G"
        y = self.check_states(y, "y")  # G is blamed only for what it does with states of the right shape
        theta = () if self.theta is None else (self.theta.to(y),)
        if self.autonomous:
            return self._call("G", lambda z: self.known(z, *theta), y, y.shape, what)
        t, u = self._time_and_controls(y, t, u)
        return self._call("G", lambda z: self.known(t, z, u, *theta), y, y.shape, what)

    def rows_rhs(self, y: torch.Tensor, t, u: torch.Tensor | None, theta: torch.Tensor) -> torch.Tensor:
        """G for states ``(B, d)`` with each row's own uncertain parameters ``theta (B, k)`` (times and controls as in
        :meth:`known_rhs`): one call of G for the batch where G broadcasts or vmap traces it
        (:func:`~torchmisspec.systems._rows.per_row`), else one call per distinct theta."""
        return rows_of(self, y, t, u, theta)

    def __getstate__(self) -> dict:
        """Pickled and copied without the per-row caller (a closure; rebuilt at the next :meth:`rows_rhs`)."""
        state = dict(self.__dict__)
        state.pop("_rows", None)
        return state

    def at(self, theta) -> MisspecifiedSystem:
        """This system with its uncertain parameters fixed at ``theta`` ``(k,)`` (a system without uncertain ones)."""
        return self._with_theta(theta, None, "at(theta): expected a system with uncertain parameters to fix")

    def recentred(self, theta) -> MisspecifiedSystem:
        """This system with its uncertain parameters still uncertain (the same priors) but G evaluated, and
        linearised in them, at ``theta`` ``(k,)`` instead of the prior mean: its correction samples are the
        residuals there (:func:`~torchmisspec.correction_samples`)."""
        expected = "recentred(theta): expected a system with uncertain parameters"
        if self.parameters is None:  # none declared, or fixed by at()
            raise InputError(f"system '{self.name}': {expected}, got one without")
        return self._with_theta(theta, self.parameters, expected)

    def _with_theta(self, theta, parameters, expected: str) -> MisspecifiedSystem:
        """A copy with ``theta`` (checked) and ``parameters``; ``expected`` the caller's words for a system without."""
        if self.theta is None:
            raise InputError(f"system '{self.name}': {expected}, got one without")
        theta = check_finite(as_tensor(theta, "theta", dtype=torch.float64), "theta").detach()
        if theta.shape != self.theta.shape:
            raise ShapeError(
                f"theta: expected shape {tuple(self.theta.shape)} (one value per parameter), got {tuple(theta.shape)}"
            )
        out = copy.copy(self)
        out.theta, out.parameters, out._vectorised = theta, parameters, dict(self._vectorised)
        return out

    def copies_rhs(self, thetas: torch.Tensor):
        """``rhs(y, t, u)``: G for a batch of ``V`` copies of this system, copy c's rows (the c-th of ``V`` equal
        blocks of ``y``'s rows) at ``thetas[c]`` ``(V, k)`` (the perturbed copies of a fit's Jacobian): one call of G
        with each row's theta (:meth:`rows_rhs`), or at the one theta they share."""
        unique = torch.unique(thetas.detach(), dim=0)
        if unique.shape[0] == 1:
            return self.at(unique[0]).known_rhs
        V = thetas.shape[0]

        def rhs(y, t=None, u=None):
            return self.rows_rhs(y, t, u, thetas.detach().to(y).repeat_interleave(y.shape[0] // V, 0))

        return rhs

    def _time_and_controls(self, y: torch.Tensor, t, u):
        if self.time_dependent and t is None:
            raise InputError(f"system '{self.name}': G depends on time; expected the times t with the states, got None")
        u = None if u is None else as_tensor(u, "u")
        if self.num_controls and (u is None or u.shape[:-1] != y.shape[:-1] or u.shape[-1] != self.num_controls):
            got = None if u is None else tuple(u.shape)
            raise ShapeError(
                f"system '{self.name}': G depends on {self.num_controls} control(s); expected controls of shape "
                f"{tuple(y.shape[:-1]) + (self.num_controls,)} with the states {tuple(y.shape)}, got {got}. Pass "
                "each experiment's controls (Trajectories(..., controls=...), predict(..., controls=...))"
            )
        t = y.new_zeros(()) if t is None else check_broadcasts(as_tensor(t, "t", dtype=y.dtype), y.shape[:-1], "t")
        u = y.new_zeros(y.shape[:-1] + (0,)) if u is None else u.to(y)
        return t.to(y.device), u

    def _call(self, key: str, fn, x: torch.Tensor, shape, what: str) -> torch.Tensor:
        """``fn(x)`` with its output checked; the first batched call also checks that ``fn`` broadcasts over the
        leading dimensions: a function written for one state (``y[0]``, ``torch.stack([...])`` along the first axis)
        can return the right shape for a batch whose size equals d and silently mix its rows."""
        out = checked_output(call_user(fn, x, what), shape, what, x)
        if self._vectorised[key] or x.dim() < 2 or x[..., :1].numel() == 0 or (key == "G" and not self.autonomous):
            return out  # G(t, y, u) reads per-row times and controls: a one-state call would need them too
        with torch.no_grad():
            try:
                single = fn(x.reshape(-1, x.shape[-1])[0])
            except Exception:  # noqa: BLE001 - it works on the batch: a function that needs one is allowed
                single = None
            first = out.reshape(-1, out.shape[-1])[0]
            if (
                isinstance(single, torch.Tensor)
                and single.shape == first.shape
                and not torch.allclose(single.to(first), first, rtol=1e-6, atol=1e-12, equal_nan=True)
            ):
                raise ShapeError(
                    f"{what} must broadcast over leading dimensions, states (..., d) -> (..., d): called with a batch "
                    f"of shape {tuple(x.shape)} it gave another value for the batch's first state than for that state "
                    "alone (it mixes the batch's rows). Write it with tensor operations on the last axis, e.g. "
                    "y[..., 0] instead of y[0], and torch.stack([...], dim=-1) for the result"
                )
        self._vectorised[key] = True
        return out

    def true_rhs(self, y: torch.Tensor, t=None, u: torch.Tensor | None = None) -> torch.Tensor:
        """G + F at states ``(..., d)`` (just G when the system has no true correction); ``t`` and ``u`` as for
        :meth:`known_rhs`."""
        g = self.known_rhs(y, t, u)
        if self.correction is None:
            return g
        return g + self.embed(self.true_correction(self.select_inputs(y, u)))

    def __repr__(self) -> str:
        controls = f"num_controls={self.num_controls}, " if self.num_controls else ""
        timed = "time_dependent=True, " if self.time_dependent else ""
        timed += f"parameters={list(self.parameters.names)}, " if self.parameters is not None else ""
        return (
            f"MisspecifiedSystem(name={self.name!r}, state_dim={self.state_dim}, {controls}{timed}"
            f"correction_inputs={list(self.correction_inputs)}, correction_outputs={list(self.correction_outputs)}, "
            f"has_correction={self.has_correction})"
        )


# ---------------------------------------------------------------------------------------------------------------
PAPER_LINEAR_A = ((0.02, 0.10), (-0.10, -0.06))


def paper_linear() -> MisspecifiedSystem:
    """Paper §5.1: G(y) = A y with A = [[0.02, 0.10], [-0.10, -0.06]], true F(y) = 0.01 [y1^2, y2^2].

    The domain is D = [-1, 1]^2; the paper observes t in [0, 6] at T = 11 times.
    """
    A = torch.tensor(PAPER_LINEAR_A, dtype=torch.float64)
    return MisspecifiedSystem(
        LinearField(A),
        2,
        correction=QuadraticField(0.01),
        domain=((-1.0, 1.0), (-1.0, 1.0)),
        known_matrix=A,
        name="paper_linear",
    )


PAPER_GRAVITY_KNOWN_MASS = 0.2  #: the mass at the origin that the known model G of :func:`paper_gravity` has


def paper_gravity() -> MisspecifiedSystem:
    """Paper §5.3: a unit mass in the plane, state (x1, x2, v1, v2).

    G: one mass :data:`PAPER_GRAVITY_KNOWN_MASS` at the origin. True F: masses 0.1 at (0, 4) and 0.4 at
    (0.5, 3.8), acting on the velocities (outputs 2, 3) and depending on the positions (inputs 0, 1). The paper
    does not state its domain D; we use the box [-2, 2]^2 around the central mass, where
    :func:`torchmisspec.design.candidates.orbits` places the initial positions.
    """
    return MisspecifiedSystem(
        PointMassGravity([PAPER_GRAVITY_KNOWN_MASS], [[0.0, 0.0]], first_order=True),
        4,
        correction=PointMassGravity([0.1, 0.4], [[0.0, 4.0], [0.5, 3.8]]),
        correction_inputs=(0, 1),
        correction_outputs=(2, 3),
        domain=((-2.0, 2.0), (-2.0, 2.0)),
        name="paper_gravity",
    )


def data_driven(system: MisspecifiedSystem) -> MisspecifiedSystem:
    """The fully data-driven view of ``system`` (paper §5.2): no known part, the whole G + F is to be learned.

    Its known model is zero and its true correction is G + F of the original system (so it needs a system whose
    correction inputs and outputs are all components). Fit a :class:`CorrectionGP` to its correction samples to get
    the data-driven estimator; its estimate of F is then (estimate - G).
    """
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {system!r:.60} ({type(system).__name__})")
    full = tuple(range(system.state_dim))
    if system.correction_inputs != full or system.correction_outputs != full:
        raise InputError(
            f"system '{system.name}': the data-driven view needs a correction on all components: expected every "
            "state as an input and an output, got "
            f"correction_inputs={list(system.correction_inputs)}, correction_outputs={list(system.correction_outputs)}"
        )
    return MisspecifiedSystem(
        ZeroField(),
        system.state_dim,
        correction=system.true_rhs,
        domain=system.domain,
        name=f"{system.name}_data_driven",
    )


SYSTEMS: dict[str, Callable[[], MisspecifiedSystem]] = {
    "paper_linear": paper_linear,
    "paper_gravity": paper_gravity,
}


def get_system(name: str) -> MisspecifiedSystem:
    """A built-in system by name (see :data:`SYSTEMS`)."""
    try:
        return SYSTEMS[name]()
    except (KeyError, TypeError):  # TypeError: an unhashable name (a list)
        raise InputError(f"system: expected one of {sorted(SYSTEMS)}, got the unknown name {name!r}") from None


def load_system(spec: str | MisspecifiedSystem) -> MisspecifiedSystem:
    """A system from a command-line style spec: a built-in name, ``module:function`` or ``path/to/file.py:function``.

    * a built-in name (see :data:`SYSTEMS`, e.g. ``"paper_linear"``) returns :func:`get_system` of it;
    * ``"module:function"`` imports ``module`` (a dotted name importable from ``sys.path``) and calls
      ``function()`` with no arguments; it must return a :class:`MisspecifiedSystem`;
    * ``"path/to/file.py:function"`` does the same with the module loaded from that file.

    Importing a user module runs its code, and so does calling the function: this is what a spec that names
    them asks for, so only pass specs you trust (the package itself never imports anything named in a data file).
    A :class:`MisspecifiedSystem` passed in, or named by the spec (a module-level system), is returned as it is.

    Raises:
        InputError: an unknown built-in name, a module that cannot be imported (with the import's error and its
            file and line), a missing or non-callable function, a function that raises (with its error and its file
            and line; a package error, such as a G whose signature does not fit the system, keeps its type), or
            one that returns something other than a MisspecifiedSystem.
    """
    if isinstance(spec, MisspecifiedSystem):
        return spec
    if not isinstance(spec, str):
        raise InputError(f"system: expected a name or 'module:function', got {type(spec).__name__}")
    if ":" not in spec:
        if spec not in SYSTEMS:
            raise InputError(
                f"unknown system name {spec!r}: expected one of {sorted(SYSTEMS)} or 'module:function' (a function "
                f"returning a MisspecifiedSystem), got {spec!r}"
            )
        return get_system(spec)
    module_name, _, function_name = spec.rpartition(":")
    if not module_name or not function_name.isidentifier():
        raise InputError(f"system: expected 'module:function' with a function name after the colon, got {spec!r}")
    module = import_module(module_name, spec)
    if not hasattr(module, function_name):
        public = sorted(n for n in dir(module) if not n.startswith("_") and callable(getattr(module, n, None)))
        raise InputError(
            f"system {spec!r}: expected a function {function_name!r} in module {module_name!r}, got none (the "
            f"module defines {public[:20]})"
        )
    function = getattr(module, function_name)
    if isinstance(function, MisspecifiedSystem):  # the system itself, built at the module's top level
        return function
    if not callable(function):
        raise InputError(f"system {spec!r}: expected {function_name!r} to be a function, got {type(function).__name__}")
    try:
        system = function()
    except TorchMisspecError as exc:  # the system it builds is refused (a G of the wrong form, clashing names)
        raise type(exc)(f"system {spec!r}: {exc}") from exc
    except Exception as exc:
        at = where(exc)
        raise InputError(
            f"system {spec!r}: expected {function_name}() to return a MisspecifiedSystem, got {one_line(exc)} when "
            "calling it" + (f" (at {at})" if at else "")
        ) from exc
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(
            f"system {spec!r}: expected {function_name}() to return a torchmisspec MisspecifiedSystem, got "
            f"{type(system).__name__}"
        )
    return system
