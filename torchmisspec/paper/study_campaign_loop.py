"""Study of issue 42, item 1: one round of the README's design loop keeps the model it started from.

The system is one the package does not ship: an oscillator whose lab model is the linear damped spring
(dx/dt = v, dv/dt = -k x - c v) while the truth's spring hardens, a term missing from dv/dt: ``cubic``, -eps x^3 (a
monomial the feature kernel holds), or ``saturating``, -eps x^3 / (1 + x^2) (none does); the correction is declared
on (x, v) with one output (dv/dt). Each realization is a lab's CSV of 8 experiments (21 times on [0, 6], noise of
standard deviation 0.02 on both states, initial states uniform in [-2, 2]^2). Then the README's loop, defaults
only:

``fit_correction`` -> ``Campaign(system, grid 13 x 13, times, gp)`` -> ``tell(observed)`` (what is known
already) -> ``ask(3)`` -> the 3 experiments run on the truth with the same noise -> ``tell``.

Reported per realization: the trajectory RMSE against the truth on 20 new initial states in [-2, 2]^2 (21 times on
[0, 6]) of the fit and of the campaign's model after the round, their ratio (issue 42's floor: within 1.05 in at
least 9 of 10), whether the round failed, whether the model holds each sample once (its training inputs are all
distinct and as many as fit_correction's own on the 11 experiments), and the same round with the campaign's former
rule as the peer (the samples added to the fit's and the GP refitted by marginal likelihood: a campaign started from
a GP that does not carry its data, which is what every campaign did before).

The parametric oracle is the peer that shows what the floor asks of any fit: the truth's own form with its one
coefficient eps fitted by least squares through the ODE (initial states free), on the lab's 8 experiments and then on
the campaign's 11, scored on the same new states. Its ratio is a property of the data, not of the package: an
estimate near the truth's coefficient by chance moves when three more noisy experiments are added, even when they
are informative, and the ratio of two small errors is then far above 1.

Where the round ends above 1.05x with the cubic truth, the fit it started from was nearly exact (the feature kernel
found -eps x^3 to a fraction of its posterior standard deviation), and the three corner experiments the design asks
for move the coefficient by about half a standard deviation or keep a spurious term within about one: a direct fit of
the 11 experiments gives the same model. With the saturating truth the cross-validation's lengthscale moves with
the corner experiments. The refined feature kernel as a rival of the choice (as for one trajectory) fixed one
realization and cost 15-60 s per fit; it is not in the package (CHANGELOG).
"""

from __future__ import annotations

import csv
import tempfile
import time
import warnings
from pathlib import Path

import torch

import torchmisspec as tms
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.paper.oracle import fitted_through_ode
from torchmisspec.parallel import map_tasks

DEFAULT_JSON = ROOT / "benchmarks" / "study_campaign_loop.json"
DOC_PAGE = ROOT / "docs" / "studies" / "campaign-loop.md"
MARK_START = "<!-- study:campaign-loop:start -->"
MARK_END = "<!-- study:campaign-loop:end -->"
DT = torch.float64
SEED = 42_000
K_SPRING, DAMPING, EPS = 1.0, 0.2, 0.3
#: The measurement noise's standard deviation (the states span about -3 to 3).
NOISE = 0.02
FULL = {"realizations": 10, "n_test": 20}
SMOKE = {"realizations": 1, "n_test": 5}
#: Issue 42's floor: the error after one round within this factor of the fit's, in at least 9 of 10 realizations.
RATIO_GOAL, SHARE_GOAL = 1.05, 0.9
BOX = [(-2.0, 2.0), (-2.0, 2.0)]


def known(y: torch.Tensor) -> torch.Tensor:
    """The lab's model: a linear damped spring."""
    return torch.stack([y[..., 1], -K_SPRING * y[..., 0] - DAMPING * y[..., 1]], dim=-1)


def cubic(x: torch.Tensor) -> torch.Tensor:
    """A hardening spring's missing term on dv/dt: -eps x^3 (one of the feature kernel's monomials)."""
    return -EPS * x[..., :1] ** 3


