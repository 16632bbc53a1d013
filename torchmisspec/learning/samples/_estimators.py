"""The derivative estimators applied to :class:`~torchmisspec.Trajectories` (ragged data and missing entries
included), and the self-check that ranks them without the truth (:func:`estimator_error`, :func:`choose_derivative`,
what ``correction_samples(derivative="auto")`` uses). See :mod:`torchmisspec.learning.samples.observations`."""

from __future__ import annotations

import math

import torch

from ..._errors import InputError, IntegrationError, ShapeError, TorchMisspecWarning, warn
from ..._validation import check_positive_int
from ...data import Trajectories, simulate, simulate_known_each
from ...data._input import check_named_as
from ...parallel import adaptive_threads
from ...systems import MisspecifiedSystem
from ._gp_in_time import GP_MIN_SAMPLES, _gp_time, gp_derivative
from ._stencils import _check_stencil_options, _masked, finite_difference, smoothed_derivative


def _check_trajectories_and_system(trajectories, system) -> None:
    """Trajectories that fit ``system``: their shapes, their controls (:meth:`MisspecifiedSystem.check_controls`,
    by name too) and, when both name the states, the same names in the same order (states in another order would
    be read as the wrong ones). Every function taking trajectories and a system checks them here (fit_correction,
    calibrate_bands, fit_trajectories, cross_validate, correction_samples, estimator_error, Campaign.tell)."""
    if not isinstance(trajectories, Trajectories):
        raise InputError(
            f"trajectories: expected a torchmisspec Trajectories object, got {type(trajectories).__name__}; "
            "wrap arrays with Trajectories(times, states)"
        )
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
    if trajectories.state_dim != system.state_dim:
        names = trajectories.state_names
        raise ShapeError(
            f"trajectories: expected state dimension {system.state_dim} of system '{system.name}', got "
            f"trajectories.state_dim={trajectories.state_dim} (state columns {list(names)}; "
            f"{_describe_states(trajectories)}); load every state component the system has "
            "(Trajectories.load(..., state_columns=[...]) with one column per component, in the system's order)"
            + (
                f"; the system also takes {system.num_controls} input(s) {list(system.control_names)}: name their "
                "columns (Trajectories.load(..., control_columns=[...]), --input-columns on the command line)"
                if system.num_controls and trajectories.controls is None
                else ""
            )
        )
    check_named_as(trajectories.state_names, system.state_names, f"system '{system.name}'")
    system.check_controls(trajectories.controls, trajectories.num_experiments, "trajectories.controls")


def _describe_states(trajectories: Trajectories) -> str:
    """The states' shape in words, ragged data included."""
    if trajectories.is_ragged:
        return (
            f"{trajectories.num_experiments} experiments of {min(trajectories.lengths)}..{max(trajectories.lengths)} "
            f"times x {trajectories.state_dim} components"
        )
    return f"states {tuple(trajectories.states.shape)}"


def _estimate(name: str, states: torch.Tensor, times: torch.Tensor, options: dict):
    """``(dy/dt, variance or None)`` of the estimator ``name`` (``central`` / ``smooth`` / ``gp``)."""
    if name == "central":
        return finite_difference(states, times, order=options.get("order", 2)), None
    if name == "smooth":
        return smoothed_derivative(
            states, times, window=options.get("window", 7), degree=options.get("degree", 2)
        ), None
    if name == "gp":
        out = gp_derivative(states, times, max_iter=options.get("max_iter", 50))
        return out.mean, out.variance
    raise InputError(f"derivative: expected one of {list(_SELF_CHECKED)}, got {name!r}")


