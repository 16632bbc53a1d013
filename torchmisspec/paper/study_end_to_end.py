"""Study of issue 22: the scientist's whole loop, with defaults only, on a system the package does not ship.

The system is the one of the issue's user trial: an epidemic with three states (S, I, R), whose known model has
mass-action incidence beta S I while the truth saturates, beta S I / (1 + a I); the correction is declared on two
inputs (S, I) and two outputs (dS/dt, dI/dt), and its true form is never given to the package. Each realization is a
lab's CSV (columns ``experiment, day, S, I, R``): 8 experiments of 9 to 25 irregular days on [0, 40], states with
2 % multiplicative noise. Then, with defaults only, as the README shows:

``Trajectories.load`` -> ``fit_correction`` -> ``CorrectedODE.predict`` (new initial conditions) ->
``calibrate`` -> ``posterior`` -> ``design.greedy`` -> ``design.Campaign`` (ask 3, tell noisy results, ask 2).

Reported per realization and as mean ± standard error: the corrected model's trajectory RMSE over the known model's
on 50 new initial conditions (against the true system), the coverage of the true states by the calibrated central
90 % band (every time after the first and every component), the seconds of ``fit_correction`` and of ``calibrate``,
whether greedy and the campaign returned their experiments, and the warnings a user saw.
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
from torchmisspec.metrics import mean_and_standard_error
from torchmisspec.parallel import map_tasks

DEFAULT_JSON = ROOT / "benchmarks" / "study_end_to_end.json"
DOC_PAGE = ROOT / "docs" / "studies" / "end-to-end.md"
MARK_START = "<!-- study:end-to-end:start -->"
MARK_END = "<!-- study:end-to-end:end -->"
DT = torch.float64
SEED = 22_000
BETA, GAMMA, SATURATION = 0.5, 0.1, 5.0
FULL = {"realizations": 10, "n_test": 50, "num_samples": 64}
SMOKE = {"realizations": 2, "n_test": 10, "num_samples": 16}
GOALS = {"rmse_ratio": 0.1, "coverage": (0.85, 0.95), "fit_seconds": 10.0}
#: Issue 41's goal for the 90 % band over each half of the prediction horizon.
HALF_GOAL = (0.80, 0.97)


def known(y: torch.Tensor) -> torch.Tensor:
    """The lab's model: mass-action incidence."""
    S, I = y[..., 0], y[..., 1]
    incidence = BETA * S * I
    return torch.stack([-incidence, incidence - GAMMA * I, GAMMA * I], dim=-1)


def missing(x: torch.Tensor) -> torch.Tensor:
    """The truth's saturating incidence minus the model's, on (dS/dt, dI/dt); x = (S, I)."""
    S, I = x[..., 0], x[..., 1]
    excess = -BETA * SATURATION * S * I**2 / (1 + SATURATION * I)
    return torch.stack([-excess, excess], dim=-1)


def system(with_truth: bool) -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        known,
        3,
        correction=missing if with_truth else None,
        correction_inputs=[0, 1],
        correction_outputs=[0, 1],
        domain=[(0.0, 1.0), (0.0, 0.6)],
        name="sir_saturating",
    )


def initial_states(n: int, g: torch.Generator) -> torch.Tensor:
    """Epidemics from 2 % to 32 % infected, the rest split between S and R (S at least half of it)."""
    infected = 0.02 + 0.3 * torch.rand(n, 1, generator=g, dtype=DT)
    susceptible = (1 - infected) * (0.5 + 0.5 * torch.rand(n, 1, generator=g, dtype=DT))
    return torch.cat([susceptible, infected, 1 - susceptible - infected], dim=-1)


def noisy(states: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    return states * (1 + 0.02 * torch.randn(states.shape, generator=g, dtype=DT))


def write_lab_csv(path: Path, g: torch.Generator) -> None:
    truth = system(True)
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["experiment", "day", "S", "I", "R"])
        for k in range(8):
            n = int(torch.randint(9, 26, (1,), generator=g))
            days = torch.sort(torch.rand(n, generator=g, dtype=DT) * 40).values
            days[0] = 0.0
            states = noisy(tms.simulate(truth, initial_states(1, g), days).states[0], g)
            for t, row in zip(days.tolist(), states.tolist(), strict=True):
                out.writerow([f"run{k + 1}", f"{t:.3f}", *(f"{v:.5g}" for v in row)])


