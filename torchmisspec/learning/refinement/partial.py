"""Partly measured states: which corrections the measurements see, and the states that were not measured.

A lab rarely measures every state: biomass but not substrate, infected but not susceptible. An experiment that
observes component j fewer than :data:`~torchmisspec.data.MIN_MEASURED` times does not *measure* it
(:attr:`Trajectories.measured <torchmisspec.Trajectories.measured>`). Derivatives of such a component cannot be
estimated, so the correction is learned through the ODE (:func:`~torchmisspec.fit_correction` does this by itself):

1. every experiment's unmeasured initial values that its first row does not give are estimated with the known
   model G alone (:func:`estimate_initial_states`: Levenberg-Marquardt on the measured values, one batched solve per
   step; the given ones are kept until the next step);
2. the unmeasured components are filled with the model's path (:func:`complete`), so that F's inputs are known;
3. a first model of F (the feature kernel's terms) is fitted through the ODE to what was measured, the initial
   states with it (sparse Bayesian learning with the unmeasured entries left out of the misfit), the data completed
   again with that model, and the usual model choice made on the completed data; a refinement through the ODE
   then fits the chosen model to the *measured* values (``refine``; by default by
   :func:`~torchmisspec.fit_correction`'s rule, and for any kernel when F acts on or depends on a component not
   measured directly, whose samples came from the first model's paths; autonomous systems).

**Uncertain parameters of G** are learned in step 3, with the first model's terms and the initial states (their
Levenberg-Marquardt problem, theta in units of its prior standard deviations). Their posterior is the Laplace one
from the same Gauss-Newton Hessian, the coefficients and initial states marginalised, or the cluster-robust sandwich
over experiments when that is wider on average (what the polynomial F misses of the true term is shared by an
experiment's times, and the Laplace posterior would let theta absorb it with unearned confidence). F is then chosen
and refined at theta's posterior mean. Derivative samples of the completed data are not used for theta: the
completed paths were drawn with a first model, and theta fitted to them stayed near that model's (on the chemostat,
3 to 4 of its standard deviations from the truth).

**Do no harm**: :func:`~torchmisspec.fit_correction` keeps a correction learned here only when it forecasts
held-out later times better than the known model alone (:mod:`torchmisspec.learning.choice._partial_choice`).

Whether the measurements can tell anything about F is structural (:func:`identifiability`): F acting on component
j is seen by the measurements when j is measured, or when j drives a measured component through G or F (a path in
the dependency graph of the right-hand side, found numerically from G's Jacobian at the data). A correction output
that no measured component sees cannot be learned from these data, and the fit refuses it.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import torch

from ..._errors import FittingError, InputError, IntegrationError, TorchMisspecWarning, warn
from ..._ode import FITTING_TOLERANCES, PREDICTION_TOLERANCES
from ...data import Trajectories
from ...data._trajectories import MIN_MEASURED
from ...parameters import ParameterPosterior, parameter_basis
from ...systems import MisspecifiedSystem
from ..samples._gp_in_time import observed_rms
from ..samples.observations import correction_samples
from ._first_model import FIRST_MODEL, FirstModel, first_model
from .trajectory_fit import _mean_field, _shooting, _solve_rhs, _state_noise, fit_trajectories

__all__ = [
    "Identifiability",
    "complete",
    "estimate_initial_states",
    "identifiability",
    "initial_guess",
]


@dataclass(frozen=True)
class Identifiability:
    """Which measured components see each component F acts on (:func:`identifiability`).

    Attributes:
        outputs: the names of the components F acts on (``system.correction_outputs``).
        seen_by: for each output, the measured components through which the data see it (itself first when it
            is measured); empty when none does.
        measured: the state components some experiment measures, and the readings of combinations of them
            (:attr:`Trajectories.readout <torchmisspec.Trajectories.readout>`) some experiment reads.
        unmeasured: the state components some experiment does not measure.
        unmeasured_inputs: F's inputs among them (their values come from the fitted paths).
    """

    outputs: tuple[str, ...]
    seen_by: tuple[tuple[str, ...], ...]
    measured: tuple[str, ...]
    unmeasured: tuple[str, ...]
    unmeasured_inputs: tuple[str, ...]

    @property
    def from_paths(self) -> bool:
        """Whether F's samples on the completed data rest on fitted paths: an output of F or one of its inputs is not
        measured directly (then the model chosen on those samples is refined through the ODE)."""
        direct = all(seen and seen[0] == out for out, seen in zip(self.outputs, self.seen_by, strict=True))
        return not direct or bool(self.unmeasured_inputs)

    @property
    def unseen(self) -> tuple[str, ...]:
        """The outputs of F that no measured component sees: not identifiable from these data."""
        return tuple(o for o, s in zip(self.outputs, self.seen_by, strict=True) if not s)

    def summary(self) -> str:
        """One line per output of F: measured, seen through which measured components, or not identifiable."""
        lines = []
        for out, seen in zip(self.outputs, self.seen_by, strict=True):
            if not seen:
                lines.append(f"F on d{out}/dt: not identifiable ({out} is not measured and drives no measured state)")
            elif seen[0] == out:
                lines.append(f"F on d{out}/dt: measured directly")
            else:
                lines.append(f"F on d{out}/dt: seen through {', '.join(seen)} ({out} is not measured)")
        if self.unmeasured_inputs:
            lines.append(
                f"F's inputs {', '.join(self.unmeasured_inputs)}: not measured in every experiment, taken from the "
                "fitted paths where not"
            )
        return "\n".join(lines)

    def check(self, system_name: str) -> None:
        """Raise :class:`InputError` when some output of F is not identifiable."""
        if self.unseen:
            names = ", ".join(self.unseen)
            one = len(self.unseen) == 1
            raise InputError(
                f"system '{system_name}': the correction acts on {names}, which no experiment measures and which "
                f"drive{'s' if one else ''} no measured component through G or F, so these data cannot inform it: "
                f"expected a measurement that sees {names}, got none (measured: "
                f"{', '.join(self.measured) or 'nothing'}); measure {names} in some experiment, or drop "
                f"{'it' if one else 'them'} from correction_outputs"
            )


def _dependencies(system: MisspecifiedSystem, states: torch.Tensor, times, controls, correction=True) -> torch.Tensor:
    """``(d, d)`` boolean: entry (a, b) when dy_b/dt depends on y_a through G (its Jacobian at the states, nonzero
    somewhere) or, with ``correction``, through F (a an input of F and b one of its outputs)."""
    d = system.state_dim
    y = states.detach().clone().requires_grad_(True)
    out = system.known_rhs(y, times, controls)
    depends = torch.zeros(d, d, dtype=torch.bool)
    for b in range(d):
        (grad,) = torch.autograd.grad(out[..., b].sum(), y, retain_graph=b < d - 1, allow_unused=True)
        if grad is not None:
            scale = grad.abs().amax().clamp_min(torch.finfo(grad.dtype).tiny)
            depends[:, b] = (grad.abs() > 1e-10 * scale).any(0).cpu()
    for a in system.correction_inputs if correction else ():
        if a < d:
            for b in system.correction_outputs:
                depends[a, b] = True
    return depends


def identifiability(
    system: MisspecifiedSystem, trajectories: Trajectories, *, completed: Trajectories | None = None
) -> Identifiability:
    """Which measured components see each output of F, from the dependency graph of G + F at the data.

    Component j is *seen* by measured component m when a chain j -> ... -> m of dependencies (dy_b/dt depending on
    y_a) exists, and by a reading of a combination (:attr:`Trajectories.readout
    <torchmisspec.Trajectories.readout>`) when such a chain reaches a state the reading weighs (a reading of a sum
    sees each of its terms, though not which one F changed: that is left to the fit through the ODE); the
    dependencies of G are read off its Jacobian at every state of ``completed`` (so a dependence that vanishes at
    all the data is missed). ``completed``: the data with the unmeasured components filled in
    (:func:`complete`); by default the paths of G alone from initial states estimated by
    :func:`estimate_initial_states`."""
    measured = trajectories.measured.any(0).cpu()  # (d,): measured in some experiment
    if completed is None:
        completed = _completed_by_g(system, trajectories)
    filled = completed.filled()
    states = filled.flat_states()
    keep = torch.isfinite(states).all(-1)
    times = filled.flat_times()[keep]
    controls = filled.flat_controls()
    controls = None if controls is None else controls[keep]
    depends = _dependencies(system, states[keep], times, controls)
    d = system.state_dim
    reach = depends | torch.eye(d, dtype=torch.bool)
    for _ in range(d):  # transitive closure: reach[a, b] when a chain a -> ... -> b exists
        reach = reach | ((reach.to(torch.int64) @ reach.to(torch.int64)) > 0)
    names = system.state_names_for(trajectories) or trajectories.state_names
    readout, read = trajectories.readout, []
    if readout is not None:  # a reading sees every state it weighs (when some experiment reads it often enough)
        values, mask = trajectories.observed_values()
        counts = (torch.isfinite(values[..., d:]) & mask.unsqueeze(-1)).sum(1)  # (K, m)
        weighs = (readout.matrix != 0).cpu()
        read = [
            (readout.names[r], weighs[r]) for r in range(weighs.shape[0]) if bool((counts[:, r] >= MIN_MEASURED).any())
        ]
    seen_by = []
    for j in system.correction_outputs:
        seen = [names[m] for m in range(d) if measured[m] and reach[j, m]]
        seen += [name for name, w in read if bool((reach[j] & w).any())]
        if measured[j]:  # itself first
            seen = [names[j]] + [s for s in seen if s != names[j]]
        seen_by.append(tuple(seen))
    unmeasured = [names[j] for j in range(d) if not bool(trajectories.measured[:, j].all())]
    inputs = [names[i] for i in system.correction_inputs if i < d and names[i] in unmeasured]
    return Identifiability(
        outputs=tuple(names[j] for j in system.correction_outputs),
        seen_by=tuple(seen_by),
        measured=tuple(names[j] for j in range(d) if measured[j]) + tuple(name for name, _ in read),
        unmeasured=tuple(unmeasured),
        unmeasured_inputs=tuple(inputs),
    )


def initial_guess(trajectories: Trajectories, system: MisspecifiedSystem | None = None) -> torch.Tensor:
    """``(K, d)`` starting values of the initial states: the first observed states (missing entries estimated by
    :meth:`Trajectories.filled`); a component never observed in an experiment starts at its mean over the
    experiments that observe it, or, when it is only read in combinations (:attr:`Trajectories.readout`), at the
    least-squares solution of the first readings given the states known there. A component no experiment observes
    at all, neither alone nor in a reading, starts at the data's scale (the mean magnitude of every observed value,
    1 when they are all 0; the unmeasured hares of a predator-prey model start at the size of the predator counts),
    with a warning: the fit through the ODE (:func:`estimate_initial_states`) then estimates it from the measured
    components it drives. With ``system``, one that drives no measured component through G (nothing could estimate
    it) raises :class:`InputError`."""
    first = trajectories.initial_conditions
    if trajectories.readout is not None:
        first = _from_readings(trajectories, first)[0]
    if bool(torch.isfinite(first).all()):
        return first
    flat = trajectories.flat_states()
    seen = torch.isfinite(flat)
    if trajectories.readout is not None:  # a state read in a combination counts as observed there
        values, _ = trajectories.observed_values()
        read = torch.isfinite(values[..., trajectories.state_dim :]).flatten(0, -2).any(0)  # (m,)
        seen = seen | ((trajectories.readout.matrix != 0) & read.unsqueeze(-1)).any(0)
    zero = torch.zeros((), dtype=flat.dtype, device=flat.device)
    known = seen & torch.isfinite(flat)
    mean = torch.where(known, flat, zero).sum(0) / known.sum(0).clamp_min(1)
    never = ~seen.any(0)
    if bool(never.any()):
        size = flat[torch.isfinite(flat)].abs().mean() if bool(torch.isfinite(flat).any()) else zero
        size = torch.where(size > 0, size, torch.ones_like(size))
        mean = torch.where(never, size, mean)
        _refuse_or_warn(trajectories, system, never, torch.where(torch.isfinite(first), first, mean), float(size))
    return torch.where(torch.isfinite(first), first, mean.expand_as(first))


def _refuse_or_warn(trajectories: Trajectories, system, never: torch.Tensor, start: torch.Tensor, size: float):
    """For :func:`initial_guess`: warn that the components ``never`` (``(d,)``) no experiment observes start at
    ``size``; with ``system``, raise :class:`InputError` naming those that drive no measured component through G
    (at the states started from ``start`` ``(K, d)``): nothing could estimate them."""
    names = trajectories.state_names
    stuck = torch.zeros_like(never)
    if system is not None:
        states = torch.where(torch.isfinite(trajectories.flat_states()), trajectories.flat_states(), start[:1])
        keep = torch.isfinite(states).all(-1)
        controls = trajectories.flat_controls()
        times = trajectories.flat_times()[keep]
        depends = _dependencies(system, states[keep], times, None if controls is None else controls[keep], False)
        reach = depends | torch.eye(depends.shape[0], dtype=torch.bool)
        for _ in range(reach.shape[0]):  # transitive closure: reach[a, b] when a chain a -> ... -> b exists
            reach = reach | ((reach.to(torch.int64) @ reach.to(torch.int64)) > 0)
        measured = (~never).cpu()
        stuck = never.cpu() & ~(reach & measured.unsqueeze(0)).any(1)
    if bool(stuck.any()):
        listed = ", ".join(repr(names[j]) for j in stuck.nonzero().flatten().tolist())
        raise InputError(
            f"trajectories: component {listed} is never observed in any experiment, so its initial values have "
            "nothing to start from and, as it drives no measured component through the known model, nothing to "
            "estimate them from; give each experiment's initial value of it in the first row, or measure it at "
            "least once"
        )
    listed = ", ".join(repr(names[j]) for j in never.nonzero().flatten().tolist())
    warn(
        f"trajectories: component {listed} is never observed in any experiment; its initial values start at "
        f"{size:.3g} (the mean magnitude of the observed values), from which the fit through the ODE estimates them; "
        "give a better start as each experiment's first-row value of it",
        TorchMisspecWarning,
    )


def _from_readings(trajectories: Trajectories, first: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``first (K, d)`` with its missing entries solved from each experiment's readings at its first time, given the
    known entries (the minimum-norm least-squares solution; entries the readings do not reach stay NaN), and the
    ``(K, d)`` mask of the entries the readings determine (uniquely: as many independent readings as unknowns)."""
    values, _ = trajectories.observed_values()
    d = trajectories.state_dim
    H = trajectories.readout.matrix.to(first)
    out, determined = first.clone(), torch.zeros_like(first, dtype=torch.bool)
    for k in range(first.shape[0]):
        unknown = ~torch.isfinite(first[k])
        row = values[k, 0, d:]  # the readings at the first time
        read = torch.isfinite(row)
        if not bool(unknown.any() and read.any()):
            continue
        A = H[read][:, unknown]  # (r, u)
        reached = (A != 0).any(0)
        if not bool(reached.any()):
            continue
        A = A[:, reached]
        rhs = row[read] - H[read][:, ~unknown] @ first[k][~unknown]
        idx = unknown.nonzero().flatten()[reached]
        out[k, idx] = torch.linalg.lstsq(A, rhs.unsqueeze(-1), driver="gelsd").solution.squeeze(-1)
        determined[k, idx] = int(torch.linalg.matrix_rank(A)) == A.shape[1]
    return out, determined


