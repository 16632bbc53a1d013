"""Study of issue 43 on real data: a new subject predicted from its first 2 measurements (theophylline, and two
tree-growth populations).

Three of R's population data sets, each with the model a scientist writes (:func:`torchmisspec.datasets.load`),
relative errors, every uncertain parameter varying between subjects:

* ``datasets::Theoph`` (Boeckmann, Sheiner & Beal 1994): 12 subjects given an oral dose of theophylline (mg/kg), the
  plasma concentration measured 11 times over 25 h, the dose in the gut at t = 0 and never measured after; the
  one-compartment model with first-order absorption, ka, ke and V;
* ``datasets::Loblolly``: 14 loblolly pines, their height measured at 6 ages from 3 to 25 years; the growth model
  the data set ships with, its two parameters;
* ``datasets::Orange``: 5 orange trees, their trunk circumference at 7 ages; logistic growth, r and K.

Each subject in turn is left out; the others are fitted, and the subject is predicted from its first 2
measurements (for theophylline the dose and its concentration at t = 0, and the concentration at 0.25-0.6 h): its
remaining measurements of the scored state (concentration, height, circumference) are scored by the RMSE of their
logs.

Methods, on the same folds:

* **the package**: :func:`~torchmisspec.population.fit.fit_population`, the parameters log-normal between subjects
  (defaults otherwise), then :func:`~torchmisspec.population.predict.predict_subject` with the first 2
  measurements (empirical Bayes);
* **the classical answer**: the same population model with F = 0 (the nonlinear mixed-effects model of the known
  model, ``result.classical``), predicted the same way;
* **one set of parameters**: the package's defaults before populations (``fit_correction`` on the other subjects,
  one set of parameters for all), predicted from the subject's first row;
* **the subject alone**: the known model fitted to the subject's own first 2 measurements, its priors as the only
  other information.

Also recorded: the 90 % band of new measurements of the package's prediction and whether it holds the held-out
values, calibrated on the other subjects (:mod:`torchmisspec.population.calibration`, the default) and not, the
calibration's scale; the same for the band from the population alone (the subject's first row's state, every later
measurement scored; the textbook prediction interval when uncalibrated); and the wall time of each population fit
with its calibrations (the speed goal: theophylline's 12 subjects, all of them).
"""

from __future__ import annotations

import math
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec import datasets
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.learning.refinement._known_fit import fit_known_model
from torchmisspec.noise import as_noise_model
from torchmisspec.population import Population
from torchmisspec.population.fit import fit_population
from torchmisspec.population.predict import predict_subject

from ._ratios import describe, paired_ratio

DEFAULT_JSON = ROOT / "benchmarks" / "study_population_data.json"
DOC_PAGE = ROOT / "docs" / "studies" / "population-real-data.md"
MARK_START = "<!-- study:population-data:start -->"
MARK_END = "<!-- study:population-data:end -->"
DT = torch.float64
#: the data sets and the state each scores
SETS = {"theoph": "conc", "loblolly": "height", "orange": "circumference"}
FULL = {"subjects": {"theoph": 12, "loblolly": 14, "orange": 5}, "num_samples": 64}
SMOKE = {"subjects": {"theoph": 1}, "num_samples": 8}
FIRST = 2
GOALS = {"vs_classical": 1.0, "seconds": 30.0}


def _log_rmse(pred: torch.Tensor, values: torch.Tensor) -> float:
    seen = torch.isfinite(values)
    if not bool(torch.isfinite(pred[seen]).all()):
        return math.nan
    return float((pred[seen].clamp_min(1e-6).log() - values[seen].log()).pow(2).mean().sqrt())