def run_one(seed: int, cfg: dict, folder: Path) -> dict:
    g = torch.Generator().manual_seed(seed)
    path = folder / f"lab-{seed}.csv"
    write_lab_csv(path, g)
    lab, truth = system(False), system(True)
    rec: dict = {"seed": seed}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        observed = tms.Trajectories.load(path, time_column="day", state_columns=["S", "I", "R"])
        t0 = time.perf_counter()
        gp = tms.fit_correction(observed, lab)
        rec["fit_seconds"] = time.perf_counter() - t0
        rec["model"] = repr(gp)[:160]
        model = tms.CorrectedODE(lab, gp)
        y0 = initial_states(cfg["n_test"], g)
        days = torch.linspace(0, 40, 21, dtype=DT)
        true = tms.simulate(truth, y0, days).states
        known_only = tms.simulate(lab, y0, days, known_only=True).states
        rec["rmse_ratio"] = float(
            tms.trajectory_rmse(model.predict(y0, days), true) / tms.trajectory_rmse(known_only, true)
        )
        t0 = time.perf_counter()
        cal = model.calibrate(observed)
        rec["calibrate_seconds"] = time.perf_counter() - t0
        rec["scale"], rec["held_out_coverage"], rec["reached"] = cal.scale, cal.coverage, cal.reached
        post = model.posterior(y0, days, num_samples=cfg["num_samples"], generator=g)
        covered = post.covers(true, 0.9)[:, 1:].double()  # (B, T - 1, d): every time after the first
        rec["coverage"] = float(covered.mean())
        half = covered.shape[1] // 2  # and over each half of the days (issue 41: bands honest over time)
        rec["coverage_first_half"] = float(covered[:, :half].mean())
        rec["coverage_second_half"] = float(covered[:, half:].mean())
        candidates = initial_states(200, g)
        try:
            plan = tms.design.greedy(candidates, 3, system=lab, times=days, gp=gp)
            rec["greedy"] = len(set(plan.indices.tolist())) == 3
        except tms.TorchMisspecError as exc:
            rec["greedy"] = False
            rec["greedy_error"] = f"{type(exc).__name__}: {str(exc)[:200]}"
        try:
            campaign = tms.design.Campaign(lab, candidates, days, gp)
            asked = campaign.ask(3)
            campaign.tell(tms.Trajectories(days, noisy(tms.simulate(truth, asked, days).states, g)))
            rec["campaign"] = campaign.ask(2).shape == (2, 3)
            rec["campaign_unmatched"] = campaign.history[-2]["unrequested"]  # told first states matched to no ask
        except tms.TorchMisspecError as exc:
            rec["campaign"] = False
            rec["campaign_error"] = f"{type(exc).__name__}: {str(exc)[:200]}"
    rec["warnings"] = sorted({f"{w.category.__name__}: {str(w.message)[:90]}" for w in caught})
    return rec


def _task(args: tuple) -> dict:
    seed, cfg, folder = args
    return run_one(seed, cfg, Path(folder))  # each realization writes its own files (named by its seed)


def study(cfg: dict, log=print, executor=None) -> dict:
    """Every realization (independent tasks, each seeded: through ``executor`` the same numbers)."""
    with tempfile.TemporaryDirectory() as folder:
        tasks = [(SEED + r, cfg, folder) for r in range(cfg["realizations"])]
        runs = map_tasks(_task, tasks, executor)
        for r, rec in enumerate(runs):
            log(
                f"  r={r}: fit {rec['fit_seconds']:.1f} s, RMSE ratio {rec['rmse_ratio']:.3f}, calibrate "
                f"{rec['calibrate_seconds']:.1f} s (scale {rec['scale']:.3g}), coverage {rec['coverage']:.3f}, greedy "
                f"{rec['greedy']}, campaign {rec['campaign']}"
            )
    summary = {}
    for key in ("rmse_ratio", "coverage", "coverage_first_half", "coverage_second_half", "fit_seconds",
                "calibrate_seconds", "scale"):  # fmt: skip
        values = [r[key] for r in runs if key in r]
        if not values:
            continue
        m, se = mean_and_standard_error(values)
        summary[key] = {"mean": float(m), "se": float(se), "min": min(values), "max": max(values)}
    return {"runs": runs, "summary": summary, "config": cfg}


