"""Study of issue 24 (part 3): partly measured states, half of the state measured.

Two systems the package does not ship elsewhere, each with one of its two components measured:

* **pk** (the correction acts on the measured component): a two-compartment pharmacokinetic model, a dose in the
  central compartment (measured) spreading to a peripheral one (not measured; its first value, 0, is known),

      dC/dt = -0.8 C + 0.2 P + F(C),        dP/dt = 0.5 C - 0.2 P,

  with a missing saturable elimination F(C) = -0.8 C / (0.5 + C); 8 experiments, doses in [0.5, 4], 12-19 times
  each at random on [0, 8] (ragged), 2 % multiplicative noise;
* **chemostat** (the correction acts on the unmeasured component, seen only through the measured one): biomass X
  measured, substrate S not (only its first value, written with a 5 % error, as a lab that prepared the medium
  knows it), a dilution input D(t) with three levels,

      dX/dt = mu(S) X - D X - 0.05 X,        dS/dt = -2 mu(S) X + D (3 - S) + F(X),

  mu(S) = 0.8 S / (0.5 + S), with a missing maintenance uptake F(X) = -0.3 X / (0.5 + X); 8 experiments x 30 times
  on [0, 12], 1 % multiplicative noise.

Each realization is fitted with the defaults (``fit_correction``, which learns through the ODE when a component is
not measured, see :mod:`torchmisspec.learning.refinement.partial`), and predicts 20 new experiments (new doses; new
initial states and input profiles) from their true initial states. Reported per component: the corrected model's RMSE
over the known model's (mean ± standard error over realizations, and the range per realization), the same for the fit of
the same data with *every* component measured (what not measuring costs), the error of the estimated initial values of
the unmeasured component, and the seconds of one fit.
"""

from __future__ import annotations

import math
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.metrics import mean_and_standard_error

DEFAULT_JSON = ROOT / "benchmarks" / "study_partial.json"
DOC_PAGE = ROOT / "docs" / "studies" / "partial.md"
MARK_START = "<!-- study:partial:start -->"
MARK_END = "<!-- study:partial:end -->"
DT = torch.float64
SEED = 24_300
FULL = {"realizations": 10, "experiments": 8, "n_test": 20}
SMOKE = {"realizations": 1, "experiments": 4, "n_test": 4, "cases": ["pk"]}  # the chemostat: tests/test_partial.py
GOALS = {"measured": 0.2}
CASES = ("pk", "chemostat")


def _pk(y):
    c, p = y[..., 0], y[..., 1]
    return torch.stack([-0.8 * c + 0.2 * p, 0.5 * c - 0.2 * p], dim=-1)


def _chemostat(t, y, u):  # noqa: ARG001 - G(t, y, u)
    X, S = y[..., 0], y[..., 1]
    mu = 0.8 * S / (0.5 + S)
    return torch.stack([mu * X - u[..., 0] * X - 0.05 * X, -2.0 * mu * X + u[..., 0] * (3.0 - S)], dim=-1)


def system(case: str, *, truth: bool = False) -> tms.MisspecifiedSystem:
    """The system of ``case`` as the lab declares it, or with its true correction (``truth``)."""
    if case == "pk":
        kw = dict(state_names=["central", "peripheral"], correction_inputs=[0], correction_outputs=[0], name="pk")
        F = lambda x: -0.8 * x / (0.5 + x)  # noqa: E731
        return tms.MisspecifiedSystem(_pk, 2, correction=F if truth else None, **kw)
    kw = dict(
        num_controls=1,
        control_names=["D"],
        state_names=["X", "S"],
        correction_inputs=[0],
        correction_outputs=[1],
        name="chemostat",
    )
    F = lambda x: -0.3 * x / (0.5 + x)  # noqa: E731
    return tms.MisspecifiedSystem(_chemostat, 2, correction=F if truth else None, **kw)


