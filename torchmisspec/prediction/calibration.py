"""Calibrating the predicted uncertainty bands on held-out experiments.

The bands of :meth:`CorrectedODE.posterior <torchmisspec.CorrectedODE.posterior>` are exact for the GP model, but
the GP model is not the truth: with few experiments the marginal likelihood picks hyperparameters that are too
sure of themselves (long lengthscales, small output scales), and a stationary prior fitted near the data does not
know that F grows away from it. The bands then cover the true trajectories less often than they claim
(``docs/studies/calibration.md``). Hyperparameter uncertainty (``hyperparameters="laplace"``) helps but does not
repair a prior of the wrong shape.

:func:`calibrate_bands` measures the miscalibration where it matters, on trajectories, with the data already in
hand: each fold of experiments is held out, the correction GP is refitted (or conditioned) on the rest and
refined through the ODE when the model was, and the corrected model's posterior paths are started from each
held-out experiment's first observed state and compared with its observed states. The band's spread is widened
(or narrowed) by one factor ``c`` on the deviation of every sampled path from the mean path (the path of the
posterior mean of F),

    y_c(t) = y_mean(t) + c (y_s(t) - y_mean(t)),

to first order in the deviation the path of the draw F_c = mu + c (F_s - mu), that is, of the posterior covariance of
F times ``c^2``. Scaling the paths rather than integrating the widened draws keeps every path one the solver already
integrated: a draw widened 8 times is a field far from the data that can make the solver stall (the issue's trial),
and each held-out posterior is integrated once, not once per scale tried. The calibrated ``c`` is the smallest one
under which the held-out observed states lie in the central ``level`` band at least a fraction ``level`` of the time
(pooled over every held-out time after the first and every component; found by bisection in log c: the paths are
the same at every c, so coverage grows with c). This is the recalibration of
Kuleshov et al. (2018, "Accurate uncertainties for deep learning using calibrated regression") with the held-out
experiments as the calibration set; like any such rule it assumes new initial conditions resemble the experiments'.

Observation noise on the states (``state_noise``; by default the noise the GP in time finds in the data) is added to
the held-out paths before they are compared with the observed states, so that noisy observations do not inflate
``c``, and early observations, where the paths have not yet spread, can be covered at all; the calibrated bands are
for the states themselves. The uncertainty of a noisy first observed state is not propagated: it is absorbed into ``c``.
"""

from __future__ import annotations

import math
import warnings

import torch

from .._errors import (
    FittingError,
    InputError,
    IntegrationError,
    LinearAlgebraError,
    NumericalWarning,
    ShapeError,
    TorchMisspecWarning,
    clipped,
    warn,
)
from .._validation import as_tensor, check_flag, check_positive_int, check_real, progress_bar
from ..data import Trajectories
from ..gp._calibration import BandCalibration
from ..learning.choice.cross_validation import _check_cv_inputs
from ..learning.refinement.trajectory_fit import fit_trajectories
from ..learning.samples._gp_in_time import estimate_observed_noise
from ..learning.samples.observations import CorrectionSamples, _check_trajectories_and_system
from ..learning.theta.through_ode import fit_parameters
from ..parallel import check_executor, map_tasks
from ._bands import band_quantiles, path_quantiles

__all__ = ["MAX_LOG2_SCALE", "MIN_LOG2_SCALE", "BandCalibration", "calibrate_bands"]

#: The bisection's bracket of log2 c: c from 1/16 to 256.
MIN_LOG2_SCALE, MAX_LOG2_SCALE = -4.0, 8.0
#: Observation-noise draws added to each held-out path when ``state_noise`` is given (so that the band of path plus
#: noise is estimated from num_samples x NOISE_DRAWS values, not from num_samples alone).
NOISE_DRAWS = 16
#: Bisection steps: the bracket of 12 in log2 c shrinks to 12 / 2^10 < 0.012, a relative precision of ~1 % on c
#: (each step costs a few tensor operations: the paths are integrated once).
BISECTION_STEPS = 10


