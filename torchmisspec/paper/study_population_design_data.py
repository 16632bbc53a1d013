"""Study of issue 43 (item 3) on real data: the next subject's 4 sampling times, designed, on three public
population data sets.

On real data the truth is not known, but subjects measured at every one of a data set's times let every choice of 4
of them be scored against what the subject's own data say. Three of R's data sets
(:func:`torchmisspec.datasets.load`), with the model a scientist writes, relative errors, every parameter log-normal
between subjects:

* ``datasets::Theoph`` (Boeckmann, Sheiner & Beal 1994): 12 subjects given an oral dose of theophylline, the plasma
  concentration measured 11 times over 25 h (at about 0, 0.25, 0.5, 1, 2, 3.5, 5, 7, 9, 12 and 24 h); the
  one-compartment model with first-order absorption, ka, ke and V; every subject left out in turn;
* ``datasets::ChickWeight`` (Crowder & Hand 1990): 50 chicks weighed 12 times over 21 days; logistic growth, r and K;
  the first 12 chicks weighed on every day left out in turn (each against the other 49);
* ``datasets::Orange``: 5 orange trees, their trunk circumference at 7 ages; logistic growth, r and K; every tree
  left out in turn (each against the other 4).

The other subjects are fitted (:func:`~torchmisspec.population.fit.fit_population`, defaults). The left-out
subject's 4 sampling times are then chosen among its own measured times after the first:

* **designed**: :func:`~torchmisspec.population.design.design_subject` for the subject's own parameters, defaults,
  from its first measured state (a dose, a chick's or a tree's first size); the design sees the population only,
  never the subject's later measurements;
* **standard**: the first 4 of those times (theophylline's 0.25, 0.5, 1 and 2 h);
* **random**: every set of 4 (210 for theophylline, 330 for a chick, 15 for a tree): the exact expectation of a set
  drawn at random; also the best of them in hindsight and the designed set's rank among them.

Each set of 4 measurements gives the subject's parameters by empirical Bayes under the population fit
(:func:`~torchmisspec.population.predict.subjects_parameters`, every set in one batched fit), scored two ways:

* **parameters**: the RMS over the varying parameters of the difference from the subject's estimate from all its
  measurements (the same fit), in units of the population's fitted spread;
* **path**: the log-RMSE of the subject's path predicted from those parameters (G + F's mean, from its first state)
  against all its measurements after the first (the 4 used among them: every rule uses 4).

Per subject the ratio of the rule's error to the standard's and to the random expectation; the table gives their
geometric mean over the subjects of each data set and its spread.
"""

from __future__ import annotations

import itertools
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec import datasets
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.population import Population
from torchmisspec.population._subjects import drawn_controls
from torchmisspec.population.design import design_subject
from torchmisspec.population.fit import fit_population
from torchmisspec.population.predict import _paths, subjects_parameters

from ._ratios import describe, paired_ratio
from .study_population_data import _by_set  # the runs of each data set, as that study groups them

DEFAULT_JSON = ROOT / "benchmarks" / "study_population_design_data.json"
DOC_PAGE = ROOT / "docs" / "studies" / "population-design-real-data.md"
MARK_START = "<!-- study:population-design-data:start -->"
MARK_END = "<!-- study:population-design-data:end -->"
DT = torch.float64
BUDGET = 4
#: the data sets and the state each scores
SETS = {"theoph": "conc", "chickweight": "weight", "orange": "circumference"}
FULL = {"subjects": {"theoph": 12, "chickweight": 12, "orange": 5}}
SMOKE = {"subjects": {"theoph": 1}}
GOALS = {"ratio": 0.8}
SCORES = ("parameters", "path")


def _scores(fit, t: torch.Tensor, y: torch.Tensor, sets: list[tuple[int, ...]], names, c: int) -> dict:
    """Each set's parameter error against the subject's all-data estimate (in spreads) and the log-RMSE of its
    predicted state ``c`` at every measured time after the first."""
    X = torch.zeros(1, 0, dtype=DT)
    rows = torch.tensor([[0, *s] for s in sets])
    reference, _, _ = subjects_parameters(fit, tms.Trajectories(t, y[None], state_names=names), X)
    eta, _, y0 = subjects_parameters(fit, tms.Trajectories(t[rows], y[rows], state_names=names), X)
    spread = fit.nlme.values.spread
    parameters = ((eta - reference) / spread).pow(2).mean(-1).sqrt()
    nlme = fit.nlme
    controls = drawn_controls(fit.system, nlme.layout, eta, nlme.modes.shared, t[:1])
    paths = _paths(fit, y0, t, controls)[:, 1:, c]  # (N, T - 1)
    seen = torch.isfinite(y[1:, c])
    logs = paths.clamp_min(1e-6).log() - y[1:, c].log()
    path = logs[:, seen].pow(2).mean(-1).sqrt()
    return {"parameters": parameters, "path": path}


def left_out(name: str, count: int) -> list[int]:
    """The first ``count`` subjects of data set ``name`` measured at every one of its times (each left out in
    turn: every set of their times can be scored)."""
    lengths = [len(t) for t, _ in datasets.load(name).trajectories.experiments()]
    return [k for k, n in enumerate(lengths) if n == max(lengths)][:count]