def saturating(x: torch.Tensor) -> torch.Tensor:
    """A spring that hardens and saturates: -eps x^3 / (1 + x^2) (no finite sum of monomials)."""
    y = x[..., :1]
    return -EPS * y**3 / (1 + y**2)


#: The truths' missing terms, by the name the study reports.
MISSING = {"cubic": cubic, "saturating": saturating}


def system(with_truth: bool, truth: str = "cubic") -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        known, 2, correction=MISSING[truth] if with_truth else None, correction_inputs=[0, 1],
        correction_outputs=[1], domain=BOX, name="duffing_lab",
    )  # fmt: skip


def noisy(states: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """The lab's instrument: errors of one size (NOISE) whatever the state, as for a position and a velocity."""
    return states + NOISE * torch.randn(states.shape, generator=g, dtype=DT)


def write_lab_csv(path: Path, times: torch.Tensor, g: torch.Generator, truth: str) -> None:
    y0 = tms.design.candidates.uniform_box(8, BOX, generator=g)
    states = noisy(tms.simulate(system(True, truth), y0, times).states, g)
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["run", "t", "x", "v"])
        for k in range(states.shape[0]):
            for t, row in zip(times.tolist(), states[k].tolist(), strict=True):
                out.writerow([f"run{k + 1}", f"{t:.4f}", *(f"{v:.6g}" for v in row)])


def _one_round(lab, gp, observed, times, g_state, truth) -> tuple[tms.design.Campaign, tms.CorrectionGP]:
    """The README's round from ``gp`` (the told experiments' noise drawn from ``g_state``)."""
    g = torch.Generator().manual_seed(0)
    g.set_state(g_state)
    campaign = tms.design.Campaign(lab, tms.design.candidates.grid(BOX, 13), times, gp)
    campaign.tell(observed)  # what is known already
    asked = campaign.ask(3)
    campaign.tell(tms.Trajectories(times, noisy(tms.simulate(truth, asked, times).states, g)))
    return campaign, campaign.gp


def _rmse(lab, gp, y0, times, true) -> float:
    return float(tms.trajectory_rmse(tms.CorrectedODE(lab, gp).predict(y0, times), true))


def run_one(seed: int, cfg: dict, folder: Path, which: str) -> dict:
    g = torch.Generator().manual_seed(seed)
    times = torch.linspace(0, 6, 21, dtype=DT)
    path = folder / f"lab-{which}-{seed}.csv"
    write_lab_csv(path, times, g, which)
    lab, truth = system(False), system(True, which)
    y0 = tms.design.candidates.uniform_box(cfg["n_test"], BOX, generator=g)
    true = tms.simulate(truth, y0, times).states
    rec: dict = {"seed": seed, "truth": which}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        observed = tms.Trajectories.load(path, experiment_column="run", time_column="t", state_columns=["x", "v"])
        gp = tms.fit_correction(observed, lab, progress=False)
        rec["fit_rmse"] = _rmse(lab, gp, y0, times, true)
        rec["fit_samples"] = int(gp.train_inputs_.shape[0])
        rec["fit_model"] = _chosen(gp)
        state = g.get_state()
        for name, start in (("loop", gp), ("former", _without_data(gp))):
            t0 = time.perf_counter()
            try:
                campaign, after = _one_round(lab, start, observed, times, state, truth)
            except tms.TorchMisspecError as exc:
                rec[f"{name}_error"] = f"{type(exc).__name__}: {str(exc)[:200]}"
                continue
            rec[f"{name}_seconds"] = time.perf_counter() - t0
            rec[f"{name}_rmse"] = _rmse(lab, after, y0, times, true)
            rec[f"{name}_ratio"] = rec[f"{name}_rmse"] / rec["fit_rmse"]
            rec[f"{name}_model"] = _chosen(after)
            X = after.train_inputs_
            rec[f"{name}_samples"] = int(X.shape[0])
            rec[f"{name}_distinct"] = int(torch.unique(X, dim=0).shape[0])
            if name == "loop":
                direct = tms.fit_correction(campaign.data, lab, progress=False)
                rec["direct_samples"] = int(direct.train_inputs_.shape[0])
                rec["oracle_fit_rmse"] = oracle_rmse(which, observed, y0, times, true)
                rec["oracle_rmse"] = oracle_rmse(which, campaign.data, y0, times, true)
                rec["oracle_ratio"] = rec["oracle_rmse"] / rec["oracle_fit_rmse"]
    rec["warnings"] = sorted({f"{w.category.__name__}: {str(w.message)[:90]}" for w in caught})
    return rec


