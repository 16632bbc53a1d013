"""Study of issue 24 (part 4): designing input profiles with the information criterion, against random profiles.

The system is a tank the package does not ship: level y, a known inflow u(t) the lab sets, known outflow 0.7 y and a
missing term that grows with both, F(y, u) = -0.5 u y / (1 + y), so what is learned depends on the inflows tried.
A candidate experiment is an initial level and an inflow profile (three levels in [0, 2] held on [0, 2), [2, 4),
[4, 6]): 8 initial levels in [0.2, 2.5] x 12 random profiles = 96 candidates per realization.

The design runs before any data, from a stated prior (RBF, lengthscale 0.7, output scale 0.1, noise 1e-4), with
``design.greedy(..., controls=profiles)`` by the information criterion and by the domain criterion (the variance of
F over the box removed; its picks in order, so the first K are its design of K); the baseline takes K candidates at
random. Each selection's experiments are simulated (61 times on [0, 6], state noise 1e-3) and F is learned with
``fit_correction`` (defaults); the error is the integrated error of F over the box level in [0, 3] x inflow in
[0, 2]. (With 13 times the derivative samples between the inflow's jumps are too poor: random picks' error grew with
K, 0.28 at K = 2 to 0.73 at K = 16, so no design could be compared; with 61 times it falls, 0.078 to 0.023.)
Reported per K: the mean ± standard error over realizations; and the number of designed experiments that reaches
random's error at K (interpolated in K on the log error), over K: the issue's goal is at most 0.7 averaged over K.
"""

from __future__ import annotations

import math
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.metrics import mean_and_standard_error

DEFAULT_JSON = ROOT / "benchmarks" / "study_input_design.json"
DOC_PAGE = ROOT / "docs" / "studies" / "input-design.md"
MARK_START = "<!-- study:input-design:start -->"
MARK_END = "<!-- study:input-design:end -->"
DT = torch.float64
SEED = 24_400
#: "support_ks": numbers of experiments measured only to interpolate "experiments needed" below the smallest K of
#: "ks" (without them, a design already better than random at the smallest K counts as needing all of it)
FULL = {"realizations": 10, "ks": [2, 3, 4, 6, 8], "support_ks": [1], "states": 8, "profiles": 12, "times": 61}
SMOKE = {"realizations": 2, "ks": [2, 4], "states": 4, "profiles": 4, "times": 31}
GOAL = 0.7
PRIOR = {"lengthscale": 0.7, "outputscale": 0.1, "noise_variance": 1e-4}


def system() -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        lambda t, y, u: -0.7 * y + u,
        1,
        num_controls=1,
        control_names=["inflow"],
        state_names=["level"],
        correction=lambda x: -0.5 * x[..., 1:] * x[..., :1] / (1 + x[..., :1]),
        correction_inputs=["level", "inflow"],
        domain=[(0.0, 3.0), (0.0, 2.0)],
        name="tank",
    )


def candidates(cfg: dict, g: torch.Generator) -> tuple[torch.Tensor, tms.Controls]:
    """Every initial level with every profile: ``(states x profiles, 1)`` and their Controls."""
    levels = torch.linspace(0.2, 2.5, cfg["states"], dtype=DT)
    profiles = 2.0 * torch.rand(cfg["profiles"], 3, 1, generator=g, dtype=DT)
    y0 = levels.repeat_interleave(cfg["profiles"]).unsqueeze(-1)
    values = profiles.repeat(cfg["states"], 1, 1)
    return y0, tms.Controls(torch.tensor([0.0, 2.0, 4.0], dtype=DT), values, names=["inflow"])