def run_one(task: tuple[str, int, dict]) -> dict:
    name, k, cfg = task
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    data = datasets.load(name)
    trajs, system = data.trajectories, data.system
    train = trajs[[i for i in range(trajs.num_experiments) if i != k]]
    t, y = trajs.experiments()[k]
    t0 = time.perf_counter()
    fit = fit_population(train, system, Population(list(system.parameters.names)), noise=data.noise, progress=False)
    out = {"set": name, "subject": k + 1, "fit_seconds": time.perf_counter() - t0, "known_model": fit.known_model}
    design = design_subject(
        fit, t, BUDGET, initial_states=y[0].nan_to_num(0.0), generator=torch.Generator().manual_seed(k)
    )
    designed = tuple(int((t - s).abs().argmin()) for s in design.times)
    sets = list(itertools.combinations(range(1, len(t)), BUDGET))
    t1 = time.perf_counter()
    scores = _scores(fit, t, y, sets, trajs.state_names, list(trajs.state_names).index(SETS[name]))
    out["score_seconds"] = time.perf_counter() - t1
    arms = {"designed": sets.index(designed), "standard": sets.index(tuple(range(1, 1 + BUDGET)))}
    for name, i in arms.items():
        out[f"{name}_times"] = [float(t[j]) for j in sets[i]]
    for what, values in scores.items():
        for name, i in arms.items():
            out[f"{name}_{what}"] = float(values[i])
        out[f"random_{what}"] = float(values.mean())
        best = int(values.argmin())
        out[f"best_{what}"], out[f"best_{what}_times"] = float(values[best]), [float(t[j]) for j in sets[best]]
        out[f"designed_{what}_rank"] = int((values < values[arms["designed"]]).sum()) + 1
    out["sets"] = len(sets)
    return out


def study(cfg: dict, log=print, executor=None) -> dict:
    from torchmisspec.parallel import map_tasks

    tasks = [(name, k, cfg) for name, count in cfg["subjects"].items() for k in left_out(name, count)]
    runs = map_tasks(run_one, tasks, executor=executor)
    for r in runs:
        log(
            f"{r.get('set', 'theoph')} subject {r['subject']}: designed {r['designed_times']} parameters "
            f"{r['designed_parameters']:.3f} (standard {r['standard_parameters']:.3f}, random "
            f"{r['random_parameters']:.3f}, rank "
            f"{r['designed_parameters_rank']} of {r['sets']}); path {r['designed_path']:.3f} (standard "
            f"{r['standard_path']:.3f}, random {r['random_path']:.3f}); fit {r['fit_seconds']:.1f} s"
        )
    return {"config": cfg, "runs": runs, "goals": GOALS}


def _ratio(runs, arm: str, other: str, what: str) -> str:
    return describe(paired_ratio([r[f"{arm}_{what}"] for r in runs], [r[f"{other}_{what}"] for r in runs]))


def _rows(name: str, runs: list[dict]) -> list[str]:
    goal, lines = f"<= {GOALS['ratio']}", []
    # the goal is the subject's parameters' (issue 43); the path is what a user sees of them
    for what, label, aim in (("parameters", "parameters", goal), ("path", "path (log-RMSE)", "")):
        lines += [
            f"| {name}: {label}, designed / standard first 4 | {_ratio(runs, 'designed', 'standard', what)} | {aim} |",
            f"| {name}: {label}, designed / random 4 (every set's mean) | {_ratio(runs, 'designed', 'random', what)} "
            f"| {aim} |",
            f"| {name}: {label}, the best set in hindsight / random 4 | {_ratio(runs, 'best', 'random', what)} | |",
        ]
    ranks = sorted(r["designed_parameters_rank"] for r in runs)
    lines.append(f"| {name}: the designed set's rank among the {runs[0]['sets']} sets (parameters), per subject | "
                 f"{', '.join(map(str, ranks))} | |")  # fmt: skip
    lines.append(
        f"| {name}: a correction kept (F not 0) | {sum(not r['known_model'] for r in runs)} of {len(runs)} | |"
    )
    return lines


def table(result: dict) -> str:
    lines = ["| measure | value | goal |", "|---|---|---|"]
    for name, runs in _by_set(result).items():
        lines += _rows(name, runs)
    return "\n".join(lines) + "\n"


def per_subject(result: dict) -> str:
    lines = [
        "| data | subject | designed times | parameters: designed / standard / random / best | rank | path: designed "
        "/ standard / random / best | fit s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        times = ", ".join(f"{t:g}" for t in r["designed_times"])
        par = " / ".join(f"{r[a + '_parameters']:.3f}" for a in ("designed", "standard", "random", "best"))
        path = " / ".join(f"{r[a + '_path']:.3f}" for a in ("designed", "standard", "random", "best"))
        lines.append(
            f"| {r.get('set', 'theoph')} | {r['subject']} | {times} | {par} | {r['designed_parameters_rank']} | {path} "
            f"| {r['fit_seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""{MARK_START}
## The next subject's sampling times on real data (`scripts/study_population_design_data.py`)

Written by `python scripts/study_population_design_data.py --markdown` ({wall / 60:.1f} min, {info["cpu"]},
{info["logical_cpus"]} logical CPUs): subjects of R's Theoph, ChickWeight and Orange left out in turn, each one's 4
sampling times designed among its own measured times against the first 4 and every set of 4; see
[docs/studies/population-design-real-data.md](docs/studies/population-design-real-data.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""# Study: the next subject's sampling times on real data

This page is written by `python scripts/study_population_design_data.py --markdown`; every number on it comes from
that run (raw numbers: `benchmarks/study_population_design_data.json`). Machine: {info["cpu"]},
{info["logical_cpus"]} logical CPUs, torch {info["torch"]}, commit {info["git_commit"]}; wall time
{wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
{per_subject(result)}"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