def table(result: dict) -> str:
    s, runs = result["summary"], result["runs"]
    cov_lo, cov_hi = GOALS["coverage"]

    def row(label, key, goal, ok):
        v = s[key]
        return (
            f"| {label} | {v['mean']:.3g} ± {v['se']:.2g} | {v['min']:.3g} - {v['max']:.3g} | {goal} | "
            f"{'met' if ok else 'missed'} |"
        )

    lines = [
        "| quantity | mean ± s.e. | per realization (min - max) | goal | |",
        "|---|---|---|---|---|",
        row(
            "corrected / known trajectory RMSE",
            "rmse_ratio",
            f"<= {GOALS['rmse_ratio']}",
            s["rmse_ratio"]["mean"] <= 0.1,
        ),
        row(
            "calibrated 90 % band: coverage of the true states",
            "coverage",
            f"in [{cov_lo}, {cov_hi}]",
            cov_lo <= s["coverage"]["mean"] <= cov_hi,
        ),
        *(
            row(
                f"calibrated 90 % band: coverage over the {which} half of the days",
                f"coverage_{which}_half",
                f"in [{HALF_GOAL[0]}, {HALF_GOAL[1]}]",
                HALF_GOAL[0] <= s[f"coverage_{which}_half"]["mean"] <= HALF_GOAL[1],
            )
            for which in ("first", "second")
            if f"coverage_{which}_half" in s
        ),
        row("`fit_correction` seconds", "fit_seconds", f"<= {GOALS['fit_seconds']:g}", s["fit_seconds"]["mean"] <= 10),
        row("`calibrate` seconds", "calibrate_seconds", "", True),
        row("calibrated scale c", "scale", "", True),
        f"| greedy returned 3 experiments | {sum(r['greedy'] for r in runs)} of {len(runs)} | | all | "
        f"{'met' if all(r['greedy'] for r in runs) else 'missed'} |",
        f"| Campaign ask / tell / ask | {sum(r['campaign'] for r in runs)} of {len(runs)} | | all | "
        f"{'met' if all(r['campaign'] for r in runs) else 'missed'} |",
        f"| told experiments whose noisy first state matched no ask (of 3) | "
        f"{sum(r.get('campaign_unmatched', 0) for r in runs)} in all | | | |",
    ]
    return "\n".join(lines) + "\n"


def per_realization(result: dict) -> str:
    lines = [
        "| seed | model chosen | fit s | RMSE ratio | calibrate s | scale | held-out coverage | coverage (true) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        lines.append(
            f"| {r['seed']} | `{r['model'].split(',')[0]})` | {r['fit_seconds']:.1f} | {r['rmse_ratio']:.3f} | "
            f"{r['calibrate_seconds']:.1f} | {r['scale']:.3g} | {r['held_out_coverage']:.3f} | {r['coverage']:.3f} |"
        )
    seen: dict[str, int] = {}
    for r in result["runs"]:
        for w in r["warnings"]:
            seen[w] = seen.get(w, 0) + 1
    lines += ["", "Warnings the user saw (realizations in which each appeared; messages cut at 90 characters):", ""]
    lines += [f"- {n} of {len(result['runs'])}: {w}" for w, n in sorted(seen.items(), key=lambda kv: -kv[1])] or [
        "- none"
    ]
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    cfg = result["config"]
    return f"""{MARK_START}
## The whole loop with defaults (`scripts/study_end_to_end.py`)

Written by `python scripts/study_end_to_end.py --markdown` ({wall / 60:.1f} min, {result["machine"]["cpu"]},
{result["machine"]["logical_cpus"]} logical CPUs): the issue's SIR trial (8 ragged experiments of 9-25 irregular days,
2 % noise, a lab's CSV), {cfg["realizations"]} realizations, defaults only; see
[docs/studies/end-to-end.md](docs/studies/end-to-end.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""# Study: the scientist's whole loop, with defaults only

This page is written by `python scripts/study_end_to_end.py --markdown`; every number on it comes from that run (raw
numbers: `benchmarks/study_end_to_end.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs, torch
{info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
{per_realization(result)}"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