def error_of(picks: list[int], y0, profiles, sys_, times, g) -> float:
    chosen = profiles[picks]
    clean = tms.simulate(sys_, y0[picks], times, controls=chosen).states
    data = tms.Trajectories(times, clean + 1e-3 * torch.randn(clean.shape, generator=g, dtype=DT), controls=chosen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = tms.fit_correction(data, sys_, progress=False)
    return float(tms.correction_error(gp, sys_))


def run_one(seed: int, cfg: dict) -> dict:
    g = torch.Generator().manual_seed(seed)
    sys_ = system()
    y0, profiles = candidates(cfg, g)
    times = torch.linspace(0, 6, cfg["times"], dtype=DT)
    prior = tms.CorrectionGP(**PRIOR)
    t0 = time.perf_counter()
    kw = dict(system=sys_, times=times, gp=prior, controls=profiles)
    plan = tms.design.greedy(y0, max(cfg["ks"]), **kw)
    seconds = time.perf_counter() - t0
    domain = tms.design.greedy(y0, max(cfg["ks"]), criterion="domain", **kw)
    orders = {
        "designed": plan.indices.tolist(),
        "domain": domain.indices.tolist(),
        "random": torch.randperm(y0.shape[0], generator=g).tolist(),
    }
    out = {"seed": seed, "design_seconds": seconds, **{name: {} for name in orders}}
    for k in cfg["ks"] + cfg.get("support_ks", []):  # the support after the rest: their noise draws unchanged
        for name, order in orders.items():
            out[name][str(k)] = error_of(order[:k], y0, profiles, sys_, times, g)
    return out


def study(cfg: dict, log=print) -> dict:
    runs = []
    for r in range(cfg["realizations"]):
        runs.append(run_one(SEED + r, cfg))
        one = runs[-1]
        log(f"realization {r}: information {one['designed']}, domain {one['domain']}, random {one['random']}")
    return {"config": cfg, "prior": PRIOR, "goal": GOAL, "runs": runs}


def _means(result: dict, which: str, ks=None) -> list[tuple[float, float]]:
    out = []
    for k in result["config"]["ks"] if ks is None else ks:
        m, se = mean_and_standard_error(torch.tensor([r[which][str(k)] for r in result["runs"]], dtype=DT))
        out.append((float(m), float(se)))
    return out


def experiments_needed(ks: list[int], designed: list[float], target: float) -> float:
    """The (interpolated) number of designed experiments whose mean error reaches ``target``: linear in K on the log
    error between the grid's points; beyond the grid, ``nan`` (not reached) or the first K (reached already)."""
    logs = [math.log(e) for e in designed]
    goal = math.log(target)
    if logs[0] <= goal:
        return float(ks[0])  # reached at the smallest K tried: an upper bound
    for i in range(1, len(ks)):
        if logs[i] <= goal:
            frac = (logs[i - 1] - goal) / (logs[i - 1] - logs[i])
            return ks[i - 1] + frac * (ks[i] - ks[i - 1])
    return math.nan


def table(result: dict) -> str:
    ks = result["config"]["ks"]
    grid = sorted(ks + result["config"].get("support_ks", []))  # where the designs' errors were measured
    arms = {"designed": "information design", "domain": "domain design"}
    ran = _means(result, "random", grid)
    lines = [
        "| K | random: integrated error of F | "
        + " | ".join(f"{label} | / random | experiments reaching random's error, / K" for label in arms.values())
        + " |",
        "|---|---|" + "---|---|---|" * len(arms),
    ]
    ratios = {arm: [] for arm in arms}
    means = {arm: _means(result, arm, grid) for arm in arms}
    for i, k in enumerate(grid):
        cells = [f"{ran[i][0]:.4g} ± {ran[i][1]:.2g}"]
        for arm in arms:
            des = means[arm]
            ratio = experiments_needed(grid, [m for m, _ in des], ran[i][0]) / k
            if k in ks:
                ratios[arm].append(ratio)
            shown = f"{ratio:.3f}" if k in ks else f"({ratio:.3f}, interpolation only)"
            cells += [f"{des[i][0]:.4g} ± {des[i][1]:.2g}", f"{des[i][0] / ran[i][0]:.3f}", shown]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    lines.append("")
    for arm, label in arms.items():
        finite = [r for r in ratios[arm] if math.isfinite(r)]
        mean = sum(finite) / len(finite) if finite else math.nan
        verdict = "met" if len(finite) == len(ratios[arm]) and mean <= GOAL else "**not met**"
        unreached = len(ratios[arm]) - len(finite)
        lines.append(
            f"- {label}: experiments needed for random's error, over K, averaged over K = {ks}: **{mean:.3f}** "
            f"(goal <= {GOAL}: {verdict}"
            + (f"; not reached within the grid at {unreached} K" if unreached else "")
            + f"; the smallest K measured, {grid[0]}, bounds it from above where the design is already better there)"
        )
    secs = [r["design_seconds"] for r in result["runs"]]
    lines.append(f"- seconds of one information design of {max(ks)}: median {sorted(secs)[len(secs) // 2]:.2f}")
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""{MARK_START}
## Designing input profiles (`scripts/study_input_design.py`)

Written by `python scripts/study_input_design.py --markdown` ({wall / 60:.1f} min, {info["cpu"]}, {info["logical_cpus"]}
logical CPUs): a tank whose missing term depends on the inflow, candidate experiments = initial level x inflow
profile, greedy information design before any data against random picks, {result["config"]["realizations"]}
realizations; see [docs/studies/input-design.md](docs/studies/input-design.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    per = ["| seed | " + " | ".join(f"K={k} information / domain / random" for k in result["config"]["ks"]) + " |"]
    per.append("|---|" + "---|" * len(result["config"]["ks"]))
    for r in result["runs"]:
        cells = [
            f"{r['designed'][str(k)]:.3g} / {r['domain'][str(k)]:.3g} / {r['random'][str(k)]:.3g}"
            for k in result["config"]["ks"]
        ]
        per.append(f"| {r['seed']} | " + " | ".join(cells) + " |")
    return f"""# Study: designing input profiles

This page is written by `python scripts/study_input_design.py --markdown`; every number on it comes from that run
(raw numbers: `benchmarks/study_input_design.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs,
torch {info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
Per realization (integrated error of F):

{chr(10).join(per)}
"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
