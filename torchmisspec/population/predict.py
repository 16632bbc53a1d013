"""A new subject's trajectory: from the population alone, or updated by its first measurements.

The subject's varying parameters are drawn from

* the population (no measurement yet): eta ~ N(typical(covariates), diag(omega'^2)): bands that hold the spread
  between subjects, omega' the spread with the population's values' own uncertainty folded in (their standard
  errors and the spread's degrees of freedom: :func:`~torchmisspec.population.uncertainty.new_subject_prior`, the
  textbook prediction interval; a population of few subjects knows its spread poorly);
* their posterior given the subject's first measurements (empirical Bayes): the conditional mode under the
  population's point estimates (as NONMEM's and Monolix's empirical Bayes estimates; why, below) and F, with its
  Laplace covariance (:mod:`~torchmisspec.population._modes`, the shared parameters held at the population's
  values): the bands narrow as the subject's own data come in.

Each parameter draw is integrated with :data:`F_DRAWS` posterior draws of F (:meth:`CorrectedODE.posterior
<torchmisspec.CorrectedODE.posterior>`), so the bands hold both; without a correction (F = 0 kept) the draws are of
the parameters alone. The result is a :class:`~torchmisspec.TrajectoryPosterior` of one path: its ``interval`` is
the band of the subject's states, ``measured(...)`` that of its new measurements. F's draws are the GP's own
(``scale=1.0`` of :meth:`CorrectedODE.posterior <torchmisspec.CorrectedODE.posterior>`). Either band is then
scaled as the population's held-out subjects showed it must be (:mod:`~torchmisspec.population.calibration`,
``fit.calibration`` and ``fit.calibration_alone``): on R's Loblolly 0.68 of a new tree's later heights fell in the
uncalibrated 90 % band from its 2 early heights, which pin its curve as if the population's residual scale held for
its whole future, and 1.00 in the band from the population alone.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from .._errors import InputError, TorchMisspecWarning, warn
from .._validation import check_flag, check_positive_int
from ..data import Trajectories
from ..noise import Additive
from ..prediction._bands import TrajectoryPosterior, widened
from ..prediction._flags import first_flagged
from ._misfit import misfit_scale
from ._modes import conditional_modes, held_prior
from ._subjects import drawn_controls
from .model import covariate_matrix

#: the share of a new subject's drawn paths outside F's training range that :func:`warn_beyond_f` warns about
BEYOND_F = 0.05
#: the share of drawn paths above (or below) the mean path beyond which the mean is said to be outside the band
OUTSIDE = 0.025

__all__ = [
    "SubjectDraws",
    "SubjectPrediction",
    "predict_subject",
    "subject_draws",
    "subject_parameters",
    "subjects_parameters",
    "times_from",
    "F_DRAWS",
]

#: posterior draws of F per draw of the subject's parameters
F_DRAWS = 4


@dataclass(frozen=True)
class SubjectPrediction:
    """A new subject's prediction (:func:`predict_subject`).

    Attributes:
        posterior: the subject's paths (:class:`~torchmisspec.TrajectoryPosterior`, one initial condition).
        theta: ``(k,)`` the subject's parameters at the centre of their distribution (G's order).
        eta_covariance: ``(k_v, k_v)`` the varying parameters' covariance in eta's units.
        updated: whether the subject's own measurements updated the population's distribution.
        band_scale: the factor on the drawn paths' deviation from the mean path (the fit's calibration on held-out
            subjects; 1: none applied).
    """

    posterior: TrajectoryPosterior
    theta: torch.Tensor
    eta_covariance: torch.Tensor
    updated: bool
    band_scale: float = 1.0


def subject_parameters(fit, first: Trajectories, X: torch.Tensor):
    """``(eta (k_v,), covariance (k_v, k_v), y0 (d,))``: a new subject's conditional mode given its measurements
    ``first`` (one experiment) under the fitted population and F."""
    if not isinstance(first, Trajectories) or first.num_experiments != 1:
        got = type(first).__name__ if not isinstance(first, Trajectories) else f"{first.num_experiments} experiments"
        raise InputError(f"first: expected the new subject's measurements as Trajectories of one experiment, got {got}")
    eta, cov, y0 = subjects_parameters(fit, first, X)
    return eta[0], cov[0], y0[0]


def subjects_parameters(fit, measured: Trajectories, X: torch.Tensor):
    """``(eta (K, k_v), covariance (K, k_v, k_v), y0 (K, d))``: :func:`subject_parameters` of each of the ``K``
    experiments of ``measured``, each an independent new subject (covariates ``X (K or 1, c)``), in one batched fit
    (the shared parameters are held at the population's values, and each sample is weighed by the population's
    misfit scale at the subject's own times, so the subjects do not interact): what scoring many candidate sets of
    sampling times costs as one fit. The fit stops when the subjects' total misfit settles, so a subject's mode can
    differ from its own fit's by that tolerance."""
    if not isinstance(measured, Trajectories):
        raise InputError(
            f"measured: expected Trajectories (one experiment per new subject), got {type(measured).__name__}"
        )
    from ..learning.choice._partial_choice import given_initial_states
    from ..learning.refinement.partial import initial_guess

    nlme = fit.nlme
    K = measured.num_experiments
    free = ~given_initial_states(measured)
    data = measured.with_initial_states(initial_guess(measured, fit.system))
    typical, spread = nlme.values.typical(X).expand(K, -1), nlme.values.spread  # point estimates (the notes)
    # the population's residual scale at each subject's own times (the design's weights): a subject's first few
    # measurements cannot estimate it, and a time where the population's model is off is trusted less
    times = measured.padded()[0]
    scale = torch.stack([misfit_scale(fit, t) for t in times])
    correction = fit.mean_correction
    prior = held_prior(nlme.modes.shared)
    modes = conditional_modes(nlme.layout, correction, data, free, fit.noise, typical, spread, prior, scale=scale)
    return modes.eta, modes.covariance, modes.initial_states


@dataclass(frozen=True)
class SubjectDraws:
    """A new subject's drawn paths (:func:`subject_draws`), before any calibration.

    Attributes:
        times: ``(T,)``; ``mean``: ``(1, T, d)`` the path at the parameters' centre and F's mean.
        parameters: ``(S, 1, T, d)`` the paths of the parameters' draws under F's mean.
        with_f: ``(S F_DRAWS, 1, T, d)`` the same draws each under :data:`F_DRAWS` posterior draws of F (``None``:
            not drawn, or F = 0).
        eta, covariance: the varying parameters' centre ``(k_v,)`` and covariance in eta's units.
    """

    times: torch.Tensor
    mean: torch.Tensor
    parameters: torch.Tensor
    with_f: torch.Tensor | None
    eta: torch.Tensor
    covariance: torch.Tensor


def subject_draws(
    fit, y0, times, *, covariates=None, first: Trajectories | None = None, controls=None, num_samples: int = 64,
    generator: torch.Generator | None = None, f_draws: bool = True,
) -> SubjectDraws:  # fmt: skip
    """:func:`predict_subject`'s drawn paths before its calibration and warnings (its arguments); ``f_draws``: draw F
    too (where F is kept)."""
    num_samples = check_positive_int(num_samples, "num_samples")
    X = covariate_matrix(fit.population, covariates, 1)
    nlme, layout = fit.nlme, fit.nlme.layout
    if first is not None:
        eta, cov, start = subject_parameters(fit, first, X)
    else:
        typical, spread = nlme.new_subject_prior(X)
        eta, cov, start = typical[0], torch.diag(spread**2), None
    from_first = y0 is None
    if y0 is None:
        if start is None:
            raise InputError("y0: expected the subject's initial state (d,), got None without first measurements")
        y0 = start
    y0 = torch.as_tensor(y0, dtype=torch.float64).reshape(-1)
    times = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    lead = 0
    if from_first:  # the state fitted at the first measurement: the path starts there
        times, lead = times_from(times, first)
    L = torch.linalg.cholesky(cov + 1e-12 * torch.eye(cov.shape[0], dtype=cov.dtype))
    draws = eta + torch.randn(num_samples, eta.shape[0], dtype=eta.dtype, generator=generator) @ L.T
    ctrl = drawn_controls(fit.system, layout, torch.cat([eta[None], draws]), nlme.modes.shared, times[:1], controls)
    paths = _parameter_paths(fit, y0.expand(num_samples + 1, -1), times, ctrl)[:, lead:]  # (1 + S, T, d)
    with_f = None
    if f_draws and not fit.known_model:
        with_f = _with_f_draws(fit, y0.expand(num_samples, -1), times, ctrl[1:], generator)[..., lead:, :]
    return SubjectDraws(times[lead:], paths[:1], paths[1:, None], with_f, eta, cov)


def predict_subject(
    fit, y0, times, *, covariates=None, first: Trajectories | None = None, controls=None, num_samples: int = 64,
    generator: torch.Generator | None = None, calibrated: bool = True,
) -> SubjectPrediction:  # fmt: skip
    """A new subject's trajectory from ``y0 (d,)`` over ``times (T,)`` under the population ``fit``
    (:class:`~torchmisspec.population.fit.PopulationFit`), its ``covariates`` (``{name: value}``), updated by its
    measurements ``first`` where given (the module's notes); ``y0=None`` takes ``first``'s fitted initial state,
    at its first time: ``times`` then run from there on (the path is integrated from that time; a time before it is
    refused). ``y0`` given is the state at ``times[0]``. ``controls``: the subject's own input profile for a system
    with controls. ``num_samples`` parameter draws. ``calibrated``: the band as the fit's calibration
    on held-out subjects found it must be (``fit.calibration`` with ``first``, ``fit.calibration_alone`` from the
    population alone; :mod:`~torchmisspec.population.calibration`, where the fit has one): with F's draws or F's
    mean, and the drawn paths' deviation from the mean path times its scale in the noise model's space
    (``calibrated=False``: the model's own band; from the population alone, the textbook prediction interval)."""
    calibrated = check_flag(calibrated, "calibrated")
    calibration = fit.calibration_for(first) if calibrated else None
    if calibration is not None and first is not None and first.num_times != calibration.first:
        warn(
            f"predict_subject: the fit's bands are calibrated for a subject predicted from its first "
            f"{calibration.first} measurements, and this one has {first.num_times}: its band is the model's own, not "
            f"calibrated. Calibrate for it with fit.recalibrated(first={first.num_times}) (seconds)",
            TorchMisspecWarning,
        )
        calibration = None
    use_f = calibration is None or calibration.f_draws
    draws = subject_draws(
        fit, y0, times, covariates=covariates, first=first, controls=controls, num_samples=num_samples,
        generator=generator, f_draws=use_f,
    )  # fmt: skip
    times, mean = draws.times, draws.mean
    samples = draws.parameters if draws.with_f is None else draws.with_f
    scale = 1.0 if calibration is None else calibration.scale
    if scale != 1.0:
        samples = widened(samples, mean, scale, fit.noise)
    if draws.with_f is not None:
        warn_beyond_f(fit, times, samples)
    warn_below_zero(fit, times, samples)
    warn_mean_outside(fit, times, mean, samples, with_f=draws.with_f is not None)
    T = times.shape[0]
    posterior = TrajectoryPosterior(
        times=times[None],
        samples=samples,
        mean_path=mean,
        support=torch.zeros(1, T, dtype=mean.dtype),
        extrapolating=torch.zeros(1, dtype=torch.bool),
        threshold=1.0,
        state_names=fit.system.state_names,
    )
    theta = fit.nlme.layout.theta(draws.eta, fit.nlme.modes.shared)
    return SubjectPrediction(posterior, theta, draws.covariance, first is not None, scale)


def times_from(times: torch.Tensor, first: Trajectories, name: str = "times") -> tuple[torch.Tensor, int]:
    """``(times to integrate over, how many lead them)``: ``times`` from the time of ``first``'s first measurement
    (prepended where they start later); a time before it is refused (the fitted state is the one there)."""
    origin = float(first.padded()[0].reshape(-1)[0])
    tol = 1e-9 * max(1.0, abs(origin))
    if float(times[0]) < origin - tol:
        raise InputError(
            f"{name}: expected times from the subject's first measurement at t = {origin:g} on (its fitted state is "
            f"there, and the path runs forward from it), got {float(times[0]):g}; start the times at {origin:g}, or "
            "give the state at the earlier time (y0; on the command line --next-initial) instead of the first "
            "measurements"
        )
    if float(times[0]) > origin + tol:
        return torch.cat([times.new_tensor([origin]), times]), 1
    return times, 0


def _with_f_draws(fit, y0: torch.Tensor, times: torch.Tensor, controls, generator) -> torch.Tensor:
    """``(S F_DRAWS, 1, T, d)``: every parameter draw's path (row of ``y0 (S, d)`` and ``controls``) under
    :data:`F_DRAWS` posterior draws of F; the draws that left the data's region are NaN from there, with one warning
    in the subject's terms (the solver's names the rows of ``y0``, here parameter draws, "initial conditions")."""
    with warnings.catch_warnings():  # the drawn paths that leave, said below; the mean paths that stall, said once
        warnings.filterwarnings(
            "ignore", "CorrectedODE.posterior: .* sampled paths left the region", TorchMisspecWarning
        )  # (by _parameter_paths: the same parameter draws under F's mean; the solver's words reached a trial)
        warnings.filterwarnings("ignore", "CorrectedODE.predict: .* stop early", TorchMisspecWarning)
        post = fit.corrected.posterior(
            y0, times, num_samples=F_DRAWS, controls=controls, generator=_on(generator), scale=1.0
        )  # F's own band: the held-out calibration of fit_correction does not apply to a population's F
    samples = post.samples.reshape(-1, 1, *post.samples.shape[2:])
    left = int((~torch.isfinite(samples).all(-1).all(-1)).sum())
    if left:
        warn(
            f"predict_subject: {left} of {samples.shape[0]} draws of the subject's path ({y0.shape[0]} draws of its "
            f"parameters, {F_DRAWS} draws of F each) left the region of the population's data and were stopped "
            "there: under those draws of F the path diverges, and the band comes from the draws that remain. F is "
            "extrapolated there: a shorter time span, or the subject's later measurements, keep the path nearer the "
            "data",
            TorchMisspecWarning,
        )
    return samples


def warn_beyond_f(fit, times: torch.Tensor, samples: torch.Tensor) -> None:
    """One warning where more than :data:`BEYOND_F` of the drawn paths ``samples (S, 1, T, d)`` take a state that F
    reads outside the range F was learned on (its training inputs: the states along the population's fitted
    paths): F is extrapolated there, and the band from that time on is F's prior guess more than the data's (on
    the populations tutorial, a patient's band at 12 h reached down to 2e-308 mg/L, below every concentration the
    population was measured at)."""
    system, X = fit.corrected.system, fit.gp.train_inputs_
    found = []
    for p, j in enumerate(system.correction_inputs):
        if j >= samples.shape[-1]:  # a control F reads: the subject's own, not drawn
            continue
        lo, hi = float(X[:, p].min()), float(X[:, p].max())
        x = samples[..., j].reshape(-1, samples.shape[-2])  # (S, T)
        seen = torch.isfinite(x)
        out = ((x < lo) | (x > hi)) & seen
        share = out.sum(0) / seen.sum(0).clamp_min(1)
        beyond = (share > BEYOND_F).nonzero().flatten()
        if beyond.numel():
            name = system.state_names[j] if system.state_names else f"y{j}"
            found.append(f"{name} from t = {float(times[beyond[0]]):.4g} (F learned on {lo:.3g} to {hi:.3g})")
    if found:
        warn(
            f"predict_subject: more than {BEYOND_F:.0%} of the subject's drawn paths leave the range of the states F "
            f"was learned on (the population's fitted paths): {'; '.join(found)}. F is extrapolated there, and the "
            "band from that time on is F's prior guess more than the data's: read it within that range, or measure "
            "the subject there",
            TorchMisspecWarning,
        )


def warn_below_zero(fit, times: torch.Tensor, samples: torch.Tensor) -> None:
    """One warning where some of the drawn paths ``samples (S, 1, T, d)`` take a state below 0 that the noise model
    measures as positive (relative or count noise): the band's lower edge is then below 0 there. On nlme's
    Remifentanil a next subject's band of the concentration reached -0.08 ng/mL after an hour, F's draws near 0
    (where a correction of the state alone is least pinned) pulling some paths below it."""
    if isinstance(fit.noise, Additive):
        return
    x = samples[:, 0]  # (S, T, d)
    below = (x < 0) & torch.isfinite(x)
    draws = below.any(1).sum(0)  # (d,) how many drawn paths go below 0 in each state
    found = [
        f"{name} in {int(draws[j])} of {x.shape[0]} {since}"
        for j, name, since in _first_times(fit, times, below.any(0))
    ]
    if found:
        warn(
            f"predict_subject: some of the subject's drawn paths go below 0, where its measurements are positive "
            f"(noise '{fit.noise.name}'): {'; '.join(found)}. The band's lower edge is below 0 there: those are F's "
            "draws (or G's) beyond what the data pin down, not possible values; read the band's lower edge as 0",
            TorchMisspecWarning,
        )


def warn_mean_outside(
    fit, times: torch.Tensor, mean: torch.Tensor, samples: torch.Tensor, *, with_f: bool = True
) -> None:
    """One warning where the path at the parameters' mode and F's mean, ``mean (1, T, d)``, lies above or below
    more than :data:`OUTSIDE` of the drawn paths ``samples (S, 1, T, d)`` (outside a 95 % band; paths that agree with
    it to the solver's precision, as at the subject's own first state, are neither). ``with_f``: the paths were
    drawn with F's draws; else over the subject's parameters under F's mean (a calibration that chose F's mean),
    where a path at the parameters' mode outside their paths means the path bends with them (G nonlinear in them).
    On nlme's Remifentanil, while F's derivative samples took one noise size for every concentration, a next
    subject's concentration at F's mean fell to 0.18 ng/mL while 95 % of the paths drawn with F stayed above 1.75: F's
    posterior spread at low concentrations (0.5-0.6 ng/mL/min) exceeded the elimination there (0.01-0.15), so most
    draws of F held the path at some level where the mean of F let it fall (now estimated in the noise model's space:
    :mod:`~torchmisspec.learning.samples._noise_space`)."""
    x = samples[:, 0]  # (S, T, d)
    seen = torch.isfinite(x)
    n = seen.sum(0).clamp_min(1)
    tol = 1e-6 * mean[0].abs()  # paths that agree with it to the solver's precision (its first time: all of them)
    above = ((x > mean[0] + tol) & seen).sum(0) / n
    below = ((x < mean[0] - tol) & seen).sum(0) / n
    outside = ((above > 1 - OUTSIDE) | (below > 1 - OUTSIDE)) & (seen.sum(0) > 0)
    found = [f"{name} {since}" for _, name, since in _first_times(fit, times, outside)]
    if not found:
        return
    where = "; ".join(found)
    why = (
        f"with F ({where}): F's draws there move the path where F's mean does not (F's uncertainty is larger than "
        "the dynamics it corrects, as near a steady state)"
        if with_f
        else f"over its parameters under F's mean ({where}): the path bends with its parameters, and the one at "
        "their mode is not the middle of those drawn about it"
    )
    warn(
        f"predict_subject: the subject's path at its parameters' mode and F's mean lies outside the central 95 % "
        f"of its paths drawn {why}. Read the band, not the mean path, and measure the subject there",
        TorchMisspecWarning,
    )


def _first_times(fit, times: torch.Tensor, flags: torch.Tensor) -> list[tuple[int, str, str]]:
    """:func:`~torchmisspec.prediction._flags.first_flagged` with the fit's state names."""
    return first_flagged(fit.system.state_names, times, flags)


def _parameter_paths(fit, y0: torch.Tensor, times: torch.Tensor, controls) -> torch.Tensor:
    """``(1 + S, T, d)``: :func:`_paths` of the subject's centre and its ``S`` parameter draws (rows of ``y0``); a
    path that stops early (the solver stalls: under F's mean, a drawn subject whose concentrations run where F is
    extrapolated) is NaN from there, with one warning in the subject's terms (the solver's names the rows,
    here parameter draws, "initial conditions": on nlme's Remifentanil 2 of 65 drawn subjects stalled during the
    infusion)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.filterwarnings("always", "CorrectedODE.predict: .* stop early", TorchMisspecWarning)
        paths = _paths(fit, y0, times, controls)
    for w in caught:
        if not str(w.message).startswith("CorrectedODE.predict:") or "stop early" not in str(w.message):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    stopped = int((~torch.isfinite(paths[1:]).all(-1).all(-1)).sum())
    if stopped:
        warn(
            f"predict_subject: the paths of {stopped} of {y0.shape[0] - 1} draws of the subject's parameters (under "
            "F's mean) stop early where the solver stalls, and are left out of the band from there: those drawn "
            "subjects run where F is extrapolated (beyond the population's data), and their path there is not known",
            TorchMisspecWarning,
        )
    return paths


def _paths(fit, y0, times, controls) -> torch.Tensor:
    """``(B, T, d)``: the paths of G (+ F's mean where there is a correction) from ``y0 (B, d)``, each row under its
    own ``controls``."""
    if fit.gp is not None:
        return fit.corrected.predict(y0, times, controls=controls)
    from ..data import simulate

    sim = simulate(fit.subject_system, y0, times, known_only=True, controls=controls, rtol=1e-7, atol=1e-9)
    return sim.states


def _on(generator):
    """A generator for F's draws, seeded from ``generator`` (``None``: none)."""
    if generator is None:
        return None
    g = torch.Generator(device=generator.device)
    g.manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))
    return g