def oracle_system(truth: str) -> tms.MisspecifiedSystem:
    """The truth's own form with its one coefficient eps uncertain (prior 0 +- 1): what a scientist who knew the
    missing term's form would fit, F = 0."""

    def rhs(y, theta):
        base = known(y)
        return torch.cat([base[..., :1], base[..., 1:] + MISSING[truth](y) * theta[0] / EPS], dim=-1)

    return tms.MisspecifiedSystem(rhs, 2, parameters={"eps": (0.0, 1.0)}, domain=BOX, name=f"{truth}_oracle")


def oracle_rmse(truth: str, data: tms.Trajectories, y0, times, true) -> float:
    """The trajectory RMSE on the test states of the truth's form fitted through the ODE to ``data`` (least squares
    on the states, the initial states free): the parametric oracle, the best a fit of these data can do."""
    fitted = fitted_through_ode(oracle_system(truth), data, "additive")
    return float(tms.trajectory_rmse(tms.simulate(fitted, y0, times).states, true))


def _chosen(gp: tms.CorrectionGP) -> str:
    """The model a fit chose: the known model alone, or the cross-validation's label (else the kernel's name)."""
    if getattr(gp, "known_model_", False):
        return "known model"
    cv = getattr(gp, "cross_validation_", None)
    return str(gp.kernel) if cv is None else cv.best


def _without_data(gp: tms.CorrectionGP) -> tms.CorrectionGP:
    """``gp`` as a campaign saw every fit before it carried its data: samples only."""
    import copy

    out = copy.deepcopy(gp)
    out.trajectories_ = out.pipeline_ = None
    return out


def _task(args: tuple) -> dict:
    seed, cfg, folder, which = args
    return run_one(seed, cfg, Path(folder), which)


def study(cfg: dict, log=print, executor=None) -> dict:
    """Every realization of each truth (independent, seeded tasks)."""
    with tempfile.TemporaryDirectory() as folder:
        tasks = [(SEED + r, cfg, folder, which) for which in MISSING for r in range(cfg["realizations"])]
        runs = map_tasks(_task, tasks, executor)
    return {"runs": runs, "summary": {w: _summary([r for r in runs if r["truth"] == w], log) for w in MISSING},
            "config": cfg}  # fmt: skip


def _summary(runs: list[dict], log) -> dict:
    for r, rec in enumerate(runs):
        log(
            f"  {rec['truth']} r={r}: fit {rec.get('fit_model')} RMSE {rec['fit_rmse']:.4f}, after "
            f"{rec.get('loop_model')} {_fmt(rec.get('loop_ratio'))}x (former rule "
            f"{_fmt(rec.get('former_ratio'))}x), samples {rec.get('loop_samples')} of {rec.get('direct_samples')}"
        )
    summary = {}
    for name in ("loop", "former"):
        ratios = [r.get(f"{name}_ratio") for r in runs]
        ok = [x is not None and x <= RATIO_GOAL for x in ratios]
        summary[name] = {
            "within": sum(ok),
            "failed": sum(x is None for x in ratios),
            "median_ratio": _median([x for x in ratios if x is not None]),
            "held_once": sum(r.get(f"{name}_distinct") == r.get(f"{name}_samples") for r in runs),
        }
    summary["loop"]["as_direct"] = sum(r.get("loop_samples") == r.get("direct_samples") for r in runs)
    oracle = [r.get("oracle_ratio") for r in runs]
    summary["oracle"] = {
        "within": sum(x is not None and x <= RATIO_GOAL for x in oracle),
        "median_ratio": _median([x for x in oracle if x is not None]),
    }
    summary["realizations"] = len(runs)
    return summary