def _starts(case: str, n: int, g: torch.Generator):
    """``n`` initial states (and input profiles for the chemostat)."""
    if case == "pk":
        return torch.stack([0.5 + 3.5 * torch.rand(n, generator=g, dtype=DT), torch.zeros(n, dtype=DT)], -1), None
    y0 = torch.stack(
        [0.2 + 1.3 * torch.rand(n, generator=g, dtype=DT), 0.5 + 2.5 * torch.rand(n, generator=g, dtype=DT)], -1
    )
    levels = 0.05 + 0.35 * torch.rand(n, 3, 1, generator=g, dtype=DT)
    return y0, tms.Controls(torch.tensor([0.0, 4.0, 8.0], dtype=DT), levels, names=["D"])


def data(case: str, cfg: dict, g: torch.Generator) -> tuple[tms.Trajectories, tms.Trajectories, torch.Tensor]:
    """``(partly measured, fully measured, true initial states)``: the same noisy experiments, the second with the
    unmeasured component kept."""
    truth = system(case, truth=True)
    y0, u = _starts(case, cfg["experiments"], g)
    names = list(system(case).state_names)
    if case == "pk":
        times, states = [], []
        for k in range(cfg["experiments"]):
            n = int(torch.randint(12, 20, (1,), generator=g))
            t = torch.sort(torch.rand(n, generator=g, dtype=DT) * 8).values
            t[0] = 0.0
            y = tms.simulate(truth, y0[k : k + 1], t).states[0]
            times.append(t)
            states.append(y * (1 + 0.02 * torch.randn(y.shape, generator=g, dtype=DT)))
        full = tms.Trajectories(times, states, state_names=names)
        partial = []
        for y in states:
            y = y.clone()
            y[:, 1] = math.nan
            y[0, 1] = 0.0  # the peripheral compartment starts empty: known
            partial.append(y)
        return tms.Trajectories(times, partial, state_names=names), full, y0
    t = torch.linspace(0, 12, 30, dtype=DT)
    clean = tms.simulate(truth, y0, t, controls=u).states
    noisy = clean * (1 + 0.01 * torch.randn(clean.shape, generator=g, dtype=DT))
    full = tms.Trajectories(t, noisy, controls=u, state_names=names)
    part = noisy.clone()
    first = y0[:, 1] * (1 + 0.05 * torch.randn(y0.shape[0], generator=g, dtype=DT))
    part[..., 1] = math.nan
    part[:, 0, 1] = first  # the medium's substrate, known to about 5 %
    return tms.Trajectories(t, part, controls=u, state_names=names), full, y0


def _fit(trajectories, declared):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        gp = tms.fit_correction(trajectories, declared, progress=False)
        seconds = time.perf_counter() - t0
    return gp, seconds, [str(w.message)[:200] for w in caught if issubclass(w.category, tms.TorchMisspecWarning)]


def run_one(case: str, seed: int, cfg: dict) -> dict:
    g = torch.Generator().manual_seed(seed)
    declared, truth = system(case), system(case, truth=True)
    partial, full, y0 = data(case, cfg, g)
    y0n, un = _starts(case, cfg["n_test"], g)
    t = torch.linspace(0, 8 if case == "pk" else 12, 30, dtype=DT)
    ref = tms.simulate(truth, y0n, t, controls=un).states
    known = tms.simulate(declared, y0n, t, controls=un, known_only=True).states

    def ratios(gp) -> list[float]:
        pred = tms.CorrectedODE(declared, gp).predict(y0n, t, controls=un)
        return [
            float(tms.trajectory_rmse(pred[..., j : j + 1], ref[..., j : j + 1]))
            / float(tms.trajectory_rmse(known[..., j : j + 1], ref[..., j : j + 1]))
            for j in range(2)
        ]

    gp, seconds, warned = _fit(partial, declared)
    gp_full, seconds_full, _ = _fit(full, declared)
    y0_error = (gp.initial_states_[:, 1] - y0[:, 1]).abs() / y0[:, 1].abs().clamp_min(1e-12)
    return {
        "seed": seed,
        "ratio": ratios(gp),
        "ratio_fully_measured": ratios(gp_full),
        "fit_seconds": seconds,
        "fit_seconds_fully_measured": seconds_full,
        "initial_error": float(y0_error.mean()) if case == "chemostat" else float(gp.initial_states_[:, 1].abs().max()),
        "kernel": repr(gp.kernel),
        "identifiability": gp.identifiability_.summary(),
        "warnings": warned,
    }