def estimate_initial_states(
    system: MisspecifiedSystem,
    rhs,
    trajectories: Trajectories,
    free: torch.Tensor,
    *,
    noise: torch.Tensor | None = None,
    iterations: int = 20,
    max_steps: int | None = None,
) -> torch.Tensor:
    """``(K, d)`` initial states whose ``free (K, d)`` entries minimise the squared misfit of the path of ``rhs``
    (``rhs(y, t, u)``, e.g. the known model G) to every observed value and reading, each weighted by ``noise``
    (``(d + m,)`` standard deviations of the states' and readings' observations; default: the noise the fit
    through the ODE assumes,
    :func:`~torchmisspec.fit_trajectories`); the other entries stay at ``trajectories.initial_conditions`` (set
    :attr:`Trajectories.initial_states` to start elsewhere). Levenberg-Marquardt per experiment (experiments are
    independent), the Jacobian by forward differences of all free components at once in one batched solve per
    step."""
    K, d = free.shape
    start = trajectories.initial_conditions
    if not bool(torch.isfinite(start).all()):  # unmeasured entries without a value: from the other experiments
        start = initial_guess(trajectories, system)
    trajectories = trajectories.with_initial_states(start)
    if not bool(free.any()):
        return trajectories.initial_conditions
    solver = dict(rtol=FITTING_TOLERANCES[0], atol=FITTING_TOLERANCES[1], max_steps=max_steps)
    residuals, _, _ = _shooting(trajectories, "single", dict(solver, what="estimate_initial_states"), system)
    kd = dict(dtype=trajectories.dtype, device=trajectories.device)
    if noise is None:
        variance = _state_noise(None, trajectories, kd)
        sizes = torch.cat([trajectories.flat_states(), trajectories.initial_conditions])
        if variance is not None:
            noise = variance.sqrt()
        else:  # each state's and reading's size
            values, mask = trajectories.observed_values()
            noise = torch.cat([observed_rms(sizes), observed_rms(values[mask])[d:]])
    sd = noise.to(**kd)  # offsets and residuals in units of each component's noise
    experiment = residuals.experiment  # (n,)
    cols = free.any(0).nonzero().flatten().tolist()
    m = len(cols)
    step = 1e-4
    off = torch.zeros(K, d, dtype=sd.dtype, device=sd.device)
    lam = torch.full((K,), 1e-3, dtype=sd.dtype, device=sd.device)

    def per_experiment_cost(r: torch.Tensor) -> torch.Tensor:  # r (n, e) weighted residuals
        return torch.zeros(K, dtype=r.dtype, device=r.device).index_add_(0, experiment, r.pow(2).sum(-1))

    with torch.no_grad():
        for _ in range(iterations):
            offs = off.expand(m + 1, K, d).clone()
            for c, j in enumerate(cols):
                offs[c + 1, :, j] += step * free[:, j].to(off)
            R = residuals.many(rhs, m + 1, offs, sd) / sd  # (m + 1, n, e): the states and any readings
            r0 = R[0]
            J = ((R[1:] - r0) / step).permute(1, 2, 0)  # (n, e, m)
            A = torch.zeros(K, m, m, dtype=r0.dtype, device=r0.device).index_add_(
                0, experiment, J.transpose(-1, -2) @ J
            )
            b = torch.zeros(K, m, dtype=r0.dtype, device=r0.device).index_add_(
                0, experiment, (J.transpose(-1, -2) @ r0.unsqueeze(-1)).squeeze(-1)
            )
            mask = free[:, cols].to(A)  # entries that are not free: identity rows, no step
            A = A * mask.unsqueeze(-1) * mask.unsqueeze(-2) + torch.diag_embed(1 - mask)
            diag = torch.diagonal(A, dim1=-2, dim2=-1)
            A = A + torch.diag_embed(lam.unsqueeze(-1) * (diag + 1e-12))
            delta = -torch.linalg.solve(A, (b * mask).unsqueeze(-1)).squeeze(-1) * mask
            trial = off.clone()
            trial[:, cols] += delta
            cost0 = per_experiment_cost(r0)
            cost1 = per_experiment_cost(residuals.many(rhs, 1, trial.unsqueeze(0), sd)[0] / sd)
            better = torch.isfinite(cost1) & (cost1 < cost0)
            off = torch.where(better.unsqueeze(-1), trial, off)
            lam = torch.where(better, lam * 0.3, lam * 10.0).clamp(1e-9, 1e9)
            gain = torch.where(better, (cost0 - cost1) / cost0.clamp_min(torch.finfo(cost0.dtype).tiny), 0.0)
            if float(gain.max()) < 1e-6 and bool(better.any()):  # every experiment has settled
                break
    y0 = trajectories.initial_conditions + off * sd[:d]
    if not bool(torch.isfinite(y0).all()):
        raise FittingError("estimate_initial_states: the estimate is not finite (the model's paths blow up)")
    return y0