def run_one(task: tuple[str, int, dict]) -> dict:
    name, k, cfg = task
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    data = datasets.load(name)
    trajs, system = data.trajectories, data.system
    c = list(trajs.state_names).index(SETS[name])
    train = trajs[[i for i in range(trajs.num_experiments) if i != k]]
    t, y = trajs.experiments()[k]
    first = tms.Trajectories(t[:FIRST], y[:FIRST][None], state_names=trajs.state_names)
    held = y[FIRST:, c]
    t0 = time.perf_counter()
    fit = fit_population(train, system, Population(list(system.parameters.names)), noise=data.noise, progress=False)
    out = {"set": name, "subject": k + 1, "fit_seconds": time.perf_counter() - t0, "known_model": fit.known_model}
    g = torch.Generator().manual_seed(k)
    for method, model in (("package", fit), ("classical", fit.as_classical())):
        pred = predict_subject(model, None, t, first=first, num_samples=cfg["num_samples"], generator=g)
        out[method] = _log_rmse(pred.posterior.mean_path[0, FIRST:, c], held)
    for key, calibrated in (("covered", True), ("covered_uncalibrated", False)):
        pred = predict_subject(
            fit, None, t, first=first, num_samples=cfg["num_samples"], generator=g, calibrated=calibrated
        )
        band = pred.posterior.measured(fit.noise, fit.nlme.modes.scale, generator=g).interval(0.9)
        inside = (held >= band[0][0, FIRST:, c]) & (held <= band[1][0, FIRST:, c])
        out[key], out["scored"] = int(inside.sum()), int(held.numel())
    out.update(_alone_covered(fit, trajs.initial_conditions[k], t, y[1:, c], c, cfg, g))
    cal = fit.calibration
    out["band_scale"] = None if cal is None else cal.scale
    out["f_draws"] = None if cal is None else cal.f_draws
    gp = tms.fit_correction(train, system, noise=data.noise, progress=False)
    pooled = tms.CorrectedODE(system.at(gp.parameters_.mean), gp).predict(y[0][None].nan_to_num(0.0), t)[0]
    out["one_set"] = _log_rmse(pooled[FIRST:, c], held)
    noise = as_noise_model(data.noise, first)
    alone = fit_known_model(system, first, torch.zeros(1, y.shape[-1], dtype=torch.bool), noise)
    path = tms.simulate(system.at(alone.theta), y[0][None], t, rtol=1e-7, atol=1e-9).states[0]
    out["alone"] = _log_rmse(path[FIRST:, c], held)
    return out


def _alone_covered(fit, y0: torch.Tensor, t: torch.Tensor, later: torch.Tensor, c: int, cfg: dict, g) -> dict:
    """How many of the subject's measurements after its first row lie in the 90 % band of new measurements from the
    population alone (its first row's state), calibrated on the other subjects and not."""
    out = {"alone_scored": int(torch.isfinite(later).sum())}
    for key, calibrated in (("alone_covered", True), ("alone_covered_uncalibrated", False)):
        pred = predict_subject(fit, y0, t, num_samples=cfg["num_samples"], generator=g, calibrated=calibrated)
        lo, hi = pred.posterior.measured(fit.noise, fit.nlme.modes.scale, generator=g).interval(0.9)
        out[key] = int(((later >= lo[0, 1:, c]) & (later <= hi[0, 1:, c])).sum())
    cal = fit.calibration_alone
    out["alone_band_scale"] = None if cal is None else cal.scale
    return out


def _all_subjects_seconds() -> float:
    data = datasets.load("theoph")
    t0 = time.perf_counter()
    fit_population(data.trajectories, data.system, Population(["ka", "ke", "V"]), noise=data.noise, progress=False)
    return time.perf_counter() - t0


def study(cfg: dict, log=print, executor=None) -> dict:
    from torchmisspec.parallel import map_tasks

    tasks = [(name, k, cfg) for name, count in cfg["subjects"].items() for k in range(count)]
    runs = map_tasks(run_one, tasks, executor=executor)
    for r in runs:
        log(
            f"{r['set']} subject {r['subject']}: package {r['package']:.3f}, classical {r['classical']:.3f}, one set "
            f"{r['one_set']:.3f}, alone {r['alone']:.3f}; {r['fit_seconds']:.1f} s"
        )
    torch.set_num_threads(1)
    seconds = _all_subjects_seconds()
    log(f"all 12 subjects, 3 varying parameters: {seconds:.1f} s")
    return {"config": cfg, "runs": runs, "all_subjects_seconds": seconds, "goals": GOALS}


def _by_set(result: dict) -> dict[str, list[dict]]:
    """The runs of each data set (a run from before several sets is theophylline's)."""
    out: dict[str, list[dict]] = {}
    for r in result["runs"]:
        out.setdefault(r.get("set", "theoph"), []).append(r)
    return out


