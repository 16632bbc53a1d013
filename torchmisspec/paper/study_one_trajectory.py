"""Study: the package's defaults on the one-trajectory protocols of the literature (issue 41).

Two protocols, each one noisy trajectory, each with the package's defaults only (``fit_correction(data, system,
progress=False)``, then ``CorrectedODE(system, gp)``'s ``predict`` and ``posterior(..., num_samples=64)``):

* **UDE Lotka-Volterra** (Rackauckas et al. 2020, "Universal differential equations for scientific machine
  learning"): dx/dt = a x - b x y, dy/dt = c x y - d y, (a, b, c, d) = (1.3, 0.9, 0.8, 1.8), x0 = (0.44249296,
  4.6280594); 31 equally spaced times on [0, 3]; noise 0.05 * mean(|X|) per component times a standard normal,
  added. Known model G: dx/dt = a x, dy/dt = -d y; F = (-b x y, c x y). Forecast to t = 10.
* **GP-ODE Van der Pol** (the one-trajectory protocol of Heinonen et al. 2018, "Learning unknown ODE models with
  Gaussian processes"): dx/dt = y, dy/dt = mu (1 - x^2) y - x, mu = 1, x0 = (-1.5, 2.5); 25 equally spaced times on
  [0, 7], Gaussian noise of variance 0.05. Known model G: the harmonic oscillator dx/dt = y, dy/dt = -x; F = mu (1 -
  x^2) y on the second component. Forecast to t = 21.

Per realization (the noise drawn with the seed): the fit's time, the kernel chosen and whether the known model
alone was kept (``known_model_``); F's relative error over the data's box (the posterior mean of F against the true
F on a 30 x 30 grid over the bounding box of the true trajectory, RMS over the grid); failures of the predictions
inside the data's span (from the first noisy state and from the true initial state: a raise or a non-finite
value); the posterior's time to the forecast horizon, whether its 90 % band is finite and the fraction of the draws
that remained; the RMSE on 20 new initial conditions drawn uniformly from the data's box (fixed seed) over the
data's times, of the corrected model and of G alone against the truth; the forecast from the last true state of the
data window to the horizon, corrected and G alone. Every stage is guarded: an exception is recorded with its stage,
type and message and the realization goes on with the next stage that does not need it.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
import traceback
import warnings

import torch

import torchmisspec as tms
from torchmisspec.benchmarks.reporting import ROOT, machine, run_json, update_benchmarks, write_json, write_page
from torchmisspec.paper.real_data import _warned

DEFAULT_JSON = ROOT / "benchmarks" / "study_one_trajectory.json"
DTYPE = torch.float64
LV = {"a": 1.3, "b": 0.9, "c": 0.8, "d": 1.8}
MU = 1.0
FULL = {"realizations": 10, "num_samples": 64, "grid": 30, "new_conditions": 20, "level": 0.9}
SMOKE = {"realizations": 1, "num_samples": 64, "grid": 30, "new_conditions": 20, "level": 0.9}
#: The seed of the new initial conditions (the same for every realization) and of the posterior's draws.
NEW_SEED, DRAW_SEED = 1234, 0


def lotka_volterra() -> tms.MisspecifiedSystem:
    """The UDE paper's Lotka-Volterra: G the linear growth and decay, F the interaction terms."""
    a, b, c, d = LV["a"], LV["b"], LV["c"], LV["d"]

    def known(y):
        return torch.stack([a * y[..., 0], -d * y[..., 1]], dim=-1)

    def correction(x):
        xy = x[..., 0] * x[..., 1]
        return torch.stack([-b * xy, c * xy], dim=-1)

    return tms.MisspecifiedSystem(known, 2, correction=correction, name="ude_lotka_volterra", state_names=["x", "y"])


def van_der_pol() -> tms.MisspecifiedSystem:
    """Van der Pol with mu = 1: G the harmonic oscillator, F = mu (1 - x^2) y on the second component."""

    def known(y):
        return torch.stack([y[..., 1], -y[..., 0]], dim=-1)

    def correction(x):
        return (MU * (1.0 - x[..., 0] ** 2) * x[..., 1]).unsqueeze(-1)

    return tms.MisspecifiedSystem(
        known, 2, correction=correction, correction_outputs=[1], name="gpode_van_der_pol", state_names=["x", "y"]
    )