def _estimate_flat(name: str, trajectories: Trajectories, options: dict):
    """``(dy/dt (N, d), variance (N, d) or None, states (N, d))`` at every sample, experiment after experiment (ragged
    data too); ``states`` are the observed states with every missing entry replaced by the estimator's own fit at
    that time (the interpolant for ``central``, the local polynomial for ``smooth``, the posterior mean for ``gp``).

    Stencil estimators run once per group of equal-length experiments; the GP in time runs on the padded batch,
    so its hyperparameters stay shared by all experiments. With missing entries every estimator runs on the padded
    batch with the mask of the observed entries."""
    d = trajectories.state_dim
    cut = _cut_at_jumps(trajectories)
    if cut is not None:  # piecewise-constant controls: dy/dt jumps with them, so no stencil may straddle a jump
        segments, rows = cut
        dydt, var, states = _estimate_flat(name, segments, options)
        return dydt[rows], None if var is None else var[rows], states[rows]
    if name == "gp" and (trajectories.is_ragged or trajectories.has_missing):
        return _gp_flat(trajectories, options.get("max_iter", 50))[1]
    if trajectories.has_missing:
        if name not in _SELF_CHECKED:
            raise InputError(f"derivative: expected one of {list(_SELF_CHECKED)}, got {name!r}")
        times, states, rows = trajectories.padded()
        observed = torch.isfinite(states) & rows.unsqueeze(-1)
        _check_stencil_options(name, options, min(trajectories.lengths))
        dydt, fit = _masked(name, states, times, observed, options)
        filled = torch.where(observed, states, fit)
        return dydt[rows], None, filled[rows]
    flat = trajectories.flat_states()
    if not trajectories.is_ragged:
        dydt, var = _estimate(name, trajectories.states, trajectories.times, options)
        return dydt.reshape(-1, d), None if var is None else var.reshape(-1, d), flat
    per_experiment: list = [None] * trajectories.num_experiments
    for idx, group in trajectories.by_length():
        try:
            dydt, _ = _estimate(name, group.states, group.times, options)
        except InputError as exc:
            raise InputError(f"{exc} (experiment{'s' * (len(idx) > 1)} {idx[:5]} of the ragged data)") from None
        for i, k in enumerate(idx):
            per_experiment[k] = dydt[i]
    return torch.cat(per_experiment), None, flat


_SELF_CHECKED = ("central", "smooth", "gp")
_OPTION_NAMES = {"central": ("order",), "smooth": ("window", "degree"), "gp": ("max_iter",)}

#: ``estimator_error`` ratio above which ``correction_samples(derivative="auto")`` warns. At 0.5 the estimator's
#: own error is half the RMS of the samples the correction GP is asked to learn. On the pendulum of issue 9
#: (T = 21, friction as F), central differences of order 2 score 0.8 and gave corrected/misspecified RMSE 0.69
#: (a correction barely worth having), while order 4 and the GP in time score 0.06-0.23 (RMSE 0.08); at T = 11
#: every estimator scores above 0.8. The threshold sits between the two groups.
ESTIMATOR_ERROR_THRESHOLD = 0.5

#: Candidates of ``derivative="auto"``, in order of preference on ties: ``(name, options, samples needed)``.
AUTO_CANDIDATES: tuple[tuple[str, dict, int], ...] = (
    ("central", {"order": 4}, 5),
    ("gp", {}, GP_MIN_SAMPLES),
    ("central", {"order": 2}, 3),
    ("smooth", {"window": 5, "degree": 2}, 5),
    ("smooth", {"window": 7, "degree": 2}, 7),
    ("smooth", {"window": 9, "degree": 3}, 9),
    ("smooth", {"window": 11, "degree": 3}, 11),
)


def _check_options(name: str, options: dict) -> dict:
    if name not in _SELF_CHECKED:
        raise InputError(f"derivative: expected one of {list(_SELF_CHECKED)}, got {name!r}")
    unknown = sorted(set(options) - set(_OPTION_NAMES[name]))
    if unknown:
        raise InputError(
            f"options: derivative={name!r} accepts {list(_OPTION_NAMES[name])}, got unknown option(s) {unknown}"
        )
    return dict(options)


def _with_flat_states(trajectories: Trajectories, flat: torch.Tensor) -> Trajectories:
    """``trajectories`` with its states replaced by ``flat (N, d)`` (same experiments, times, lengths, controls)."""
    controls = trajectories.controls
    if not trajectories.is_ragged:
        return Trajectories(trajectories.times, flat.reshape(trajectories.states.shape), controls=controls)
    return Trajectories(list(trajectories.times), list(flat.split(list(trajectories.lengths))), controls=controls)


#: a segment between two jumps of the controls is estimated on its own only with at least this many samples
_MIN_SEGMENT = 4


