"""Beyond a finite candidate list: the chosen initial states moved by gradients of the criterion.

A greedy design picks from the candidates it is given; the best experiments may lie between them. The information
gain f(S) = (d_out / 2) logdet(I + K(P_S, P_S) / sigma^2) is differentiable in the initial states: the proxy
trajectories P_S come from a differentiable solve (G alone, or G + the GP's posterior mean once data are in) and the
kernel is smooth. :func:`refine` starts from a design's points and climbs f with Adam, all K initial states at
once (and, with ``control_box``, the levels of their input profiles), inside a box (each state is
``lo + (hi - lo) * sigmoid(z)``, so the box is never left), conditioned on the GP's data like
:func:`~torchmisspec.design.greedy`. f is not concave in the states: the result is a local improvement of the
greedy's set (never worse: the best iterate is kept, the start included).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .._errors import InputError
from .._linalg import logdet_identity_plus
from .._ode import FITTING_TOLERANCES, solve
from .._validation import check_domain, check_positive_int, check_real, progress_bar
from ..gp import CorrectionGP
from ..signals import Controls
from ..systems import MisspecifiedSystem
from ._common import GPKernel, check_candidates, check_system, check_times
from ._proxy import choose_proxy

__all__ = ["Refinement", "refine"]


@dataclass(frozen=True)
class Refinement:
    """Initial states moved by gradients of the criterion (:func:`refine`).

    Attributes:
        points: ``(K, d)`` the refined initial states.
        start: ``(K, d)`` the states it started from.
        information_gain: the criterion at ``points`` (nats, real-Gaussian convention).
        start_gain: the criterion at ``start``.
        history: the criterion at every step.
        controls: with ``control_box``, the refined input profiles (the same knots, new levels); else the ones
            given (or ``None``).
    """

    points: torch.Tensor
    start: torch.Tensor
    information_gain: float
    start_gain: float
    history: tuple[float, ...]
    controls: object = None


def _box(spec, name: str, dim: int, kd: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi - lo)`` of a box given as one ``(lo, hi)`` per coordinate."""
    bounds = torch.tensor(check_domain(spec, name, dim=dim), **kd)
    return bounds[:, 0], (bounds[:, 1] - bounds[:, 0]).clamp_min(torch.finfo(bounds.dtype).tiny)


def _logits(x: torch.Tensor, lo: torch.Tensor, span: torch.Tensor) -> torch.Tensor:
    """The unconstrained coordinates z of ``x = lo + span * sigmoid(z)`` (1e-6 inside the box's faces)."""
    return torch.logit(((x - lo) / span).clamp(1e-6, 1 - 1e-6)).detach()


def _objective(system, gp, kern, times, proxy):
    """``f(y0 (K, d), controls) -> information gain`` (a differentiable scalar, in the states and the profiles'
    levels)."""
    if proxy == "corrected":
        from ..learning.refinement.trajectory_fit import _mean_field

        rhs = _mean_field(system, gp.posterior())
    else:

        def rhs(y, t, u):
            return system.known_rhs(y, t, u)

    def gain(y0: torch.Tensor, controls=None) -> torch.Tensor:
        field, timed, jumps = system.solver_field(rhs, controls)
        paths, _ = solve(
            field,
            y0,
            times,
            timed=timed,
            jumps=jumps,
            rtol=FITTING_TOLERANCES[0],
            atol=FITTING_TOLERANCES[1],
            what="design.refine",
        )
        u = None if controls is None or not system.uses_controls else controls.at(times.expand(y0.shape[0], -1))
        x = kern.expand(system.select_inputs(paths, u).reshape(-1, system.input_dim))
        logdet, _ = logdet_identity_plus(kern.differentiable(x), kern.noise, "I + K / noise_variance (design.refine)")
        return 0.5 * kern.multiplicity(system.output_dim) * logdet

    return gain