def complete(system: MisspecifiedSystem, rhs, trajectories: Trajectories, initial_states: torch.Tensor) -> Trajectories:
    """``trajectories`` with every component an experiment does not measure replaced by the path of ``rhs`` from
    ``initial_states`` at its times (its few observed values too: the path is fitted to them), and
    :attr:`Trajectories.initial_states` set; measured components are unchanged."""
    times, states, mask = trajectories.padded()
    if times.dim() == 1:
        times = times.expand(states.shape[0], -1)
    with torch.no_grad():
        path, _ = _solve_rhs(
            system,
            rhs,
            initial_states,
            times,
            trajectories.controls,
            rtol=PREDICTION_TOLERANCES[0],
            atol=PREDICTION_TOLERANCES[1],
            what="complete",
        )
    unmeasured = ~trajectories.measured  # (K, d)
    out = torch.where(unmeasured.unsqueeze(1), path, states)
    return trajectories.with_states(out).with_initial_states(initial_states)


def _completed_by_first(at: MisspecifiedSystem, first, trajectories: Trajectories, y0, by_g: Trajectories):
    """The data completed with the first model (G at theta's posterior mean + F's first model) from ``y0``; where
    its paths cannot be integrated at the prediction tolerances (a term pruned in its last round can leave a model
    that blows up), with G alone at theta's posterior mean, and where that fails too, ``by_g`` (step 1's completion),
    with a warning: the model choice then sees the paths of a simpler model, and the refinement through the ODE
    fits F to the measured values as always."""
    try:
        return complete(at, _mean_field(at, first.posterior()), trajectories, y0)
    except IntegrationError as exc:
        error = exc
    try:
        completed = complete(at, lambda y, t, u: at.known_rhs(y, t, u), trajectories, y0)
        what = "the known model alone"
    except IntegrationError:
        completed, what = by_g, "the known model alone from its own initial states"
    warn(
        f"fit_correction: the first model of F cannot be integrated over the experiments ({str(error)[:160]}); the "
        f"unmeasured components are filled with the paths of {what} for the choice of F instead",
        TorchMisspecWarning,
    )
    return completed


