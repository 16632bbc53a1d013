"""The real-data suite's pieces (issue 41): the classical answer, the folds of each protocol, the metrics, and one
fold of the study (the package's defaults against the classical answer).

Study code: the library never imports it. Used by :mod:`torchmisspec.paper.study_real_data`.

**The classical answer** (:func:`classical_fit`): the model's uncertain parameters, and the initial states that
the first row does not give, fitted alone (F = 0) by least squares on log values (``log y`` for positive
measurements with multiplicative errors, ``log(1 + y)`` for counts), with ``scipy.optimize.least_squares`` over
:func:`~torchmisspec.simulate` of ``system.at(theta)``; the parameters and those initial states are fitted on a
log scale (all positive), from the priors' means. A solve that fails (or needs more than
:data:`CLASSICAL_MAX_STEPS` steps) gives a large residual (a rejected step); the fit's solves use looser tolerances
(:data:`CLASSICAL_TOLERANCES`) and stop at the best point so far after :data:`CLASSICAL_SECONDS`.

**Protocols** (:func:`folds`): several experiments: leave one experiment out, predict it from its first row
(every state given there). One trajectory: rolling origins, fit on the data up to the origin (a window of the last
``window`` times where set), forecast the next ``horizon`` times: from the measured state at the origin where every
state is measured, else from the start of the training data with the fitted initial state (each method its own).
"""

from __future__ import annotations

import math
import time
import traceback
import warnings

import numpy as np
import torch

import torchmisspec as tms

DT = torch.float64
#: Residual of a trial step whose solve failed (in log units: far worse than any fit).
FAILED_RESIDUAL = 1e3
#: Most solver steps of one classical solve (a trial step whose solve needs more is rejected, not waited for).
CLASSICAL_MAX_STEPS = 2000
#: The classical fit's solver tolerances (rtol, atol): the scipy fit's finite differences need far less than the
#: package's simulation accuracy, which made one trial solve of the lynx model take seconds.
CLASSICAL_TOLERANCES = (1e-7, 1e-6)
#: Wall-clock budget of one classical fit (seconds): past it the best point so far is the answer.
CLASSICAL_SECONDS = 120.0
#: Positive measurements' and predictions' floor before the log (a prediction at or below 0 scores as this).
LOG_FLOOR = 1e-6


def log_values(y: torch.Tensor, noise: str) -> torch.Tensor:
    """What the errors are measured on: ``log(1 + y)`` for counts, ``log y`` otherwise (``y`` clamped at the floor)."""
    if noise == "counts":
        return torch.log1p(y.clamp_min(0.0))
    return torch.log(y.clamp_min(LOG_FLOOR))


def log_rmse(pred: torch.Tensor, data: torch.Tensor, noise: str) -> float:
    """RMSE of the log values over the entries ``data`` has (not NaN); NaN if the prediction is not finite there."""
    seen = ~torch.isnan(data)
    diff = log_values(pred[seen], noise) - log_values(data[seen], noise)
    if not bool(torch.isfinite(pred[seen]).all()):
        return float("nan")
    return float(diff.pow(2).mean().sqrt())


# ---- the classical answer ---------------------------------------------------------------------------------------
def _unpack(x: np.ndarray, k: int, first: torch.Tensor, free: torch.Tensor):
    theta = torch.tensor(np.exp(x[:k]), dtype=DT)
    y0 = first.clone()
    y0[free] = torch.tensor(np.exp(x[k:]), dtype=DT)
    return theta, y0