def _median(values: list[float]) -> float | None:
    return float(torch.tensor(values, dtype=DT).median()) if values else None


def _fmt(x, spec: str = ".3f") -> str:
    return "failed" if x is None else format(x, spec)


def table(result: dict) -> str:
    lines = [
        "| truth | rule of `tell` | within 1.05x of the fit | failed | median ratio | each sample once | goal |",
        "|---|---|---|---|---|---|---|",
    ]
    for which, s in result["summary"].items():
        n, loop, former = s["realizations"], s["loop"], s["former"]
        met = loop["within"] >= SHARE_GOAL * n and loop["failed"] == 0 and loop["held_once"] == n == loop["as_direct"]
        lines += [
            f"| {which} | refit by `fit_correction` on the campaign's data (now) | {loop['within']} of {n} | "
            f"{loop['failed']} | {_fmt(loop['median_ratio'])} | {loop['held_once']} of {n} (as many as a direct fit: "
            f"{loop['as_direct']}) | {'met' if met else 'missed'} |",
            f"| {which} | samples added, refit by marginal likelihood (former) | {former['within']} of {n} | "
            f"{former['failed']} | {_fmt(former['median_ratio'])} | {former['held_once']} of {n} | |",
        ]
        if "oracle" in s:
            oracle = s["oracle"]
            lines.append(
                f"| {which} | the truth's form, eps fitted through the ODE (parametric oracle, the same data) | "
                f"{oracle['within']} of {n} | 0 | {_fmt(oracle['median_ratio'])} | | |"
            )
    return "\n".join(lines) + (
        f"\n\nGoal (issue 42): within {RATIO_GOAL}x of the fit in at least {SHARE_GOAL:.0%} of realizations, no "
        "failure, each sample once.\n"
    )


def per_realization(result: dict) -> str:
    lines = [
        "| truth | seed | fit: model, RMSE | after (now): model, RMSE | ratio | after (former) | ratio | oracle: fit, "
        "after | ratio | samples |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        lines.append(
            f"| {r['truth']} | {r['seed']} | {r.get('fit_model')}, {r['fit_rmse']:.2g} | {r.get('loop_model')}, "
            f"{_fmt(r.get('loop_rmse'), '.2g')} | {_fmt(r.get('loop_ratio'))} | "
            f"{_fmt(r.get('former_rmse'), '.2g')} | {_fmt(r.get('former_ratio'))} | "
            f"{_fmt(r.get('oracle_fit_rmse'), '.2g')}, {_fmt(r.get('oracle_rmse'), '.2g')} | "
            f"{_fmt(r.get('oracle_ratio'))} | {r.get('loop_samples')} / "
            f"{r.get('direct_samples')} |"
        )
    keys = ("loop_error", "former_error")
    errors = [f"- {r['truth']} seed {r['seed']} {k}: {r[k]}" for r in result["runs"] for k in keys if k in r]
    return "\n".join(lines + (["", "Failures:", "", *errors] if errors else [])) + "\n"


def render_block(result: dict, wall: float) -> str:
    return f"""{MARK_START}
## One round of the README's design loop (`scripts/study_campaign_loop.py`)

Written by `python scripts/study_campaign_loop.py --markdown` ({wall / 60:.1f} min, {result["machine"]["cpu"]},
{result["machine"]["logical_cpus"]} logical CPUs): a Duffing lab the package does not ship, {len(result["runs"])}
realizations; see [docs/studies/campaign-loop.md](docs/studies/campaign-loop.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""# Study: one round of the README's design loop

This page is written by `python scripts/study_campaign_loop.py --markdown`; every number on it comes from that run
(raw numbers: `benchmarks/study_campaign_loop.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs,
torch {info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
{per_realization(result)}"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