def _check_level(level) -> float:
    level = check_real(level, "level", positive=True)
    if level >= 1.0:
        raise InputError(f"level: expected a band's coverage in (0, 1), got {level!r}")
    return level


def _state_noise(state_noise, trajectories: Trajectories, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(absolute (e,), relative (e,))`` standard deviations of the observation noise on the states and any
    readings (e = d + m): a new observation of a value y is y + (absolute + relative |y|) z, z standard normal."""
    d, e = trajectories.state_dim, trajectories.observed_dim
    zeros = torch.zeros(e, dtype=dtype, device=device)
    if state_noise is None:
        return zeros, zeros
    if isinstance(state_noise, str) and state_noise == "auto":
        estimate = estimate_observed_noise(trajectories)
        return (zeros if estimate is None else estimate.to(dtype=dtype, device=device)), zeros
    if isinstance(state_noise, str):
        text = state_noise.strip()
        try:
            value = float(text[:-1]) / 100.0 if text.endswith("%") else math.nan
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value >= 0):
            raise InputError(
                f"state_noise: expected 'auto', a percentage such as '2%' (noise relative to the state), a "
                f"standard deviation or one per state component, got {state_noise!r}"
            )
        return zeros, zeros + value
    noise = as_tensor(state_noise, "state_noise", dtype=dtype, device=device)
    if noise.dim() == 0:
        noise = noise.expand(e)
    if noise.shape != (e,):
        what = "state" if e == d else "state and reading"
        raise ShapeError(
            f"state_noise: expected a standard deviation or {e} of them (one per {what}), got {noise.shape}"
        )
    if not bool(torch.isfinite(noise).all()) or bool((noise < 0).any()):
        raise InputError(f"state_noise: expected finite standard deviations >= 0, got {noise.tolist()}")
    return noise, zeros


def _fold(task: dict) -> dict:
    """One fold of :func:`calibrate_bands` (a task for an executor: everything it needs is in ``task``): the GP refitted
    (or conditioned) without the fold's experiments, refined like the model, and the held-out experiments' posterior
    paths. Returns ``paths`` (``None`` when the fold cannot be fitted), its warnings (``numerical``, ``other``) and
    ``failed``, the message of a held-out solve that failed."""
    f, folds, gp, samples = task["fold"], task["folds"], task["gp"], task["samples"]
    system, trajectories = task["system"], task["trajectories"]
    K = trajectories.num_experiments
    ks = [k for k in range(K) if k % folds == f]
    keep = ~torch.isin(samples.experiment, torch.tensor(ks, device=samples.experiment.device))
    sample_noise = None if samples.noise is None else samples.noise[keep]
    out = {"paths": None, "numerical": [], "other": [], "failed": None}
    with warnings.catch_warnings(record=True) as caught:  # the folds' fits are ours: summarised by the caller
        warnings.simplefilter("always")
        try:
            if task["refit"]:
                fold_gp = gp.clone(kernel=gp.kernel_spec)  # the kernel chosen, refitted
                fold_gp.fit(samples.inputs[keep], samples.targets[keep], noise=sample_noise)
            else:
                fold_gp = gp.condition(samples.inputs[keep], samples.targets[keep], noise=sample_noise)
            rest = trajectories[[k for k in range(K) if k % folds != f]]
            parameters = task["parameters"]
            if parameters is not None and samples.basis is not None:  # G's theta too
                delta = parameters.mean - parameters.prior_mean
                fold_gp = fit_parameters(fold_gp, samples.subset(keep), system, rest, delta)[0]
            if task["refinement"] is not None:  # the model was refined through the ODE: so is each fold
                found = getattr(fold_gp, "parameters_", None)  # G's theta: F refined at its mean, kept
                at = system if found is None else system.at(found.mean)
                fold_gp = fit_trajectories(fold_gp, at, rest, **task["refinement"])
                if found is not None:
                    fold_gp.parameters_ = found
        except (FittingError, LinearAlgebraError, IntegrationError):
            fold_gp = None  # this fold cannot be held out (too few samples left); the others still calibrate
    out["numerical"] = [str(w.message) for w in caught if issubclass(w.category, NumericalWarning)]
    out["other"] = [(str(w.message), w.category) for w in caught if not issubclass(w.category, NumericalWarning)]
    if fold_gp is None:
        return out
    fold_model = task["model_type"](system, fold_gp)
    experiments, values, first = task["experiments"], task["values"], task["first"]
    by_length: dict[int, list[int]] = {}
    for k in ks:  # experiments of one length are integrated together
        by_length.setdefault(experiments[k][0].shape[0], []).append(k)
    kd = dict(dtype=gp.dtype, device=gp.device)
    paths = []
    for j, group in enumerate(by_length.values()):
        times = torch.stack([experiments[k][0] for k in group]).to(**kd)
        observed = values[group, : times.shape[-1]].to(**kd)
        controls = None if trajectories.controls is None else trajectories.controls[group]
        gen = torch.Generator(device=gp.device).manual_seed(task["seed"] + 7919 * f + j)
        with warnings.catch_warnings():  # held-out paths leave their fold's data by design: not the user's
            warnings.simplefilter("ignore", TorchMisspecWarning)
            try:
                post = fold_model.posterior(
                    first[group].to(**kd),
                    times,
                    num_samples=task["num_samples"],
                    generator=gen,
                    scale=1.0,
                    controls=controls,
                    **task["posterior_options"],
                )
            except IntegrationError as exc:
                out["failed"] = f"calibrate_bands: the held-out posterior paths of fold {f} fail ({exc})"
                return out
        mean = trajectories.observe(post.mean_path[:, 1:])  # every path starts at the first observed state
        z = None
        if task["noisy"]:  # NOISE_DRAWS noise draws per path: the band's quantiles of path + noise
            shape = (task["num_samples"], NOISE_DRAWS, *mean.shape)
            z = torch.randn(shape, generator=gen, dtype=mean.dtype, device=mean.device)
        paths.append((mean, trajectories.observe(post.samples[:, :, 1:]) - mean, z, observed[:, 1:]))
    out["paths"] = paths
    return out


def calibrate_bands(
    model,
    trajectories: Trajectories,
    samples: CorrectionSamples,
    *,
    level: float = 0.9,
    folds: int = 10,
    num_samples: int = 32,
    refit: bool = True,
    state_noise="auto",
    generator: torch.Generator | None = None,
    progress: bool = True,
    executor=None,
    **posterior_options,
) -> BandCalibration:
    """Calibrate the spread of ``model.posterior``'s bands on held-out experiments (see the module docstring).

    Args:
        model: a :class:`~torchmisspec.CorrectedODE` whose GP was fitted on ``samples``.
        trajectories: the observed experiments the samples came from (experiment k of the samples is experiment k
            here); the held-out paths start at each experiment's first observed state and are compared at its other
            observed times. Missing entries (NaN) are left out of the comparison; a missing entry of a first state
            is estimated by :meth:`Trajectories.filled` (a local quadratic fit through its component's nearest
            observed values).
        samples: the correction samples (:func:`~torchmisspec.correction_samples`).
        level: the band to calibrate, in (0, 1) (default the central 90 %).
        folds: experiment k is held out in fold ``k % folds``; at most the number of experiments (>= 2).
        num_samples: posterior draws per held-out path.
        refit: re-learn the GP's hyperparameters in every fold (default: the honest choice, since the
            hyperparameters' own error is part of what the bands miss); ``False`` conditions the fitted GP on the
            other folds (cheaper, keeps the hyperparameters). A model refined through the ODE
            (:func:`~torchmisspec.fit_trajectories`, as :func:`~torchmisspec.fit_correction` does for the feature
            kernel; its settings are ``gp.refinement_``) has each fold refined the same way on the fold's
            experiments (with ``refit=False`` keeping the term weights): a fold fitted to the samples alone is a
            worse model than the one calibrated, and its held-out errors would widen the bands too much (the
            end-to-end study's bands covered 0.98 before). This costs one refinement per fold.
        state_noise: the observation noise on the states: ``"auto"`` (default: the standard deviation per
            component that the GP in time finds in the data,
            :func:`~torchmisspec.learning.samples.observations.estimate_state_noise`; about 0 for exact states), a
            standard deviation or one per state component, a percentage such as ``"2%"`` (noise proportional to the
            state), or ``None`` (exact states, the paper's setting).
        generator: ``torch.Generator`` for the draws (the same draws are reused at every scale).
        progress: show a progress bar over the folds (``False``: silent).
        executor: a ``concurrent.futures.Executor`` (:func:`torchmisspec.parallel.process_pool`, a Dask or Ray
            client's executor) to run the folds on, or ``None`` (here, one after another): the same result either
            way. A process pool must be able to pickle the model (a system whose functions are defined at a module's
            top level; an executor that pickles by value, as Dask's, takes lambdas too).
        **posterior_options: passed to ``model.posterior`` (e.g. ``hyperparameters="laplace"``, or the solver's
            settings as ``solver=Solver(...)``, :class:`~torchmisspec.Solver`).

    Returns:
        :class:`BandCalibration`; ``model.posterior(..., scale=result.scale)`` uses it, and
        :meth:`CorrectedODE.calibrate <torchmisspec.CorrectedODE.calibrate>` makes it the model's default.

    Raises:
        FittingError: no fold could be fitted and integrated (a fold that cannot is left out, with a warning).
    """
    _check_model(model, posterior_options)
    system, gp = model.system, model.gp
    level = _check_level(level)
    refit = check_flag(refit, "refit")
    num_samples = check_positive_int(num_samples, "num_samples")
    _check_trajectories_and_system(trajectories, system)
    folds = _check_cv_inputs(system, trajectories, samples, folds)
    absolute, relative = _state_noise(state_noise, trajectories, gp.dtype, gp.device)
    noisy = bool(absolute.any() or relative.any())
    seed = int(torch.randint(0, 2**62, (1,), generator=generator)) if generator is not None else 0
    executor = check_executor(executor)
    tasks = _fold_tasks(model, trajectories, samples, folds, refit, seed, num_samples, noisy, posterior_options)
    bar = progress_bar(progress, folds, "calibrate: refit and predict each fold", "fold")
    results = map_tasks(_fold, tasks, executor, each=lambda _: bar.update())
    bar.close()
    held_out = _held_out(results, gp)
    # the band the user's posterior.interval(level) draws from num_samples paths (times the noise draws)
    quantiles = band_quantiles(
        level, num_samples * (NOISE_DRAWS if noisy else 1), dtype=gp.dtype, device=gp.device, what="calibrate"
    )
    paths = [p for r in held_out for p in r["paths"]]  # (mean path, deviations, noise draws or None, observed)
    total = sum(int(torch.isfinite(obs).sum()) for *_, obs in paths)  # missing entries (NaN) are not compared
    coverage = _coverage(paths, quantiles, absolute, relative, total)
    scale, tried, reached = _smallest_covering_scale(coverage, level, total)
    final = next(v for c, v in reversed(tried) if c == scale)
    if not reached:
        warn(
            f"calibrate_bands: no scale up to {2.0**MAX_LOG2_SCALE:g} makes the central {level:g} band cover the "
            f"held-out observations (at best {final:.3f}, from scale {scale:.3g}, which is kept): some held-out bands "
            "have no spread to widen (a fold whose refit explained the signal away as noise, or observations far from "
            "every draw); these bands stay unreliable",
            TorchMisspecWarning,
        )
    if scale == 2.0**MIN_LOG2_SCALE and final >= level:  # the narrowest scale tried still covers
        scale, final = _at_the_floor(coverage, level, noisy, scale, final, tried[0][1])
    return BandCalibration(
        scale=scale,
        level=level,
        coverage_at_one=tried[0][1],
        coverage=final,
        scales=tuple(c for c, _ in tried),
        coverages=tuple(v for _, v in tried),
        folds=len(held_out),
        refit=refit,
        num_points=total,
        reached=reached,
    )


def _check_model(model, posterior_options: dict) -> None:
    """Refuse a model that is not a :class:`~torchmisspec.CorrectedODE` (this module does not import dynamics, which
    imports it: each fold's model is one of the model's kind), and posterior options that calibration sets itself."""
    if not all(hasattr(model, name) for name in ("system", "gp", "posterior")):
        raise InputError(
            f"model: expected a CorrectedODE (torchmisspec.CorrectedODE(system, gp)), got {type(model).__name__}"
        )
    if "scale" in posterior_options or "num_samples" in posterior_options:
        raise InputError(
            "posterior_options: expected neither scale nor num_samples (calibrate_bands sets them), got "
            f"{sorted(set(posterior_options) & {'scale', 'num_samples'})}"
        )


def _coverage(paths: list, quantiles, absolute: torch.Tensor, relative: torch.Tensor, total: int):
    """``coverage(c)``: the fraction of the ``total`` held-out observations inside the band at scale c, each path's
    deviation from its mean path times c (plus its noise draws): the same draws at every c, never re-integrated."""

    def coverage(c: float) -> float:
        hits = 0
        for mean, dev, z, obs in paths:
            draws = mean + c * dev
            if z is not None:
                draws = (draws.unsqueeze(1) + (absolute + relative * draws.abs()).unsqueeze(1) * z).flatten(0, 1)
            lo, hi = path_quantiles(draws, quantiles)  # a diverged path makes its side of the band unbounded
            hits += int(((obs >= lo) & (obs <= hi)).sum())  # False where obs is NaN (missing)
        return hits / max(total, 1)

    return coverage


def _fold_tasks(model, trajectories, samples, folds, refit, seed, num_samples, noisy, posterior_options) -> list:
    """One task per fold for :func:`_fold` (through an executor: each holds everything its fold needs, what every
    fold shares computed once). A model refined through the ODE has each fold refined the same way, keeping the term
    weights where the GP is conditioned rather than refitted."""
    gp = model.gp
    refinement = getattr(gp, "refinement_", None)
    if refinement is not None and not refit:  # conditioning keeps the hyperparameters: the term weights too
        refinement = {**refinement, "relevance": False}
    common = dict(
        experiments=trajectories.experiments(),
        values=trajectories.observed_values()[0],  # (K, T_max, d + m): the states and any readings
        first=trajectories.initial_conditions,  # missing first entries estimated (Trajectories.filled)
        model_type=type(model),
        parameters=getattr(model, "parameters_", None),
        system=model.system,
        gp=gp,
        trajectories=trajectories,
        samples=samples,
        folds=folds,
        refit=refit,
        refinement=refinement,
        seed=seed,
        num_samples=num_samples,
        noisy=noisy,
        posterior_options=posterior_options,
    )
    return [dict(common, fold=f) for f in range(folds)]


def _held_out(results: list[dict], gp) -> list[dict]:
    """The folds' results that hold paths, with what the folds warned passed on: their fits' numerical warnings in
    one summary, anything else as it was, and the folds whose held-out paths could not be integrated."""
    fold_warnings = [m for r in results for m in r["numerical"]]
    for message, category in (w for r in results for w in r["other"]):  # anything else reaches the user as it was
        warn(message, category)
    failed = [r["failed"] for r in results if r["failed"] is not None]
    if failed and len(failed) == len(results):
        raise FittingError(failed[0])
    if failed:  # a fold whose held-out paths cannot be integrated: calibrated on the others, and said
        warn(
            f"calibrate_bands: the held-out posterior paths of {len(failed)} of {len(results)} folds cannot be "
            f"integrated (first: {failed[0][len('calibrate_bands: ') :][:240]}); the bands are calibrated on the "
            "other folds, and predictions from states like that fold's may fail too",
            TorchMisspecWarning,
        )
    if fold_warnings:
        warn(
            f"calibrate_bands: the refit of the GP on {len(fold_warnings)} fold(s) warned (first: "
            f"{clipped(fold_warnings[0])}). The folds are refitted with the model's own settings (e.g. max_iter="
            f"{gp.max_iter}) and used as they are; to change the settings, fit the model with others (a "
            "CorrectionGP(max_iter=...) template) and calibrate again",
            NumericalWarning,
        )
    held_out = [r for r in results if r["paths"] is not None]
    if not held_out:
        raise FittingError("calibrate_bands: no fold could be fitted; calibrate with more experiments")
    return held_out


def _at_the_floor(coverage, level: float, noisy: bool, scale: float, final: float, at_one: float):
    """``(scale, coverage)`` where even the narrowest scale covers the held-out data, with a warning: where the
    measurement noise alone (the model's spread at scale 0) covers them, these data cannot tell how wide the model's
    own uncertainty should be, and the bands are left as the model gives them (scale 1: narrowing them to the floor
    made R's Indometh forecasts 16 times too narrow); otherwise the floor is kept, and the bands stay too wide."""
    if noisy and coverage(0.0) >= level:
        warn(
            f"calibrate_bands: the measurement noise alone covers {level:g} of the held-out observations (at every "
            f"scale tried, down to {scale:g}, the band covered {final:.3f}): these data cannot tell how wide the "
            "model's own uncertainty should be, so the bands are left as the model gives them (scale 1)",
            TorchMisspecWarning,
        )
        return 1.0, at_one
    warn(
        f"calibrate_bands: even the narrowest scale tried ({scale:g}) leaves the central {level:g} band covering "
        f"{final:.3f} of the held-out observations: the bands stay wider than the held-out data show",
        TorchMisspecWarning,
    )
    return scale, final


def _smallest_covering_scale(coverage, level: float, total: int) -> tuple[float, list[tuple[float, float]], bool]:
    """``(scale, tried, reached)``: the smallest scale c whose held-out ``coverage(c)`` reaches ``level``, found by
    bisection in log2 c (coverage grows with c: the paths are the same at every c); ``tried`` the (c, coverage)
    pairs evaluated, c = 1 first; ``reached`` False where no scale up to ``2**MAX_LOG2_SCALE`` covers (then the
    smallest doubling within one standard error of the best coverage over ``total`` points is kept)."""
    tried: list[tuple[float, float]] = [(1.0, coverage(1.0))]

    def covers_at(log2c: float) -> bool:
        value = coverage(2.0**log2c)
        tried.append((2.0**log2c, value))
        return value >= level

    # bracket [lo, hi] in log2 c with coverage below the level at lo and at least the level at hi
    reached = True
    if tried[0][1] >= level:
        lo, hi = MIN_LOG2_SCALE, 0.0
        if covers_at(lo):
            lo = hi = MIN_LOG2_SCALE  # even the narrowest scale covers
    else:
        lo, hi = 0.0, MAX_LOG2_SCALE
        if not covers_at(hi):
            # the widest scale fails (its draws may blow up): walk up the doublings to the first that covers
            for step in range(1, int(MAX_LOG2_SCALE)):
                if covers_at(float(step)):
                    lo, hi = step - 1.0, float(step)
                    break
            else:
                # out of reach (held-out bands with no spread: e.g. a fold whose refit explained the signal away as
                # noise): keep the smallest doubling within one standard error of the best coverage (where widening
                # stops helping; wider draws only risk blowing up)
                reached = False
                finite = [(c, v) for c, v in tried if not math.isnan(v)]
                best = max(v for _, v in finite)
                slack = max(1.0 / total, math.sqrt(best * (1.0 - best) / total))
                hi = lo = math.log2(min(c for c, v in finite if v >= best - slack))
    for _ in range(BISECTION_STEPS):
        if hi - lo <= 0:
            break
        mid = 0.5 * (lo + hi)
        if covers_at(mid):
            hi = mid
        else:
            lo = mid
    return 2.0**hi, tried, reached