def study(cfg: dict, log=print) -> dict:
    runs = {}
    for case in cfg.get("cases", CASES):
        i = CASES.index(case)
        runs[case] = []
        for r in range(cfg["realizations"]):
            one = run_one(case, SEED + 1000 * i + r, cfg)
            runs[case].append(one)
            log(
                f"{case} {r}: corrected/known measured {one['ratio'][0 if case == 'pk' else 0]:.3f}, "
                f"unmeasured {one['ratio'][1]:.3f} (fully measured {one['ratio_fully_measured'][0]:.3f}, "
                f"{one['ratio_fully_measured'][1]:.3f}); fit {one['fit_seconds']:.1f} s"
            )
    return {"config": cfg, "goals": GOALS, "runs": runs}


def _summary(values) -> str:
    x = torch.tensor(values, dtype=DT)
    m, se = mean_and_standard_error(x)
    return f"{float(m):.3f} ± {float(se):.3f} ({float(x.min()):.3f}-{float(x.max()):.3f})"


def table(result: dict) -> str:
    lines = [
        "| system | component | corrected / known RMSE, one measured | with both measured | goal |",
        "|---|---|---|---|---|",
    ]
    for case, runs in result["runs"].items():
        names = list(system(case).state_names)
        for j, label in ((0, "measured"), (1, "not measured")):
            mean = float(torch.tensor([r["ratio"][j] for r in runs], dtype=DT).mean())
            goal = "reported"
            if j == 0:
                goal = f"<= {GOALS['measured']}: {'met' if mean <= GOALS['measured'] else '**not met**'}"
            lines.append(
                f"| {case} | {names[j]} ({label}) | {_summary([r['ratio'][j] for r in runs])} | "
                f"{_summary([r['ratio_fully_measured'][j] for r in runs])} | {goal} |"
            )
    lines += ["", "| system | seconds of one fit (one measured) | (both measured) | initial values not measured |"]
    lines.append("|---|---|---|---|")
    for case, runs in result["runs"].items():
        secs = sorted(r["fit_seconds"] for r in runs)
        full = sorted(r["fit_seconds_fully_measured"] for r in runs)
        what = "largest peripheral estimate (truth 0)" if case == "pk" else "mean relative error of S(0)"
        lines.append(
            f"| {case} | median {secs[len(secs) // 2]:.1f}, max {secs[-1]:.1f} | median {full[len(full) // 2]:.1f} | "
            f"{what}: {_summary([r['initial_error'] for r in runs])} |"
        )
    return "\n".join(lines) + "\n"


def per_realization(result: dict) -> str:
    lines = [
        "| system | seed | measured | not measured | both measured | fit s | warnings |",
        "|---|---|---|---|---|---|---|",
    ]
    for case, runs in result["runs"].items():
        for r in runs:
            lines.append(
                f"| {case} | {r['seed']} | {r['ratio'][0]:.3f} | {r['ratio'][1]:.3f} | "
                f"{r['ratio_fully_measured'][0]:.3f}, {r['ratio_fully_measured'][1]:.3f} | {r['fit_seconds']:.1f} | "
                f"{len(r['warnings'])} |"
            )
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""{MARK_START}
## Partly measured states (`scripts/study_partial.py`)

Written by `python scripts/study_partial.py --markdown` ({wall / 60:.1f} min, {info["cpu"]}, {info["logical_cpus"]}
logical CPUs): half of the state measured, {result["config"]["realizations"]} realizations per system, defaults
only; see [docs/studies/partial.md](docs/studies/partial.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""# Study: partly measured states

This page is written by `python scripts/study_partial.py --markdown`; every number on it comes from that run (raw
numbers: `benchmarks/study_partial.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs, torch
{info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
Per realization (corrected / known RMSE of each component; the fully measured fit's):

{per_realization(result)}"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
