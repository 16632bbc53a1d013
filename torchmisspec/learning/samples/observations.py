"""Samples of the missing term F from observed trajectories: derivative estimators and :func:`correction_samples`.

The correction is never observed directly. From states ``y`` observed at times ``t`` we estimate ``dy/dt`` and
form the samples ``F~ = dy/dt - G(y)`` at the observed states, restricted to the components F acts on and
paired with the components F depends on. The derivative estimators:

* ``"oracle"``: the paper's observation model, the exact ``dy/dt = G(y) + F(y)`` plus Gaussian noise (simulation
  and benchmark systems only, since it needs the true F);
* ``"central"``: :func:`finite_difference`, exact Lagrange (Fornberg) weights on local, possibly non-uniform
  stencils, second or fourth order everywhere, end points included;
* ``"smooth"``: :func:`smoothed_derivative`, a local polynomial least-squares fit (Savitzky-Golay generalised to
  non-uniform grids) for noisy states;
* ``"gp"``: :func:`gp_derivative`, the posterior mean of dy/dt under a Gaussian process in time per state
  component (hyperparameters by marginal likelihood shared across experiments); its posterior variance becomes
  the samples' per-sample noise variance;
* ``"auto"`` (the default of :func:`correction_samples`): the estimator among ``central`` / ``smooth`` / ``gp``
  (several settings) with the smallest :func:`estimator_error`, chosen by :func:`choose_derivative`; a
  :class:`~torchmisspec.TorchMisspecWarning` is issued when even the best one is unreliable
  (ratio > :data:`ESTIMATOR_ERROR_THRESHOLD`).

:func:`estimator_error` is the self-check that needs no truth: the estimator's error on trajectories of the known
model G (where dy/dt = G(y) exactly), simulated from the observed initial states on the observed grids with the
state-noise level the GP in time finds in the data, relative to the size of the correction samples.

**Missing entries** (NaN states, see :class:`~torchmisspec.Trajectories`): every estimator fits each component
from its own observed times only (the stencil of a time is the nearest observed samples of that component; the GP in
time conditions on the observed entries), and returns a derivative at every time, observed or not.
:func:`correction_samples` explains how a sample at a time with a missing component is formed.

Every function is vectorised over experiments and state components, follows the dtype and device of the states,
and raises :class:`~torchmisspec._errors.InputError` / :class:`~torchmisspec._errors.ShapeError` on bad input.

The code is split by concept into private modules: the stencil estimators in
``torchmisspec.learning.samples._stencils``, the GP in time (and the state-noise level it finds) in
``torchmisspec.learning.samples._gp_in_time``, the estimators applied to trajectories and their self-check in
``torchmisspec.learning.samples._estimators``; this module forms the samples.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from ..._errors import InputError, ShapeError, TorchMisspecWarning, warn
from ..._validation import as_tensor, check_finite, check_positive_int, check_real, check_selection
from ...data import Trajectories
from ...noise import NoiseModel
from ...parameters import jacobian, parameter_basis
from ...systems import MisspecifiedSystem
from ._edges import edge_reach, rms_rows, unreliable_edges
from ._estimators import (
    AUTO_CANDIDATES,
    ESTIMATOR_ERROR_THRESHOLD,
    _check_trajectories_and_system,
    _estimate_flat,
    _sample_rows,
    choose_derivative,
    choose_with_copy,
    estimator_error,
    known_flat,
)
from ._gp_in_time import GP_MIN_SAMPLES, GPDerivative, estimate_state_noise, gp_derivative, observed_variance
from ._noise_space import in_noise_space, transforms
from ._stencils import finite_difference, smoothed_derivative

__all__ = [  # in the order of the API page
    "DERIVATIVE_ESTIMATORS",
    "GP_MIN_SAMPLES",
    "ESTIMATOR_ERROR_THRESHOLD",
    "AUTO_CANDIDATES",
    "GPDerivative",
    "CorrectionSamples",
    "finite_difference",
    "smoothed_derivative",
    "gp_derivative",
    "estimator_error",
    "choose_derivative",
    "correction_samples",
    "estimate_state_noise",
    "observed_variance",
]

#: Names accepted by ``correction_samples(derivative=...)``.
DERIVATIVE_ESTIMATORS = ("auto", "oracle", "central", "smooth", "gp")


@dataclass(frozen=True)
class CorrectionSamples:
    """Noisy samples F~ of the correction at the observed states, flattened over experiments and times.

    Samples run experiment after experiment (sample ``n = k * T + j`` is experiment k at its j-th time when every
    experiment has T samples; ragged data concatenates its experiments likewise).

    Attributes:
        inputs: ``(N, d_in)`` the correction's inputs, ``system.select_inputs(states)``.
        targets: ``(N, d_out)`` the samples ``F~ = select_outputs(dy/dt - G(y))`` (noise included).
        states: ``(N, d)`` the full observed states.
        experiment: ``(N,)`` long tensor, the experiment index k of each sample.
        noise: known per-sample noise variances of the targets, ``(N, d_out)``, or ``None`` when unknown (the
            correction GP then learns one noise variance).
        residuals: for a system with uncertain parameters, dy/dt - G(y; prior mean) on every state component
            ``(N, d)`` (``targets`` are its corrected components); ``None`` otherwise.
        basis: for a system with uncertain parameters, G's basis g_k = dG/dtheta_k at the samples ``(N, d, k)``
            (:mod:`torchmisspec.learning.theta.closed_form`); ``None`` otherwise. For a G nonlinear in theta,
            ``residuals`` and ``basis`` are its linearisation's (:meth:`linearized`).
        times, controls: for a system with uncertain parameters, the samples' times ``(N,)`` (non-autonomous
            systems) and inputs ``(N, m)`` (systems with inputs), where G is evaluated again at another theta.
        parameters_linear: whether G is linear in its uncertain parameters.
        linearized_at: for a nonlinear G, the theta ``(k,)`` it is linearised at (``None``: the prior mean).
        derivative: how dy/dt was obtained, e.g. ``"central order=4"`` (``derivative="auto"``'s choice included).
    """

    inputs: torch.Tensor
    targets: torch.Tensor
    states: torch.Tensor
    experiment: torch.Tensor
    noise: torch.Tensor | None = None
    residuals: torch.Tensor | None = None
    basis: torch.Tensor | None = None
    times: torch.Tensor | None = None
    controls: torch.Tensor | None = None
    parameters_linear: bool = True
    linearized_at: torch.Tensor | None = None
    derivative: str | None = None

    def subset(self, rows: torch.Tensor) -> CorrectionSamples:
        """The samples at ``rows`` (a boolean mask or indices)."""
        rows = torch.tensor(check_selection(rows, self.num_samples, "rows", "samples", empty=True), dtype=torch.long)
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        shared = ("parameters_linear", "linearized_at", "derivative")  # not per sample
        return CorrectionSamples(
            **{k: v if v is None or k in shared else v[rows.to(v.device)] for k, v in fields.items()}
        )

    def thinned(self, at_most: int) -> CorrectionSamples:
        """About ``at_most`` of these samples (these themselves when there are no more): each experiment's samples
        thinned evenly, in proportion to its share, at least two per experiment (its first and last)."""
        at_most = check_positive_int(at_most, "at_most")
        n = self.inputs.shape[0]
        if n <= at_most:
            return self
        rows = []
        for k in torch.unique(self.experiment).tolist():
            idx = (self.experiment == k).nonzero().squeeze(1)
            keep = max(2, math.ceil(idx.numel() * at_most / n))
            pick = torch.linspace(0, idx.numel() - 1, keep, device=idx.device).round().long().unique()
            rows.append(idx[pick])
        return self.subset(torch.cat(rows))

    def shifted(self, delta: torch.Tensor, outputs) -> CorrectionSamples:
        """These samples with the parameters moved by ``delta`` ``(k,)`` from the prior mean: the targets
        r - H delta on the corrected components ``outputs`` (exact for a G linear in them, else to first order
        around where the samples were linearised)."""
        if self.basis is None:
            raise InputError("samples: expected samples of a system with uncertain parameters (a basis), got none")
        delta = as_tensor(delta, "delta", dtype=self.basis.dtype, device=self.basis.device)
        if delta.shape != self.basis.shape[-1:]:
            raise ShapeError(f"delta: expected shape {tuple(self.basis.shape[-1:])}, got {tuple(delta.shape)}")
        moved = self.residuals - self.basis @ delta
        return dataclasses.replace(self, targets=moved[:, list(outputs)].contiguous())

    def linearized(self, system, theta: torch.Tensor, outputs) -> CorrectionSamples:
        """These samples with a nonlinear G linearised at ``theta`` ``(k,)`` instead (Gauss-Newton's step, see
        :mod:`torchmisspec.learning.theta.closed_form`): G(y; theta') ~ G(y; theta) + J (theta' - theta), so the
        residuals at the prior mean m become r(theta) + J (theta - m) and the basis J. ``system`` is the one the samples
        were taken with (its theta the prior mean); targets are the residuals at ``theta``. Unchanged for a linear G."""
        if self.parameters_linear:
            return self
        theta = theta.to(self.residuals)
        mean = system.theta.to(theta)
        before = mean if self.linearized_at is None else self.linearized_at.to(theta)

        def known(th):
            return system.at(th).known_rhs(self.states, self.times, self.controls)

        dydt = self.residuals + known(before) + self.basis @ (mean - before)
        at = dydt - known(theta)
        basis = jacobian(known, theta, system.parameters.scale.to(theta))  # nonlinear: no check again
        residuals = at + basis @ (theta - mean)
        targets = at[:, list(outputs)].contiguous()
        return dataclasses.replace(self, residuals=residuals, basis=basis, targets=targets, linearized_at=theta)

    def __len__(self) -> int:
        return self.inputs.shape[0]

    @property
    def num_samples(self) -> int:
        return self.inputs.shape[0]

    @property
    def input_dim(self) -> int:
        return self.inputs.shape[1]

    @property
    def output_dim(self) -> int:
        return self.targets.shape[1]

    def with_shared_noise(self) -> CorrectionSamples:
        """These samples with one known noise variance per sample for every output: the largest of its outputs'
        (conservative). A design conditions one kernel shared by the outputs, so it needs the same noise for each;
        the GP in time (:func:`gp_derivative`) estimates one per output. Unchanged when the noise is unknown or
        already shared."""
        if self.noise is None or bool((self.noise == self.noise[:, :1]).all()):
            return self
        noisiest = self.noise.amax(1, keepdim=True).expand_as(self.noise).contiguous()
        return dataclasses.replace(self, noise=noisiest)


#: Fewest times of an experiment that an estimator of dy/dt can use (a central difference of order 2).
MIN_DERIVATIVE_TIMES = 3


def _without_short(trajectories: Trajectories, system: MisspecifiedSystem, short: list[int], **options):
    """The samples of the experiments with at least :data:`MIN_DERIVATIVE_TIMES` times (``short`` are the others),
    their experiment indices those of ``trajectories`` (some must have them); a warning names the experiments left
    out."""
    kept = [k for k in range(trajectories.num_experiments) if k not in short]
    lengths = sorted({trajectories.lengths[k] for k in short})
    warn(
        f"correction_samples: {len(short)} experiment(s) ({short[:10]}{' ...' if len(short) > 10 else ''}) have "
        f"fewer than {MIN_DERIVATIVE_TIMES} times ({lengths}), too few to estimate dy/dt: they give no correction "
        "samples (a fit still predicts them when it scores candidates on held-out experiments)",
        TorchMisspecWarning,
    )
    samples = correction_samples(trajectories[kept], system, **options)
    index = torch.tensor(kept, device=samples.experiment.device)
    return dataclasses.replace(samples, experiment=index[samples.experiment])


#: How the derivative estimator's self-check warning begins (:func:`~torchmisspec.fit_correction` gives it only
#: where the held-out data do not show the correction predicting significantly better than the known model).
ESTIMATOR_ADVICE = "correction_samples: the best derivative estimator"


def correction_samples(
    trajectories: Trajectories,
    system: MisspecifiedSystem,
    *,
    derivative: str = "auto",
    noise_std: float = 0.0,
    generator: torch.Generator | None = None,
    order: int = 2,
    window: int = 7,
    degree: int = 2,
    noise=None,
) -> CorrectionSamples:
    """Samples F~ = dy/dt - G(y) of the missing term at every observed state.

    **Missing entries** (NaN in ``trajectories``): each component's derivative comes from its own observed times
    (see the estimators). A sample at time t_i is formed only when every output component F acts on
    (``system.correction_outputs``) was observed at t_i; a missing input or other component of that state, which
    G(y) and the sample's inputs need, is replaced by the estimator's own fit at t_i (the interpolant for
    ``central``, the local polynomial for ``smooth``, the posterior mean for ``gp``; for ``oracle``,
    :meth:`Trajectories.filled`). Why: a target at a time where its output was not observed would be an interpolation
    of its neighbours' derivative estimates, no new information but counted as if it were (and a poor one for a
    rarely measured component); since one sample carries all outputs at one input, a time missing any output gives
    no sample, and the other outputs' targets lost there are covered by their neighbours'. A filled input or G
    argument has the accuracy of the estimator's fit, the same order as its derivative's, so these samples are kept
    rather than lose every time at which some other component was not measured.

    Args:
        trajectories: the observations, ``states (K, T, d)`` or ragged (experiments of different lengths); NaN
            entries are missing.
        system: the misspecified system; its ``state_dim`` must equal d.
        derivative: how dy/dt is obtained:

            * ``"auto"`` (default): the estimator :func:`choose_derivative` picks by the self-check
              :func:`estimator_error` (``order`` / ``window`` / ``degree`` are then ignored). When the chosen
              estimator's ratio exceeds :data:`ESTIMATOR_ERROR_THRESHOLD` (0.5: the estimator's own error is more
              than half the size of the samples, so the learned correction would be dominated by it) a
              :class:`~torchmisspec.TorchMisspecWarning` is issued. Explicit estimators are not self-checked
              (call :func:`estimator_error` yourself);
            * ``"oracle"``: the paper's observation model, the exact ``G(y) + F(y)`` (``system.true_rhs``) plus
              noise; only for systems with a true correction (simulations, benchmarks);
            * ``"central"``: :func:`finite_difference` with ``order``;
            * ``"smooth"``: :func:`smoothed_derivative` with ``window`` and ``degree``;
            * ``"gp"``: :func:`gp_derivative`; its posterior variance of dy/dt on the output components becomes
              ``CorrectionSamples.noise`` (the error of G(y) caused by state noise is ignored).
        noise_std: standard deviation of i.i.d. Gaussian noise added to every target entry (for ``"oracle"`` this
            is the observation noise of the paper's model; for the estimators it is extra noise added on top of
            the estimator's own error, e.g. to mimic noisy derivative observations; with ``"gp"`` its variance is
            added to ``noise``). Must be a finite number >= 0; with 0 no random numbers are drawn.
        generator: optional ``torch.Generator`` for the noise (on the states' device), for reproducibility.
        order: finite-difference order for ``"central"`` (2 or 4).
        window: samples per local fit for ``"smooth"``.
        degree: polynomial degree of the local fits for ``"smooth"``.
        noise: the measurement noise's model (:mod:`torchmisspec.noise`; ``None``, the default, or
            :class:`~torchmisspec.noise.Additive`: the states as measured). Any other model's estimators (and the
            self-check of ``"auto"``) run in its space, where the errors are alike (``log y`` for
            :class:`~torchmisspec.noise.Relative`), and dy/dt and its variance come back by the chain rule; rows it
            cannot hold (a 0 under relative errors) give no sample (:mod:`~torchmisspec.learning.samples._noise_space`).
            :func:`~torchmisspec.fit_correction` passes its own.

    Returns:
        :class:`CorrectionSamples` with one sample per observed state (``N = K * T``, or the sum of the lengths;
        fewer with missing outputs), in the dtype and on the device of the states; its ``states`` are the observed
        states with missing entries filled as above.

    Raises:
        InputError: ``trajectories`` / ``system`` of the wrong type, an unknown ``derivative``, a bad
            ``noise_std``, ``"oracle"`` for a system without a true correction, too few samples for the
            estimator, or non-finite samples (e.g. a state sitting on a singularity of G or F).
        ShapeError: the trajectories' state dimension differs from the system's.
    """
    extra = _checked_options(trajectories, system, derivative, noise_std, generator)  # noise_std as a float
    if noise is not None and not isinstance(noise, NoiseModel):
        raise InputError(
            f"noise: expected a torchmisspec.noise.NoiseModel (the space where the measurement errors are alike) or "
            f"None, got {type(noise).__name__}; pass e.g. torchmisspec.noise.Relative()"
        )
    short = [k for k, n in enumerate(trajectories.lengths) if n < MIN_DERIVATIVE_TIMES]
    if short and len(short) < trajectories.num_experiments and derivative != "oracle":  # too short to give samples
        options = dict(derivative=derivative, noise_std=noise_std, generator=generator, order=order, window=window)
        return _without_short(trajectories, system, short, degree=degree, noise=noise, **options)
    if derivative != "oracle" and transforms(noise):  # estimated where the errors are alike (_noise_space)
        options = dict(order=order, window=window, degree=degree, checked=True)
        dydt, variance, flat_states, used, edges = in_noise_space(
            trajectories, system, noise, lambda tr, sy: _derivatives(tr, sy, derivative, **options)
        )
    else:
        dydt, variance, flat_states, used, edges = _derivatives(trajectories, system, derivative, order, window, degree)
    lengths = torch.tensor(trajectories.lengths, device=flat_states.device)
    experiment = torch.arange(trajectories.num_experiments, device=flat_states.device).repeat_interleave(lengths)
    g = known_flat(system, trajectories, flat_states)
    u = trajectories.flat_controls()
    keep = _complete_rows(trajectories, system)
    if keep is not None:
        dydt, flat_states, experiment, g, variance, u, edges = (
            None if a is None else a[keep] for a in (dydt, flat_states, experiment, g, variance, u, edges)
        )
    residuals, basis, t, linear = _theta_parts(system, trajectories, flat_states, dydt, g, u, keep)
    targets = system.select_outputs(dydt - g)
    check_finite(targets, f"correction samples dy/dt - G(y) of system '{system.name}'")
    sample_noise = None if variance is None else system.select_outputs(variance)
    if extra > 0:
        targets, sample_noise = _with_noise(targets, sample_noise, extra, noise_std, generator)
    samples = CorrectionSamples(
        inputs=system.select_inputs(flat_states, u),
        targets=targets,
        states=flat_states,
        experiment=experiment,
        noise=sample_noise,
        residuals=residuals,
        basis=basis,
        times=t,
        controls=None if system.parameters is None else u,
        parameters_linear=linear,
        derivative=used,
    )
    return samples if edges is None or not bool(edges.any()) else samples.subset(~edges)


def _checked_options(trajectories, system, derivative, noise_std, generator) -> float:
    """``noise_std`` as a float, after refusing bad trajectories or system, an unknown ``derivative``, a bad
    ``noise_std`` and a ``generator`` that is not one."""
    _check_trajectories_and_system(trajectories, system)
    if not isinstance(derivative, str) or derivative not in DERIVATIVE_ESTIMATORS:
        raise InputError(f"derivative: expected one of {list(DERIVATIVE_ESTIMATORS)}, got {derivative!r}")
    noise = check_real(noise_std, "noise_std", minimum=0.0)
    if generator is not None and not isinstance(generator, torch.Generator):
        raise InputError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    return noise


def _derivatives(
    trajectories: Trajectories, system: MisspecifiedSystem, derivative: str, order, window, degree, checked=False
):
    """``(dy/dt (N, d), its variance (N, d) or None, the states (N, d) filled by the estimator, the estimator's
    name and options)`` for :func:`correction_samples`' ``derivative``. With ``checked``, a stencil chosen by
    ``"auto"`` gives as every sample's variance the mean square of its error on the self-check's copy (in a noise
    model's space, where that error is alike for every sample: :mod:`~torchmisspec.learning.samples._noise_space`)."""
    edges, note, error = None, "", None
    if derivative == "oracle":
        dydt, flat_states = _oracle(trajectories, system)
        return dydt, None, flat_states, "oracle", None
    if derivative == "auto":
        name, options, edges, note, error = _auto_estimator(trajectories, system)
    elif derivative == "central":
        name, options = "central", {"order": order}
    elif derivative == "smooth":
        name, options = "smooth", {"window": window, "degree": degree}
    else:
        name, options = "gp", {}
    dydt, variance, flat_states = _estimate_flat(name, trajectories, options)
    if derivative in ("central", "smooth"):  # explicit stencils and local fits: no sample noise (auto: its choice's)
        variance = None
    elif variance is None and checked and error is not None:
        variance = torch.ones_like(dydt)
        variance[:, list(system.correction_outputs)] = error.to(dydt)
    used = " ".join([name, *(f"{k}={v}" for k, v in sorted(options.items()))])
    return dydt, variance, flat_states, used + note, edges


def _oracle(trajectories: Trajectories, system: MisspecifiedSystem):
    """``(dy/dt, states)``: the exact ``G(y) + F(y)`` at the states (missing entries filled), for a system with a true
    correction."""
    if not system.has_correction:
        raise InputError(
            f"derivative='oracle': oracle derivatives need a system with a true correction F, and system "
            f"'{system.name}' has none; use 'auto', 'central', 'smooth' or 'gp' for real data"
        )
    flat_states = trajectories.filled().flat_states()
    check_finite(flat_states, "trajectories.states")
    with torch.no_grad():  # data, not a graph: a G that is an nn.Module with parameters must not leak into them
        if system.autonomous:
            return system.true_rhs(flat_states), flat_states
        flat_t = trajectories.flat_times().to(flat_states)
        return system.true_rhs(flat_states, flat_t, trajectories.flat_controls()), flat_states


def _auto_estimator(trajectories: Trajectories, system: MisspecifiedSystem):
    """``(name, options, left out (N,) or None, a note, the mean square of its error on the self-check's copy (o,)
    or None)``: the estimator :func:`choose_derivative` picks, with the
    warning (:data:`ESTIMATOR_ADVICE`) when its self-checked error exceeds :data:`ESTIMATOR_ERROR_THRESHOLD` of the
    samples' size, and the edge samples it cannot be trusted at (:mod:`~torchmisspec.learning.samples._edges`)."""
    name, options, errors, copy = choose_with_copy(trajectories, system)
    edges, note, kept, error = _edges(name, options, trajectories, copy, system)
    ratio = errors[(name, tuple(sorted(options.items())))] if kept is None else kept
    if ratio > ESTIMATOR_ERROR_THRESHOLD:  # NaN: not ranked (choose_derivative said why)
        warn(
            f"{ESTIMATOR_ADVICE} ({name} {options}) has an error on the known "
            f"model of {ratio:.3g} times the size of the correction samples (threshold "
            f"{ESTIMATOR_ERROR_THRESHOLD}): the learned correction would mostly fit estimator error. Fixes: "
            "sample the states more densely in time, try another estimator (estimator_error tells which is "
            "best), or fit the correction through the ODE with tms.fit_trajectories",
            TorchMisspecWarning,
        )
    return name, options, edges, note, error


def _edges(name, options, trajectories, copy, system):
    """``(left out (N,) or None, a note for the samples' description, the self-check's ratio on the samples kept,
    the mean square of the estimator's error on the copy's rows kept (o,) or None)``: the edge samples whose estimator
    error on the known model's ``copy`` is mostly error
    (:func:`~torchmisspec.learning.samples._edges.unreliable_edges`)."""
    if copy is None or copy[1] is None:
        return None, "", None, None
    copy, (errors, targets) = copy
    if trajectories.has_missing:
        targets = torch.where(_sample_rows(trajectories, system).unsqueeze(-1), targets, math.nan)
    if copy[0].has_missing:
        errors = torch.where(_sample_rows(copy[0], system).unsqueeze(-1), errors, math.nan)
    reach = edge_reach(name, options)
    out, out_copy, worst = unreliable_edges(errors, targets, copy[0].lengths, trajectories.lengths, reach)
    seen = errors[~out_copy]
    seen = seen[torch.isfinite(seen).all(-1)]
    error = seen.pow(2).mean(0) if seen.shape[0] else None
    if not bool(out.any()):
        return None, "", None, error
    n = int(out.sum())
    note = (
        f"; {n} edge sample{'s' * (n > 1)} left out (the estimator's error there on the known model's copy up to "
        f"{worst:.3g} times the samples' RMS)"
    )
    return out, note, rms_rows(errors[~out_copy]) / rms_rows(targets[~out]), error


def _complete_rows(trajectories: Trajectories, system: MisspecifiedSystem) -> torch.Tensor | None:
    """``(N,)`` the times at which every output component of the correction was observed (``None`` without missing
    entries: every time), after refusing data with no such time."""
    if not trajectories.has_missing:
        return None
    keep = _sample_rows(trajectories, system)
    if not bool(keep.any()):
        raise InputError(
            f"trajectories: expected some time at which every output component {list(system.correction_outputs)} "
            "of the correction is observed (a sample needs them all), got none"
        )
    return keep


def _theta_parts(system, trajectories, flat_states, dydt, g, u, keep):
    """``(residuals, basis, times, linear)``: with uncertain parameters, the residuals dy/dt - G(y) of every component
    (theta's information), G's basis in theta at the samples (and whether G is linear in theta) and the samples'
    times (non-autonomous systems); ``(None, None, None, True)`` without."""
    if system.parameters is None:
        return None, None, None, True
    t = None if system.autonomous else trajectories.flat_times().to(flat_states)
    if keep is not None and t is not None:
        t = t[keep]
    basis, linear = parameter_basis(
        lambda theta: system.at(theta).known_rhs(flat_states, t, u),
        system.theta.to(flat_states),
        system.parameters.scale.to(flat_states),
    )
    return dydt - g, basis.detach(), t, linear


def _with_noise(targets, sample_noise, noise: float, noise_std, generator):
    """``(targets, their noise)`` with i.i.d. Gaussian noise of standard deviation ``noise`` added to the targets and
    its variance to the samples' own noise (where they have one)."""
    eps = torch.randn(targets.shape, generator=generator, dtype=targets.dtype, device=targets.device)
    targets = targets + noise * eps
    check_finite(targets, f"correction samples with noise_std={noise_std!r} added")
    if sample_noise is not None:
        if not math.isfinite(noise * noise):  # its variance is added to the samples' own (noise**2 overflowed)
            raise InputError(f"noise_std: expected a standard deviation whose square is finite, got {noise_std!r}")
        sample_noise = sample_noise + noise * noise
    return targets, sample_noise