def _completed_by_g(system: MisspecifiedSystem, trajectories: Trajectories, noise=None) -> Trajectories:
    """The data completed with G alone (step 1 of the module): the unmeasured initial values that no first row gives
    are fitted to the measurements; the given ones are kept (G is wrong: fitting them with G alone would move them to
    wherever G's error is best hidden, and the fit through the ODE that follows refines them with F)."""

    def known(y, t, u):
        return system.known_rhs(y, t, u)

    start = trajectories.with_initial_states(initial_guess(trajectories, system))
    given = torch.isfinite(trajectories.initial_conditions)
    if trajectories.readout is not None:  # entries the first readings determine are data too
        given = given | _from_readings(trajectories, trajectories.initial_conditions)[1]
    y0 = estimate_initial_states(system, known, start, ~trajectories.measured & ~given, noise=noise)
    return complete(system, known, trajectories, y0)


def _completed_by_known(system: MisspecifiedSystem, trajectories: Trajectories, known) -> Trajectories | None:
    """The data completed with the known model's own fit (its parameters and initial states, F = 0); ``None``
    without one, or when its paths cannot be integrated at the prediction tolerances."""
    if known is None:
        return None
    at = system if known.theta is None else system.at(known.theta)
    try:
        return complete(at, at.known_rhs, trajectories, known.initial_states)
    except IntegrationError:
        return None