def classical_fit(system: tms.MisspecifiedSystem, train: tms.Trajectories, noise: str, max_nfev: int = 200):
    """``(theta, y0)``: the parameters and every experiment's initial states ``(K, d)`` of the model alone (F = 0)
    fitted by least squares on log values (the module's docstring); entries of ``y0`` the first rows give are kept."""
    from scipy.optimize import least_squares

    experiments = train.experiments()
    times = [t for t, _ in experiments]
    first = torch.stack([y[0] for _, y in experiments])
    free = torch.isnan(first)
    observed = [~torch.isnan(y[1:]) for _, y in experiments]  # the first row is the starting point, not a residual
    targets = torch.cat([log_values(y[1:][m], noise) for (_, y), m in zip(experiments, observed, strict=True)])
    k = system.theta.numel()
    fill = float(torch.nanmean(torch.cat([y[~torch.isnan(y)] for _, y in experiments])))
    x0 = np.concatenate([np.log(system.theta.numpy()), np.full(int(free.sum()), math.log(max(fill, 1e-3)))])

    best = {"cost": math.inf, "x": x0}
    t0 = time.perf_counter()

    def residuals(x: np.ndarray) -> np.ndarray:
        if time.perf_counter() - t0 > CLASSICAL_SECONDS:
            raise _OutOfTime
        theta, y0 = _unpack(x, k, first, free)
        try:
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rtol, atol = CLASSICAL_TOLERANCES
                grid = times if len(times) > 1 else times[0]
                sim = tms.simulate(system.at(theta), y0, grid, max_steps=CLASSICAL_MAX_STEPS, rtol=rtol, atol=atol)
        except Exception:  # noqa: BLE001 - a failed trial solve is a rejected step
            return np.full(targets.numel(), FAILED_RESIDUAL)
        paths = sim.states if isinstance(sim.states, tuple) else list(sim.states)
        pred = torch.cat([log_values(p[1:][m], noise) for p, m in zip(paths, observed, strict=True)])
        out = (pred - targets).numpy()
        out = np.where(np.isfinite(out), out, FAILED_RESIDUAL)
        if float(out @ out) < best["cost"]:
            best.update(cost=float(out @ out), x=np.array(x))
        return out

    try:
        x = least_squares(residuals, x0, method="trf", max_nfev=max_nfev, diff_step=1e-5).x
    except _OutOfTime:
        x = best["x"]
    return _unpack(x, k, first, free)


class _OutOfTime(Exception):
    """The classical fit's budget is spent (:data:`CLASSICAL_SECONDS`)."""