def _relative_noise(states: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """The UDE paper's noise: 0.05 * mean(|X|) per component times a standard normal."""
    scale = 0.05 * states.abs().mean(dim=0)
    return scale * torch.randn(states.shape, generator=gen, dtype=DTYPE)


def _variance_noise(states: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Gaussian noise of variance 0.05."""
    return math.sqrt(0.05) * torch.randn(states.shape, generator=gen, dtype=DTYPE)


PROTOCOLS = {
    "ude_lotka_volterra": {
        "system": lotka_volterra,
        "x0": (0.44249296, 4.6280594),
        "span": 3.0,
        "points": 31,
        "horizon": 10.0,
        "noise": _relative_noise,
        "source": "Rackauckas et al. 2020, Universal differential equations for scientific machine learning",
    },
    "gpode_van_der_pol": {
        "system": van_der_pol,
        "x0": (-1.5, 2.5),
        "span": 7.0,
        "points": 25,
        "horizon": 21.0,
        "noise": _variance_noise,
        "source": "Heinonen et al. 2018, Learning unknown ODE models with Gaussian processes (one trajectory)",
    },
}


def _exception(stage: str, exc: BaseException) -> dict:
    frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    where = f"{frame.filename.split('torchmisspec/')[-1]}:{frame.lineno}" if frame else ""
    return {"stage": stage, "type": type(exc).__name__, "message": str(exc)[:400], "where": where}


def _rmse(pred: torch.Tensor, truth: torch.Tensor) -> float:
    return float(((pred - truth) ** 2).mean().sqrt())


def _finite(x: torch.Tensor) -> bool:
    return bool(torch.isfinite(x).all())


def make_data(name: str, seed: int) -> dict:
    """One realization's data: the system, the times, the true and the noisy trajectory, the data's box."""
    p = PROTOCOLS[name]
    system = p["system"]()
    times = torch.linspace(0.0, p["span"], p["points"], dtype=DTYPE)
    x0 = torch.tensor(p["x0"], dtype=DTYPE)
    truth = tms.simulate(system, x0, times).states[0]
    noisy = truth + p["noise"](truth, torch.Generator().manual_seed(seed))
    dense = tms.simulate(system, x0, torch.linspace(0.0, p["span"], 301, dtype=DTYPE)).states[0]
    step = float(times[1] - times[0])
    long = torch.arange(0.0, p["horizon"] + 0.5 * step, step, dtype=DTYPE)
    return {
        "system": system,
        "times": times,
        "x0": x0,
        "truth": truth,
        "noisy": noisy,
        "dense": dense,
        "box": (dense.min(dim=0).values, dense.max(dim=0).values),
        "long": long,
        "ahead": long[long >= p["span"] - 1e-12],
    }


def _fit(data: dict, rec: dict) -> object:
    """``fit_correction`` with its defaults on the one noisy trajectory; what it chose goes into ``rec``."""
    trajectories = tms.Trajectories(data["times"], data["noisy"].unsqueeze(0), state_names=["x", "y"])
    t0 = time.perf_counter()
    gp = tms.fit_correction(trajectories, data["system"], progress=False)
    rec["fit_seconds"] = time.perf_counter() - t0
    rec["kernel"] = repr(getattr(gp, "kernel_spec", None))[:200]
    rec["kernel_name"] = str(getattr(gp, "kernel", None))
    rec["known_model"] = bool(getattr(gp, "known_model_", False))
    rec["derivative"] = str(getattr(gp, "derivative_", None))
    rec["noise_model"] = repr(getattr(gp, "noise_", None))[:120]
    rival = getattr(gp, "one_trajectory_rival_", None)
    rec["rival"] = rival
    rec["rival_kept"] = bool(rival and rival["refined features"] < rival["chosen"])
    cv = getattr(gp, "cross_validation_", None)
    if cv is not None:
        rec["cv"] = {
            "best": cv.best,
            "best_score": float(min(cv.scores)),
            "baseline": float(cv.baseline),
            "folds": int(cv.folds),
            "significant": bool(cv.significant),
            "candidates": dict(zip(cv.candidates, map(float, cv.scores), strict=True)),
        }
    return gp


def _relative(gp, system, x: torch.Tensor) -> float:
    with torch.no_grad():
        mean = gp.predict_mean(x)
    true = system.true_correction(x)
    return float(torch.linalg.norm(mean - true) / torch.linalg.norm(true))


def f_error(data: dict, gp, grid: int) -> float:
    """RMS of (posterior mean of F - true F) on a ``grid`` x ``grid`` grid of the data's box, over the true F's."""
    lo, hi = data["box"]
    axes = [torch.linspace(float(lo[i]), float(hi[i]), grid, dtype=DTYPE) for i in range(2)]
    x = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 2)
    return _relative(gp, data["system"], x)


def f_error_on_path(data: dict, gp) -> float:
    """The same ratio on the true trajectory itself (301 states over the data's span): where the data are."""
    return _relative(gp, data["system"], data["dense"])


def in_span(data: dict, model, rec: dict) -> None:
    """Predictions over the data's times from the first noisy and the true initial state: failures and RMSE."""
    failures, rmse = 0, {}
    for label, y0 in (("noisy_start", data["noisy"][0]), ("true_start", data["x0"])):
        try:
            with torch.no_grad():
                pred = model.predict(y0, data["times"])[0]
            if not _finite(pred):
                failures += 1
            rmse[label] = _rmse(pred, data["truth"])
        except Exception as exc:  # noqa: BLE001 - a failure is a result of the study
            failures += 1
            rec["exceptions"].append(_exception(f"predict in span ({label})", exc))
    rec["span_failures"] = failures
    rec["span_rmse"] = rmse
    known = tms.simulate(data["system"], data["x0"], data["times"], known_only=True).states[0]
    rec["span_rmse_known_true_start"] = _rmse(known, data["truth"])


def band(data: dict, model, cfg: dict, rec: dict) -> None:
    """The posterior from the first noisy state to the horizon: its time, its band's finiteness, what remained."""
    t0 = time.perf_counter()
    with torch.no_grad():
        post = model.posterior(
            data["noisy"][0],
            data["long"],
            num_samples=cfg["num_samples"],
            generator=torch.Generator().manual_seed(DRAW_SEED),
        )
    rec["posterior_seconds"] = time.perf_counter() - t0
    lower, upper = post.interval(cfg["level"])
    finite = torch.isfinite(lower) & torch.isfinite(upper)
    rec["band_finite"] = bool(finite.all())
    rec["band_finite_fraction"] = float(finite.to(DTYPE).mean())
    truth = tms.simulate(data["system"], data["x0"], data["long"]).states[0]
    inside = (truth >= lower[0]) & (truth <= upper[0])
    rec["band_covers_truth"] = float(inside.to(DTYPE).mean())  # NaN band entries count as not covering
    half = inside.shape[0] // 2  # over each half of the horizon (issue 41: bands honest over time)
    rec["band_covers_truth_halves"] = [float(inside[1:half].to(DTYPE).mean()), float(inside[half:].to(DTYPE).mean())]
    region = getattr(post, "region", None)  # a band end at the region's edge: the draws left there, it cannot tell
    edge = None if region is None else ((lower[0] <= region[0]) | (upper[0] >= region[1])) & finite[0]
    rec["band_at_region_edge_halves"] = None if edge is None else [
        float(edge[1:half].to(DTYPE).mean()), float(edge[half:].to(DTYPE).mean())
    ]  # fmt: skip
    remaining = getattr(post, "fraction_remaining", None)
    rec["fraction_remaining"] = None if remaining is None else float(remaining.min())
    rec["band_max_width"] = float((upper - lower)[finite].max()) if bool(finite.any()) else None
    extrapolating = getattr(post, "extrapolating", None)
    rec["extrapolating"] = None if extrapolating is None else bool(torch.as_tensor(extrapolating).any())


def _compare(system, model, y0: torch.Tensor, times: torch.Tensor) -> dict:
    """RMSE against the truth of the corrected model and of G alone from ``y0 (B, d)`` over ``times``."""
    truth = tms.simulate(system, y0, times).states
    out = {}
    with torch.no_grad():
        pred = model.predict(y0, times)
    finite = torch.isfinite(pred).flatten(1).all(dim=1)
    out["corrected_rmse"] = _rmse(pred, truth)
    out["corrected_rmse_finite"] = _rmse(pred[finite], truth[finite]) if bool(finite.any()) else None
    out["corrected_incomplete"] = int((~finite).sum())
    known = tms.simulate(system, y0, times, known_only=True).states
    out["known_rmse"] = _rmse(known, truth)
    return out


def new_conditions(data: dict, model, count: int) -> dict:
    """``count`` initial conditions uniform in the data's box (seed :data:`NEW_SEED`), over the data's times."""
    lo, hi = data["box"]
    u = torch.rand((count, 2), generator=torch.Generator().manual_seed(NEW_SEED), dtype=DTYPE)
    return _compare(data["system"], model, lo + u * (hi - lo), data["times"])


def forecast(data: dict, model) -> dict:
    """From the last true state of the data window to the horizon."""
    return _compare(data["system"], model, data["truth"][-1:], data["ahead"])


def _stage(rec: dict, stage: str, fn, *args):
    """``fn(*args)``, its exception recorded in ``rec`` (None then)."""
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - every exception is a result of the study
        rec["exceptions"].append(_exception(stage, exc))
        return None


def realization(name: str, seed: int, cfg: dict) -> dict:
    """One realization of a protocol: every stage, guarded (a stage that needs a failed one is skipped)."""
    rec: dict = {"seed": seed, "exceptions": []}
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = _stage(rec, "data", make_data, name, seed)
        gp = None if data is None else _stage(rec, "fit_correction", _fit, data, rec)
        if gp is not None:
            rec["f_relative_error"] = _stage(rec, "F error", f_error, data, gp, cfg["grid"])
            rec["f_relative_error_on_path"] = _stage(rec, "F error on the path", f_error_on_path, data, gp)
            model = _stage(rec, "CorrectedODE", tms.CorrectedODE, data["system"], gp)
            if model is not None:
                _stage(rec, "predict in span", in_span, data, model, rec)
                _stage(rec, "posterior", band, data, model, cfg, rec)
                rec["new_conditions"] = _stage(
                    rec, "new conditions", new_conditions, data, model, cfg["new_conditions"]
                )
                rec["forecast"] = _stage(rec, "forecast", forecast, data, model)
    rec["warnings"] = _warned(caught)
    rec["wall_seconds"] = time.perf_counter() - t0
    return rec


#: The summarised quantities: a label and the path into a realization's record.
QUANTITIES = {
    "fit s": ("fit_seconds",),
    "F rel. error (box)": ("f_relative_error",),
    "F rel. error (true path)": ("f_relative_error_on_path",),
    "span failures": ("span_failures",),
    "span RMSE corrected (noisy start)": ("span_rmse", "noisy_start"),
    "span RMSE corrected (true start)": ("span_rmse", "true_start"),
    "span RMSE G alone (true start)": ("span_rmse_known_true_start",),
    "posterior s": ("posterior_seconds",),
    "band finite": ("band_finite",),
    "fraction remaining (min)": ("fraction_remaining",),
    "band covers truth (fraction)": ("band_covers_truth",),
    "band covers truth, first half of the horizon": ("band_covers_truth_halves", 0),
    "band covers truth, second half of the horizon": ("band_covers_truth_halves", 1),
    "band at the region's edge, first half (fraction)": ("band_at_region_edge_halves", 0),
    "band at the region's edge, second half (fraction)": ("band_at_region_edge_halves", 1),
    "new ICs RMSE corrected": ("new_conditions", "corrected_rmse"),
    "new ICs RMSE G alone": ("new_conditions", "known_rmse"),
    "new ICs incomplete": ("new_conditions", "corrected_incomplete"),
    "forecast RMSE corrected": ("forecast", "corrected_rmse"),
    "forecast RMSE G alone": ("forecast", "known_rmse"),
}


def _get(rec: dict, path: tuple) -> float | None:
    value = rec
    for key in path:
        if isinstance(key, int):  # a position in a list (the halves of the horizon)
            value = value[key] if isinstance(value, list) and key < len(value) else None
        else:
            value = value.get(key) if isinstance(value, dict) else None
    if isinstance(value, bool):
        return float(value)
    return float(value) if isinstance(value, (int, float)) else None


def summary(runs: list[dict]) -> dict:
    """Per quantity over the realizations: median, min, max, the number with a finite value and without one."""
    out: dict = {}
    for label, path in QUANTITIES.items():
        values = [_get(r, path) for r in runs]
        good = [v for v in values if v is not None and math.isfinite(v)]
        out[label] = {
            "median": statistics.median(good) if good else None,
            "min": min(good) if good else None,
            "max": max(good) if good else None,
            "count": len(good),
            "missing": len(values) - len(good),
        }
    kernels: dict = {}
    for r in runs:
        key = "known model alone" if r.get("known_model") else r.get("kernel_name")
        if r.get("rival_kept"):  # the refined feature kernel won the held-out last piece over the pieces' choice
            key = f"{key} (refined; the pieces chose {(r.get('cv') or {}).get('best')})"
        key = "fit failed" if key is None else str(key)
        kernels[key] = kernels.get(key, 0) + 1
    out["kernels"] = kernels
    out["significant"] = sum(bool((r.get("cv") or {}).get("significant")) for r in runs)
    out["exceptions"] = sum(len(r["exceptions"]) for r in runs)
    return out


def _log(text: str) -> None:
    print(text, flush=True)


def study(cfg: dict, log=_log) -> dict:
    """Every realization of every protocol, one after the other in this process."""
    torch.set_num_threads(1)
    runs: dict = {}
    for name in cfg.get("protocols") or list(PROTOCOLS):
        runs[name] = []
        for seed in range(cfg["realizations"]):
            rec = realization(name, seed, cfg)
            runs[name].append(rec)
            log(f"{name} seed {seed}: {_line(rec)}")
    about = {
        name: {k: v for k, v in PROTOCOLS[name].items() if k not in ("system", "noise")}
        | {"noise": PROTOCOLS[name]["noise"].__doc__}
        for name in runs
    }
    summaries = {name: summary(r) for name, r in runs.items()}
    return {"config": cfg, "protocols": about, "runs": runs, "summary": summaries}


def _fmt(x, spec: str = ".3g") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _line(rec: dict) -> str:
    nc, fc = rec.get("new_conditions") or {}, rec.get("forecast") or {}
    errors = "; ".join(f"{e['stage']}: {e['type']}" for e in rec["exceptions"]) or "none"
    return (
        f"fit {_fmt(rec.get('fit_seconds'), '.1f')} s, {(rec.get('cv') or {}).get('best', rec.get('kernel_name'))}, "
        f"known {rec.get('known_model')}, "
        f"F err {_fmt(rec.get('f_relative_error'))}, span failures {rec.get('span_failures')}, "
        f"posterior {_fmt(rec.get('posterior_seconds'), '.1f')} s finite {rec.get('band_finite')}, "
        f"new ICs {_fmt(nc.get('corrected_rmse'))} vs G {_fmt(nc.get('known_rmse'))}, "
        f"forecast {_fmt(fc.get('corrected_rmse'))} vs G {_fmt(fc.get('known_rmse'))}; exceptions: {errors}"
    )


def table(result: dict) -> str:
    """Median [min, max] per protocol and quantity, then the kernels chosen."""
    summaries = {name: summary(runs) for name, runs in result["runs"].items()}  # a saved run's too, as measured
    names = list(summaries)
    lines = ["| quantity | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for label in QUANTITIES:
        cells = []
        for name in names:
            s = summaries[name][label]
            cells.append(f"{_fmt(s['median'])} [{_fmt(s['min'])}, {_fmt(s['max'])}] (n={s['count']})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for name in names:
        s = summaries[name]
        lines.append(
            f"\n{name}: chosen {s['kernels']}; significant gain over G in {s['significant']}; "
            f"exceptions {s['exceptions']}"
        )
    return "\n".join(lines) + "\n"


def run(args) -> int:
    """The command line's run: the study (or ``--from-json``), its JSON and its table."""
    if args.saved is not None:
        result = args.saved
    else:
        cfg = dict(SMOKE if args.smoke else FULL)
        if getattr(args, "realizations", None):
            cfg["realizations"] = args.realizations
        if getattr(args, "protocols", None):
            unknown = sorted(set(args.protocols) - set(PROTOCOLS))
            if unknown:
                args.parser.error(f"--protocols: unknown {unknown}; expected among {list(PROTOCOLS)}")
            cfg["protocols"] = list(args.protocols)
        t0 = time.perf_counter()
        result = study(cfg)
        result.update(
            machine=machine(),
            wall_seconds=time.perf_counter() - t0,
            smoke=args.smoke,
            command=" ".join(["python", *sys.argv]),
        )
        write_json(result, run_json(args, DEFAULT_JSON))
    print(table(result))
    if args.markdown:
        write_page(DOC_PAGE, render_page(result))
        update_benchmarks(render_block(result), MARK_START, MARK_END)
        print(f"wrote {DOC_PAGE} and the one-trajectory block of BENCHMARKS.md")
    return 0


DOC_PAGE = ROOT / "docs" / "studies" / "one-trajectory.md"
MARK_START, MARK_END = "<!-- study:one-trajectory:start -->", "<!-- study:one-trajectory:end -->"


def _header(result: dict) -> str:
    info = result.get("machine") or {}
    return (
        f"Written by `{result.get('command', 'python scripts/study_one_trajectory.py --markdown')}` on "
        f"{info.get('cpu', '?')}, {info.get('logical_cpus', '?')} logical CPUs, torch {info.get('torch', '?')}, commit "
        f"{info.get('git_commit', '?')}; wall time {result.get('wall_seconds', float('nan')) / 60:.1f} min; "
        f"{result['config']['realizations']} realizations per protocol (seeds 0 ..), median [min, max] (n: "
        "realizations with a value)."
    )


def render_page(result: dict) -> str:
    """The docs page: the protocols, then the table of :func:`table`, every number from ``result``."""
    about = "\n".join(
        f"- **{name}**: {p['points']} times on [0, {p['span']:g}], forecast to t = {p['horizon']:g}; {p['noise']} "
        f"Source: {p['source']}."
        for name, p in result["protocols"].items()
    )
    return f"""# Study: one trajectory (the UDE and GP-ODE papers' protocols)

{_header(result)} Raw numbers: `benchmarks/study_one_trajectory.json`.

{__doc__.split(chr(10), 2)[2].strip()}

## Protocols

{about}

## Results

{table(result)}
Goals (issue 41): no prediction failure inside the data's span, bands within 20 s, errors on new initial conditions
and forecasts no worse than G alone; on the UDE Lotka-Volterra protocol F's relative error over the data's box
<= 0.1 (median); the 90 % band's coverage in [0.80, 0.97] over each half of the horizon. A band end at the
region's edge (the draws that left the region are counted at the edge they crossed, and where more than the band's
tail left, the band reaches it): there the band covers the truth because it cannot tell where the state is, so read
the coverage with the fraction of the band at the region's edge beside it.
"""


def render_block(result: dict) -> str:
    """The block of BENCHMARKS.md."""
    return f"""{MARK_START}
## One trajectory: the UDE and GP-ODE protocols (`scripts/study_one_trajectory.py`)

{_header(result)} See [docs/studies/one-trajectory.md](docs/studies/one-trajectory.md).

{table(result)}{MARK_END}
"""