def _refined_or_kept(chosen, system, trajectories: Trajectories, y0, progress: bool):
    """``(model, initial states)``: ``chosen`` refined through the ODE on what was measured
    (:func:`~torchmisspec.fit_trajectories`), or, when that refinement cannot be integrated (the lynx data: not even
    G alone from the estimated start), ``chosen`` and ``y0`` as they are, with a warning: a failed refinement is a
    rejected step, not the end of the fit."""
    try:
        result = fit_trajectories(chosen, system, trajectories.with_initial_states(y0), progress=progress)
    except (IntegrationError, FittingError) as exc:
        warn(
            f"fit_correction: the refinement of the chosen model through the ODE failed ({str(exc)[:160]}); kept the "
            "model chosen on the data completed by the first model, unrefined",
            TorchMisspecWarning,
        )
        return chosen, y0
    result.cross_validation_, result.samples_ = chosen.cross_validation_, chosen.samples_
    result.input_names_ = chosen.input_names_
    return result, result.initial_states_


def _corrected(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    fit,
    *,
    progress: bool,
    known,
    first: FirstModel = FIRST_MODEL,
    **options,
):
    """The correction learned through the ODE (the steps of the module docstring), starting from the known model's
    own fit ``known`` (a :class:`~torchmisspec.learning.refinement._known_fit.KnownFit`: its parameters and initial
    states, F = 0) where there is one; its first model fitted as long as ``first`` says."""
    kd = dict(dtype=trajectories.dtype, device=trajectories.device)
    noise = _state_noise(None, trajectories, kd)  # variances of the states and readings, once for every step below
    completed = _completed_by_known(system, trajectories, known)
    if completed is None:
        completed = _completed_by_g(system, trajectories, None if noise is None else noise.sqrt())
    report = identifiability(system, trajectories, completed=completed)
    report.check(system.name)
    samples = correction_samples(completed, system, derivative="central")  # only their inputs are used
    data = trajectories.with_initial_states(completed.initial_states)
    learn = system.parameters is not None
    theta_start = None if known is None else known.theta
    first = first_model(system, data, completed, samples, noise, progress, learn, theta_start, first)
    y0 = first.initial_states_
    posterior = _first_posterior(system, first, completed) if learn else None
    at = system if posterior is None else system.at(posterior.mean)  # F is chosen at theta's posterior mean
    completed = _completed_by_first(at, first, trajectories, y0, completed)
    refine = options.pop("refine", None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TorchMisspecWarning)
        result = fit(completed, at, progress=progress, refine=False, **options)
    for w in caught:  # the estimator's advice, for data whose unmeasured components are the first model's paths
        text = str(w.message).replace(
            "or fit the correction through the ODE with tms.fit_trajectories",
            "or refit with refine=True (F then matches the measured states through the ODE)",
        )
        warnings.warn_explicit(text, w.category, w.filename, w.lineno)
    if refine is None and getattr(result, "known_model_", False):  # no correction chosen (do no harm): F = 0
        refine = False
    if refine is None:  # fit_correction's rule (the feature kernel's terms are re-learned through the ODE), and any
        # model whose samples rest on the first model's paths (F on, or of, a state not measured directly)
        spec = result.kernel_spec
        refine = system.autonomous and ((spec.terms and spec.feature_space) or report.from_paths)
    if refine:  # F through the ODE on what was measured (not on the completed paths), the initial states with it
        result, y0 = _refined_or_kept(result, at, trajectories, y0, progress)
    result.initial_states_ = y0
    result.identifiability_ = report
    if posterior is not None:
        n = result.train_inputs_.shape[0]
        result.parameters_ = dataclasses.replace(
            posterior, basis_targets=posterior.basis_targets.new_zeros(n, *posterior.basis_targets.shape[1:])
        )
        result.parameters_.warn_if_unidentified("fit_correction")
    return result