def _cut_at_jumps(trajectories: Trajectories):
    """Every experiment cut where its piecewise-constant controls jump (the states' derivative jumps there), as
    ragged segments without controls, and for every sample the row of the segments' flat arrays its derivative is
    read from; ``None`` when there is nothing to cut (no such controls, or missing entries: then the experiments are
    estimated whole). A sample at a jump ends one segment and starts the next; it takes the next one's (right)
    derivative, as the hold is right-continuous. A cut that would leave a segment shorter than :data:`_MIN_SEGMENT`
    samples is not made (those few samples keep the straddling stencils' error)."""
    controls = trajectories.controls
    if controls is None or controls.jumps is None or trajectories.has_missing:
        return None
    times, states, rows = [], [], []
    offset = 0
    cut_any = False
    changes = controls.changes()
    for k, ((t, y), (knots, _)) in enumerate(zip(trajectories.experiments(), controls.profiles(), strict=True)):
        jumps = knots[1:][changes[k, : knots.numel() - 1]]  # a repeated value (a lab's table: every row) is no jump
        inner = jumps[(jumps > t[0]) & (jumps < t[-1])].to(t)
        starts, at_jump = [0], set()
        for s in inner:
            i = int(torch.searchsorted(t, s))  # the first sample at or after the jump
            end = i + 1 if bool(t[i] == s) else i  # a sample at the jump ends the previous segment too
            if end - starts[-1] >= _MIN_SEGMENT and len(t) - i >= _MIN_SEGMENT:
                starts.append(i)
                if bool(t[i] == s):
                    at_jump.add(i)
        bounds = starts + [len(t)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            stop = b + 1 if b in at_jump else b
            times.append(t[a:stop])
            states.append(y[a:stop])
            rows += list(range(offset, offset + (b - a)))
            offset += stop - a
        cut_any = cut_any or len(bounds) > 2
    if not cut_any:
        return None
    segments = Trajectories(times, states)
    return segments, torch.tensor(rows, device=trajectories.device)


def known_flat(system: MisspecifiedSystem, trajectories: Trajectories, flat: torch.Tensor) -> torch.Tensor:
    """G at ``flat (N, d)``, the states of ``trajectories`` experiment after experiment, at their own times and
    controls (``G(y)`` for an autonomous system). Values, not a graph: a G with trainable parameters (an
    ``nn.Module``) leaves no autograd history in the samples built from them."""
    with torch.no_grad():
        if system.autonomous:
            return system.known_rhs(flat)
        return system.known_rhs(flat, trajectories.flat_times().to(flat), trajectories.flat_controls())


def _flat_observed(trajectories: Trajectories) -> torch.Tensor:
    """``(N, d)``: the observed-entry mask, experiment after experiment."""
    observed = trajectories.observed
    return torch.cat(observed) if trajectories.is_ragged else observed.reshape(-1, trajectories.state_dim)


def _known_model_copy(trajectories: Trajectories, system: MisspecifiedSystem):
    """The self-check data ``(noisy copy, noise-free flat states (N, d), the GP in time's (dy/dt, variance, filled
    states) on the real data, or None)``: G alone from the observed initial states on the observed grids, plus state
    noise of the level the GP in time finds in the real data (a fixed seed, so the check is deterministic), with the
    real data's missing entries missing too (the estimators are checked on the data's own gaps)."""
    # Tolerances 100x looser than the package's ground-truth simulations (2.5x faster): the copy's solver error
    # (~1e-8 relative) is far below any derivative estimator's error that the check has to rank.
    times = list(trajectories.times) if trajectories.is_ragged else trajectories.times
    kept = trajectories
    try:
        sim = simulate(
            system,
            trajectories.initial_conditions,
            times,
            known_only=True,
            controls=trajectories.controls,
            rtol=1e-8,
            atol=1e-10,
        )
    except IntegrationError:
        sim, kept = _known_model_where_it_integrates(trajectories, system)
    clean = sim.flat_states()
    states, real_gp = clean, None
    if min(trajectories.lengths) >= GP_MIN_SAMPLES:
        try:
            out, real_gp = _gp_flat(trajectories, 50)
            noise = out.noise
        except InputError:
            real_gp = None  # e.g. a constant component or too few observations: the check measures the bias only
        if real_gp is not None:
            gen = torch.Generator(device=states.device).manual_seed(0)
            eps = torch.randn(states.shape, generator=gen, dtype=states.dtype, device=states.device)
            states = states + noise.sqrt() * eps
    if kept.has_missing:
        states = torch.where(_flat_observed(kept), states, torch.full_like(states, math.nan))
    return _with_flat_states(sim, states), clean, real_gp


def _gp_flat(trajectories: Trajectories, max_iter: int):
    """The GP in time on the padded batch: ``(GPDerivative (padded), (dy/dt (N, d), variance (N, d), states (N, d)))``
    as :func:`_estimate_flat` returns them."""
    max_iter = check_positive_int(max_iter, "max_iter")
    times, states, rows = trajectories.padded()
    if trajectories.has_missing:
        observed = torch.isfinite(states) & rows.unsqueeze(-1)
        out, fit = _gp_time(states, times, observed, max_iter, values=True)
        filled = torch.where(observed, states, fit)[rows]
    else:
        out = _gp_time(states, times, rows if trajectories.is_ragged else None, max_iter)
        filled = trajectories.flat_states()
    return out, (out.mean[rows], out.variance[rows], filled)


def _known_model_where_it_integrates(trajectories: Trajectories, system: MisspecifiedSystem):
    """G alone from each observed initial state, keeping the experiments over which it can be integrated (the known
    model may diverge where the true system does not: what the correction exists to fix). Warns which were left out;
    raises if none is left. Returns the simulated copy and the kept experiments' observations."""
    each = simulate_known_each(system, trajectories, rtol=1e-8, atol=1e-10)
    kept = [k for k, states in enumerate(each) if states is not None]
    if not kept:
        raise IntegrationError(
            "derivative='auto': the self-check integrates the known model alone from every observed initial state, "
            f"and it diverges from all {trajectories.num_experiments} of them; choose an estimator yourself, e.g. "
            "derivative='central' or derivative='gp'"
        )
    warn(
        f"derivative='auto': the known model alone cannot be integrated from the initial states of experiments "
        f"{[k for k, states in enumerate(each) if states is None]}; the self-check ranks the estimators on the "
        f"other {len(kept)}",
        TorchMisspecWarning,
    )
    times = [t for k, (t, _) in enumerate(trajectories.experiments()) if k in kept]
    controls = None if trajectories.controls is None else trajectories.controls[kept]
    return Trajectories(times, [each[k] for k in kept], controls=controls), trajectories[kept]


def _sample_rows(trajectories: Trajectories, system: MisspecifiedSystem) -> torch.Tensor:
    """``(N,)``: the rows that give a correction sample, those at which every output component is observed."""
    return system.select_outputs(_flat_observed(trajectories)).all(-1)


def copy_errors(name, options, trajectories, known_copy, system) -> tuple[torch.Tensor, torch.Tensor]:
    """``(errors (N_copy, o), targets (N, o))``: the estimator's error in dy/dt on the correction's outputs at every
    row of the known model's copy, and the samples ``F~`` it gives at every row of the real data (rows that give no
    sample included: :func:`_sample_rows` tells which do)."""
    if name == "gp" and not options and known_copy[2] is not None:
        dydt, _, flat = known_copy[2]  # already computed for the noise level
    else:
        dydt, _, flat = _estimate_flat(name, trajectories, options)
    targets = system.select_outputs(dydt - known_flat(system, trajectories, flat))
    copy = known_copy[0]
    est, _, _ = _estimate_flat(name, copy, options)
    errors = system.select_outputs(est - known_flat(system, copy, known_copy[1]))  # dy/dt = G on the noise-free copy
    return errors, targets


def _ratio(name, options, trajectories, known_copy, system) -> float:
    return _ratio_of(*copy_errors(name, options, trajectories, known_copy, system), trajectories, known_copy, system)


def _ratio_of(errors, targets, trajectories, known_copy, system) -> float:
    """The self-check's ratio of :func:`copy_errors`' ``errors`` and ``targets``."""
    if trajectories.has_missing:
        targets = targets[_sample_rows(trajectories, system)]
    if known_copy[0].has_missing:
        errors = errors[_sample_rows(known_copy[0], system)]
    spread = float(targets.pow(2).mean().sqrt())
    err = float(errors.pow(2).mean().sqrt())
    if not math.isfinite(err) or not math.isfinite(spread):
        return float("inf")
    if spread == 0.0:
        return 0.0 if err == 0.0 else float("inf")
    return err / spread


@adaptive_threads()
def estimator_error(trajectories: Trajectories, system: MisspecifiedSystem, *, derivative: str, **options) -> float:
    """Self-check of a derivative estimator that needs no truth: its error on the known model relative to the data.

    The known model G alone is integrated from every observed initial state on the observed time grids
    (:func:`~torchmisspec.data.simulate` with ``known_only=True``); on these trajectories ``dy/dt = G(y)`` exactly.
    State noise of the level the GP in time (:func:`gp_derivative`) estimates on the real data is added to them
    (fixed seed: the check is deterministic), so the check measures the estimator's bias *and* its noise
    amplification. The estimator is applied to them, and the RMS of its error in ``dy/dt`` on the correction's
    output components is divided by the RMS of the correction samples ``F~`` the same estimator gives on the real
    data. A ratio of 0.1 means the estimator's own error is a tenth of the size of what the correction GP is asked
    to learn; a ratio near or above 1 means the samples are mostly estimator error.

    Args:
        trajectories: the observations.
        system: the misspecified system.
        derivative: ``"central"``, ``"smooth"`` or ``"gp"``.
        **options: the estimator's options (``order``; ``window``, ``degree``; ``max_iter``).

    Returns:
        The ratio (``inf`` when the estimate is not finite).

    Raises:
        InputError: bad arguments, unknown options, or too few samples for the estimator.
        IntegrationError: the known model cannot be integrated from any observed initial state (experiments from
            which it diverges are left out of the check, with a warning).
    """
    _check_trajectories_and_system(trajectories, system)
    options = _check_options(derivative, options)
    if derivative != "gp":  # cheap: bad options or too few samples fail before the simulation
        _estimate_flat(derivative, trajectories, options)
    return _ratio(derivative, options, trajectories, _known_model_copy(trajectories, system), system)


@adaptive_threads()
def choose_derivative(
    trajectories: Trajectories, system: MisspecifiedSystem
) -> tuple[str, dict, dict[tuple[str, tuple], float]]:
    """The estimator ``derivative="auto"`` uses: the candidate with the smallest :func:`estimator_error`.

    Candidates (:data:`AUTO_CANDIDATES`): ``central`` order 4 and 2, ``gp``, and ``smooth`` with windows 5, 7
    (degree 2) and 9, 11 (degree 3); those needing more samples than the trajectories have are skipped. The
    known-model copy of the data is simulated once and shared by all candidates.

    Returns:
        ``(name, options, errors)``: the chosen estimator, its options (pass them on as
        ``correction_samples(..., derivative=name, **options)``), and every candidate's ratio keyed by
        ``(name, tuple(sorted(options.items())))``.

    When the known model cannot be integrated from any observed initial state (nothing to check the estimators on),
    the first candidate that fits the data is returned unranked (its error NaN), with a warning.

    Raises:
        InputError: no candidate fits the number of samples (T < 3), or bad arguments.
    """
    name, options, errors, _ = choose_with_copy(trajectories, system)
    return name, options, errors


def choose_with_copy(trajectories: Trajectories, system: MisspecifiedSystem):
    """:func:`choose_derivative`'s ``(name, options, errors)`` and ``(the known model's copy of the data it checked
    them on, the chosen estimator's (errors on it, samples) from :func:`copy_errors`)`` (``None`` where the copy
    could not be simulated): the edge check reads them without running the estimator again."""
    _check_trajectories_and_system(trajectories, system)
    T = min(trajectories.lengths)
    candidates = [(n, o) for n, o, need in AUTO_CANDIDATES if T >= need]
    if not candidates:
        raise InputError(
            f"derivative='auto': expected at least 3 samples per trajectory, got T={T}"
            + (" (the shortest experiment)" if trajectories.is_ragged else "")
        )
    try:
        known_copy = _known_model_copy(trajectories, system)
    except IntegrationError as exc:  # nothing to check the estimators on: the first that fits, unranked
        name, options = candidates[0]
        warn(
            f"{str(exc).split(';')[0]}: no estimator could be ranked, so {name} {options} (the first that fits the "
            "data) is used unchecked; the known model blows up over the data, so check G and its parameters",
            TorchMisspecWarning,
        )
        return name, dict(options), {(name, tuple(sorted(options.items()))): math.nan}, None
    errors: dict[tuple[str, tuple], float] = {}
    parts: dict[tuple[str, tuple], tuple] = {}  # each candidate's copy errors and samples, kept for the edge check
    for name, options in candidates:
        key = (name, tuple(sorted(options.items())))
        try:
            parts[key] = copy_errors(name, options, trajectories, known_copy, system)
            errors[key] = _ratio_of(*parts[key], trajectories, known_copy, system)
        except InputError:
            errors[key] = float("inf")
    key = min(errors, key=errors.get)
    return key[0], dict(key[1]), errors, (known_copy, parts.get(key))