def classical_predict(system, theta: torch.Tensor, y0: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """``(T, d)``: the model alone at ``theta`` from ``y0 (d,)`` over ``times``."""
    with torch.no_grad():
        return tms.simulate(system.at(theta), y0[None], times).states[0]


# ---- the protocols -----------------------------------------------------------------------------------------------
def folds(data, protocol: dict, limit: int | None = None) -> list[dict]:
    """The folds of a data set: ``{"label", "train", "start", "times", "held_out", "from_origin"}``; ``start`` is the
    test path's first row (NaN where a method must use its own fitted initial state), ``held_out`` the measurements
    scored (NaN elsewhere) at the last ``len(held_out)`` of ``times``."""
    trajs = data.trajectories
    out = []
    if trajs.num_experiments > 1:
        chosen = protocol.get("experiments") or range(trajs.num_experiments)
        for k in chosen:
            t, y = trajs.experiments()[k]
            rest = [i for i in range(trajs.num_experiments) if i != k]
            out.append(dict(label=f"experiment {k + 1}", train=trajs[rest], start=y[0], times=t, held_out=y[1:]))
    else:
        t, y = trajs.experiments()[0]
        h, w = protocol["horizon"], protocol.get("window")
        for o in protocol["origins"]:  # index of the last training time
            lo = 0 if w is None else max(0, o - w + 1)
            train = tms.Trajectories(t[lo : o + 1], y[lo : o + 1][None], state_names=trajs.state_names)
            full = bool(train.measured.all())
            begin = o if full else lo
            label = f"origin {float(t[o]):g}"
            out.append(
                dict(
                    label=label, train=train, start=y[begin], times=t[begin : o + h + 1], held_out=y[o + 1 : o + h + 1]
                )
            )
    return out[:limit]


def _exception(stage: str, exc: BaseException) -> dict:
    frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    where = f"{frame.filename.split('torchmisspec/')[-1]}:{frame.lineno}" if frame else ""
    return {"stage": stage, "type": type(exc).__name__, "message": str(exc)[:400], "where": where}


def _start(fold: dict, fitted: torch.Tensor | None) -> torch.Tensor:
    """The test path's first state: the fold's, its NaN entries from the method's fitted initial state."""
    y0 = fold["start"].clone()
    missing = torch.isnan(y0)
    if bool(missing.any()):
        if fitted is None:
            raise RuntimeError("no fitted initial state for the states the data do not give")
        y0[missing] = fitted[missing]
    return y0


def _score(pred: torch.Tensor, fold: dict, noise: str) -> float:
    n = fold["held_out"].shape[0]
    return log_rmse(pred[-n:], fold["held_out"], noise)


def _warned(caught) -> list[str]:
    seen: list[str] = []
    for w in caught:
        text = f"{w.category.__name__}: {str(w.message)[:160]}"
        if text not in seen:
            seen.append(text)
    return seen


def run_default(data, fold: dict, num_samples: int, send) -> None:
    """The package's defaults on one fold: ``fit_correction(train, system)``, ``CorrectedODE.predict`` from the
    test's start and ``posterior(..., num_samples)``'s 90 % band; each stage's result ``send``-ed as it comes (a
    stage that raises is recorded with its type and message, and ends the method)."""
    system, stage = data.system, "fit_correction"
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0 = time.perf_counter()
            gp = tms.fit_correction(fold["train"], system, progress=False)
            found = getattr(gp, "parameters_", None)
            send(
                fit_seconds=time.perf_counter() - t0,
                kernel=repr(getattr(gp, "kernel", None))[:120],
                known_model=bool(getattr(gp, "known_model_", False)),
                default_theta=None if found is None else found.mean.tolist(),
            )
            stage = "predict"
            fitted = getattr(gp, "initial_states_", None)
            y0 = _start(fold, None if fitted is None else fitted[0])
            model = tms.CorrectedODE(system, gp)
            t0 = time.perf_counter()
            pred = model.predict(y0, fold["times"])[0]
            send(default_log_rmse=_score(pred.detach(), fold, data.noise), predict_seconds=time.perf_counter() - t0)
            stage = "posterior"
            t0 = time.perf_counter()
            post = model.posterior(
                y0, fold["times"], num_samples=num_samples, generator=torch.Generator().manual_seed(0)
            )
            if getattr(gp, "noise_scale_", None) is not None:  # the band of new measurements, noise included
                post = post.measured(gp.noise_, gp.noise_scale_, generator=torch.Generator().manual_seed(0))
            lower, upper = (b[0, -fold["held_out"].shape[0] :] for b in post.interval(0.9))
            seconds = time.perf_counter() - t0
            seen = ~torch.isnan(fold["held_out"])
            inside = (fold["held_out"] >= lower) & (fold["held_out"] <= upper)
            finite = torch.isfinite(lower) & torch.isfinite(upper)
            send(
                band_seconds=seconds,
                covered=int((inside & seen).sum()),
                scored=int(seen.sum()),
                band_finite=int((finite & seen).sum()),
            )
    except Exception as exc:  # noqa: BLE001 - every exception is a result of the study
        send(exceptions=[_exception(stage, exc)])
    send(default_warnings=_warned(caught))


def sindy_applies(data, fold: dict) -> bool:
    """SINDy (on the derivative samples of the known model's residual) needs every state measured in the training
    data and an autonomous system."""
    return not fold["train"].is_partial and data.system.autonomous


def run_sindy(data, fold: dict, send) -> None:
    """SINDy where it applies (:func:`sindy_applies`): the classical fit's parameters, then pysindy's STLSQ on a
    degree-2 polynomial library fitted to the samples of F = dy/dt - G(y) (central differences; the threshold by
    cross-validation over experiments, :func:`torchmisspec.paper.study_kernels.sindy`), and G + that F integrated
    from the test's start. Its failures are recorded as ``sindy_error``, not as the defaults' exceptions."""
    from .study_kernels import sindy

    if not sindy_applies(data, fold):
        send(sindy_applies=False)
        return
    t0 = time.perf_counter()
    try:
        theta, y0s = classical_fit(data.system, fold["train"], data.noise)
        at = data.system.at(theta)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            samples = tms.correction_samples(fold["train"], at, derivative="central")
            estimate, info = sindy(samples, samples.experiment)

        def known(y):
            x = at.select_inputs(y, None)
            f = estimate(x.detach().reshape(-1, x.shape[-1])).to(y).reshape(*x.shape[:-1], -1)
            return at.known_rhs(y) + at.embed(f)

        model = tms.MisspecifiedSystem(known, at.state_dim, name="sindy")
        with torch.no_grad():
            pred = tms.simulate(model, _start(fold, y0s[0])[None], fold["times"], max_steps=CLASSICAL_MAX_STEPS)
        score = _score(pred.states[0], fold, data.noise)
        send(
            sindy_applies=True, sindy_log_rmse=score, sindy_terms=info["terms"], sindy_seconds=time.perf_counter() - t0
        )
    except Exception as exc:  # noqa: BLE001 - a failure of the baseline is a result of the study
        send(sindy_applies=True, sindy_log_rmse=float("nan"), sindy_error=f"{type(exc).__name__}: {str(exc)[:160]}")


def run_classical(data, fold: dict, send) -> None:
    """The classical answer on one fold (:func:`classical_fit`, then the model alone from the test's start)."""
    stage = "classical fit"
    try:
        t0 = time.perf_counter()
        theta, y0s = classical_fit(data.system, fold["train"], data.noise)
        stage = "classical predict"
        pred = classical_predict(data.system, theta, _start(fold, y0s[0]), fold["times"])
        send(
            classical_log_rmse=_score(pred, fold, data.noise),
            classical_seconds=time.perf_counter() - t0,
            classical_theta=theta.tolist(),
        )
    except Exception as exc:  # noqa: BLE001 - every exception is a result of the study
        send(exceptions=[_exception(stage, exc)])