def _first_posterior(system: MisspecifiedSystem, first, completed: Trajectories) -> ParameterPosterior:
    """G's uncertain parameters as the joint fit through the ODE found them (``first.parameters_laplace_``: the
    Laplace posterior with F's coefficients and the initial states marginalised). F's posterior is not conditioned
    on them (no absorption terms: draws of theta and of F are independent, which overstates the spread where F
    could make up for theta)."""
    found = first.parameters_laplace_
    if found is None:  # the fit ended before its Laplace step: nothing learned
        return ParameterPosterior.prior(system.parameters, 0, system.output_dim, completed.flat_states())
    return laplace_posterior(system, *found, completed)


def laplace_posterior(system: MisspecifiedSystem, mean, cov, fixed, completed: Trajectories, n: int = 0):
    """A :class:`ParameterPosterior` from a fit through the ODE: mean ``(k,)``, Laplace covariance ``(k, k)`` and the
    covariance with the initial states (and any coefficients of F) held fixed (its diagonal: the standard deviations
    without a correction); linear or not in theta as G is at the states of ``completed``; no F to absorb theta
    (``basis_targets`` 0 at ``n`` training inputs)."""
    priors = system.parameters
    like = completed.flat_states()
    t = None if system.autonomous else completed.flat_times().to(like)
    _, linear = parameter_basis(
        lambda th: system.at(th).known_rhs(like, t, completed.flat_controls()), mean, priors.scale.to(mean)
    )
    return ParameterPosterior(
        names=priors.names,
        prior_mean=priors.mean.to(like),
        prior_scale=priors.scale.to(like),
        mean=mean.detach().to(like),
        covariance=(0.5 * (cov + cov.T)).detach().to(like),
        sd_without_correction=fixed.diagonal().clamp_min(0).sqrt().detach().to(like),
        log_evidence=math.nan,
        basis_targets=like.new_zeros(n, system.output_dim, len(priors)),
        linear=linear,
    )