def refine(
    initial_states,
    *,
    system: MisspecifiedSystem,
    times,
    gp: CorrectionGP,
    box,
    controls=None,
    control_box=None,
    steps: int = 60,
    lr: float = 0.1,
    proxy: str | None = None,
    condition: bool | None = None,
    progress: bool = False,
) -> Refinement:
    """Move ``initial_states`` within ``box`` to raise the information gain of their experiments.

    Args:
        initial_states: ``(K, d)`` the states to start from (e.g. ``design.greedy(...).points``), inside ``box``.
        system: the misspecified system.
        times: ``(T,)`` observation times.
        gp: the correction GP (a prior with its hyperparameters set, or fitted: then conditioned on its data).
        box: where the initial states may go, one ``(lo, hi)`` per state component (e.g. the candidates' range).
        controls: for a system with inputs, the K experiments' profiles (kept fixed unless ``control_box``).
        control_box: one ``(lo, hi)`` per input: the profiles' levels (their sampled values, at the same knots) are
            refined too, within these bounds; needs sample-based ``controls`` (not a function).
        steps: Adam steps.
        lr: Adam's step size in the box's logit coordinates.
        proxy: ``"known"`` (G alone) or ``"corrected"`` (G + the GP's mean; default for a fitted GP).
        condition: condition on the GP's training samples (default: when it is fitted), as ``greedy`` does.
        progress: a progress bar over the steps.

    Returns:
        :class:`Refinement`: the best states met (the start included), their criterion and the history.
    """
    system = check_system(system, controls, with_controls=True)
    if not isinstance(gp, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP, got {type(gp).__name__}")
    kern = GPKernel(gp, input_dim=system.input_dim, condition=condition, system=system)
    kd = dict(dtype=kern.dtype, device=kern.device)
    y0 = check_candidates(initial_states, system, name="initial_states", **kd)
    lo, span = _box(box, "box (one (lo, hi) per state component)", system.state_dim, kd)
    outside = ~((y0 >= lo) & (y0 <= lo + span)).all(dim=-1)
    if bool(outside.any()):
        first = int(outside.nonzero()[0])
        raise InputError(
            f"initial_states: expected every state inside box, got {int(outside.sum())} outside (first: row {first}, "
            f"{[round(v, 6) for v in y0[first].tolist()]}); clamp them or widen the box"
        )
    t = check_times(times, **kd)
    steps = check_positive_int(steps, "steps")
    lr = check_real(lr, "lr", positive=True)
    controls = system.check_controls(controls, y0.shape[0])
    levels = None
    if control_box is not None:
        if controls is None or getattr(controls, "_function", None) is not None:
            raise InputError(
                "control_box: refining input levels needs controls given as samples (Controls(knots, values))"
            )
        c_lo, c_span = _box(control_box, "control_box (one (lo, hi) per input)", system.num_controls, kd)
        values = controls.values.to(**kd)
        if not bool(((values >= c_lo) & (values <= c_lo + c_span)).all()):
            raise InputError(
                f"controls: expected every level inside control_box, got levels from {float(values.min()):g} to "
                f"{float(values.max()):g}; clamp them or widen the box"
            )
        levels = _logits(values, c_lo, c_span).requires_grad_(True)

        def profiles(w: torch.Tensor):
            return Controls(controls.knots, c_lo + c_span * torch.sigmoid(w), kind=controls.kind, names=controls.names)

    proxy = choose_proxy(proxy, gp)
    gain = _objective(system, gp, kern, t, proxy)
    z = _logits(y0, lo, span).requires_grad_(True)
    params = [z] if levels is None else [z, levels]
    opt = torch.optim.Adam(params, lr=lr)
    best_value, best, best_controls = None, y0.detach().clone(), controls
    history = []
    bar = progress_bar(progress, steps, "design.refine: climbing the criterion", "step")
    for _ in range(steps + 1):
        opt.zero_grad()
        states = lo + span * torch.sigmoid(z)
        current = controls if levels is None else profiles(levels)
        value = gain(states, current)
        history.append(float(value.detach()))
        if best_value is None or history[-1] > best_value:
            best_value, best = history[-1], states.detach().clone()
            best_controls = current if levels is None else profiles(levels.detach())
        if len(history) == steps + 1:
            break
        grads = torch.autograd.grad(-value, params)  # to the experiments only (the GP's hyperparameters stay put)
        for p, g in zip(params, grads, strict=True):
            p.grad = g
        opt.step()
        bar.update()
    bar.close()
    with torch.no_grad():
        start_gain = float(gain(y0, controls))
    if start_gain >= best_value:  # the logit start is the start up to 1e-6 of the box: keep the exact one
        best_value, best, best_controls = start_gain, y0.detach().clone(), controls
    return Refinement(best, y0.detach().clone(), best_value, start_gain, tuple(history), best_controls)