def _rows(name: str, runs: list[dict]) -> list[str]:
    n, pkg = len(runs), [r["package"] for r in runs]
    covered = sum(r["covered"] for r in runs) / max(sum(r["scored"] for r in runs), 1)
    return [
        f"| {name}: package / classical log-RMSE (geometric mean over {n} subjects) | "
        f"{describe(paired_ratio(pkg, [r['classical'] for r in runs]))} | <= {GOALS['vs_classical']} |",
        f"| {name}: package / one set of parameters | {describe(paired_ratio(pkg, [r['one_set'] for r in runs]))} | |",
        f"| {name}: package / the subject alone | {describe(paired_ratio(pkg, [r['alone'] for r in runs]))} | |",
        f"| {name}: held-out measurements in the package's 90 % band (calibrated on the other subjects) | "
        f"{covered:.2f} | 0.9 |",
        f"| {name}: the same, the band uncalibrated | {_share(runs, 'covered_uncalibrated')} | |",
        f"| {name}: the calibration's scale (median; F's draws kept in the band) | {_scales(runs)} | |",
        f"| {name}: from the population alone (its first row's state), held-out measurements in the 90 % band "
        f"(calibrated) | {_share(runs, 'alone_covered', 'alone_scored')} | 0.9 |",
        f"| {name}: the same, the band uncalibrated (the textbook prediction interval) | "
        f"{_share(runs, 'alone_covered_uncalibrated', 'alone_scored')} | |",
        f"| {name}: the population-alone calibration's scale (median) | "
        f"{_scales(runs, 'alone_band_scale', f_draws=False)} | |",
        f"| {name}: a correction kept (F not 0) | {sum(not r['known_model'] for r in runs)} of {n} | |",
    ]


def _share(runs: list[dict], key: str, scored: str = "scored") -> str:
    """The share of the held-out measurements (``scored``) in the bands of ``key`` (a run from before it: not
    measured)."""
    if any(key not in r for r in runs):
        return "not measured"
    return f"{sum(r[key] for r in runs) / max(sum(r[scored] for r in runs), 1):.2f}"


def _scales(runs: list[dict], key: str = "band_scale", *, f_draws: bool = True) -> str:
    """The calibration's median scale (``key``) with its range, and (``f_draws``) how often the band kept F's
    draws."""
    found = [r for r in runs if r.get(key) is not None]
    if not found:
        return "not measured"
    scales = sorted(r[key] for r in found)
    median = f"{scales[len(scales) // 2]:.2f} [{scales[0]:.2f}, {scales[-1]:.2f}]"
    if not f_draws:
        return median
    return f"{median}; {sum(bool(r['f_draws']) for r in found)} of {len(found)}"


def table(result: dict) -> str:
    rows = ["| measure | value | goal |", "|---|---|---|"]
    for name, runs in _by_set(result).items():
        rows += _rows(name, runs)
    rows.append(
        f"| one population fit, theophylline's 12 subjects x 11 times, 3 varying parameters (s) | "
        f"{result['all_subjects_seconds']:.1f} | <= {GOALS['seconds']:.0f} |"
    )
    return "\n".join(rows) + "\n"


def per_subject(result: dict) -> str:
    lines = ["| data | subject | package | classical | one set | alone | in band | fit s |", "|---" * 8 + "|"]
    for name, runs in _by_set(result).items():
        for r in runs:
            lines.append(
                f"| {name} | {r['subject']} | {r['package']:.3f} | {r['classical']:.3f} | {r['one_set']:.3f} | "
                f"{r['alone']:.3f} | {r['covered']} of {r['scored']} | {r['fit_seconds']:.1f} |"
            )
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""{MARK_START}
## A new subject from its first 2 measurements: real populations (`scripts/study_population_data.py`)

Written by `python scripts/study_population_data.py --markdown` ({wall / 60:.1f} min, {info["cpu"]},
{info["logical_cpus"]} logical CPUs): each subject of R's Theoph, Loblolly and Orange left out in turn; see
[docs/studies/population-real-data.md](docs/studies/population-real-data.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""# Study: a new subject from its first 2 measurements (real populations)

This page is written by `python scripts/study_population_data.py --markdown`; every number on it comes from that run
(raw numbers: `benchmarks/study_population_data.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs,
torch {info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min. The log-RMSE of each subject's
held-out measurements:

{__doc__.strip()}

{table(result)}
{per_subject(result)}"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
