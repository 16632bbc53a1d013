"""Issue 9's study (:mod:`torchmisspec.paper.study_observations`): its summary, its goals, its pages (the docs page
docs/studies/real-data.md and the block of BENCHMARKS.md) and its JSON, from a fresh run, a saved run or the runs
of disjoint systems made in parallel (``--merge``)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from torchmisspec.benchmarks.reporting import BENCHMARKS_MD, ROOT, machine, update_benchmarks, write_page
from torchmisspec.learning.samples.observations import ESTIMATOR_ERROR_THRESHOLD
from torchmisspec.metrics import mean_and_standard_error

from . import _setup as paper_setup
from .study_observations import (
    CASES,
    FIT_MAX_ITER,
    KS,
    N_TEST,
    NOISE_LEVELS,
    ORACLE_FACTOR,
    ORACLE_K,
    ORACLE_NOISE,
    RATIO_GOAL,
    RATIO_NEVER,
    REALIZATIONS,
    SEED,
    TEST_SEED,
    TEST_TIMES,
    fmt,
    study,
)

DEFAULT_JSON = ROOT / "benchmarks" / "study_observations.json"
DOC_PAGE = ROOT / "docs" / "studies" / "real-data.md"
MARK_START = "<!-- study:observations:start -->"
MARK_END = "<!-- study:observations:end -->"


def _mse(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    m, s = mean_and_standard_error(values)
    return float(m), float(s)


METHODS = ("auto", "fit_trajectories")


def summarise(raw: dict, cases, ks, noise_levels, oracle_k: int) -> dict:
    runs = raw["runs"]
    cells = []
    for case in cases:
        for K in ks:
            for level in noise_levels:
                sel = [r for r in runs if r["system"] == case.name and r["K"] == K and r["noise"] == level]
                if not sel:
                    continue
                cell = {
                    "system": case.name,
                    "K": K,
                    "noise": level,
                    "realizations": len(sel),
                    "warnings": sum(bool(r.get("warning")) for r in sel),
                    "estimators": {},
                }
                for r in sel:
                    label = r["estimator"]["label"]
                    cell["estimators"][label] = cell["estimators"].get(label, 0) + 1
                ratios = [r["estimator_ratio"] for r in sel if r.get("estimator_ratio") is not None]
                cell["estimator_ratio_mean"], cell["estimator_ratio_se"] = _mse([x for x in ratios if math.isfinite(x)])
                for m in METHODS:
                    ok = [r[m] for r in sel if r[m]["status"] == "ok"]
                    vals = [x["ratio"] for x in ok if math.isfinite(x["ratio"])]
                    mean, se = _mse(vals)
                    cell[m] = {
                        "ok": len(vals),
                        "failed": len(sel) - len(vals),
                        "errors": sorted({r[m].get("error", "non-finite ratio") for r in sel if r[m] not in ok}),
                        "ratio_mean": mean,
                        "ratio_se": se,
                        "ratio_max": max(vals) if vals else None,
                        "relative_rmse_mean": _mse([x["relative_rmse"] for x in ok])[0],
                        "seconds_mean": _mse([x["fit_seconds"] for x in ok])[0],
                    }
                    if m == "fit_trajectories":
                        cell[m]["iterations_mean"] = _mse([x["iterations"] for x in ok])[0]
                        cell[m]["evaluations_mean"] = _mse([x["evaluations"] for x in ok])[0]
                cells.append(cell)
    return {
        "cells": cells,
        "goals": goals(raw, cells, oracle_k),
        "integrated_error": integrated_error_goal(raw, oracle_k),
    }


def integrated_error_goal(raw: dict, oracle_k: int) -> dict | None:
    sel = [
        r for r in raw["runs"] if r["system"] == "paper_linear" and r["K"] == oracle_k and r["noise"] == ORACLE_NOISE
    ]
    oracle = [r["correction_error"] for r in raw["oracle_runs"] if r["status"] == "ok"]
    if not sel or not oracle:
        return None
    out = {
        "K": oracle_k,
        "noise": ORACLE_NOISE,
        "oracle_noise_std": paper_setup.NOISE_STD,
        "oracle_failed": len(raw["oracle_runs"]) - len(oracle),
    }
    mean, se = _mse(oracle)
    out["oracle"] = {"mean": mean, "se": se, "n": len(oracle)}
    ratio = [r["ratio"] for r in raw["oracle_runs"] if r["status"] == "ok" and "ratio" in r]
    out["oracle"]["trajectory_ratio_mean"], out["oracle"]["trajectory_ratio_se"] = _mse(ratio)
    for m in METHODS:
        vals = [r[m]["correction_error"] for r in sel if r[m]["status"] == "ok" and "correction_error" in r[m]]
        mean, se = _mse(vals)
        out[m] = {"mean": mean, "se": se, "n": len(vals), "failed": len(sel) - len(vals)}
        ratio = [r[m]["ratio"] for r in sel if r[m]["status"] == "ok"]
        out[m]["trajectory_ratio_mean"], out[m]["trajectory_ratio_se"] = _mse(ratio)
        out[m]["ratio_to_oracle"] = None if mean is None else mean / out["oracle"]["mean"]
        # paired per-realization ratio (same initial conditions)
        pairs = {r["realization"]: r[m].get("correction_error") for r in sel if r[m]["status"] == "ok"}
        orc = {r["realization"]: r["correction_error"] for r in raw["oracle_runs"] if r["status"] == "ok"}
        paired = [pairs[k] / orc[k] for k in pairs if k in orc and pairs[k] is not None]
        out[m]["paired_ratio_mean"], out[m]["paired_ratio_se"] = _mse(paired)
        out[m]["pass"] = (
            out[m]["ratio_to_oracle"] is not None
            and out[m]["ratio_to_oracle"] <= ORACLE_FACTOR
            and not out[m]["failed"]
        )
    return out


def goals(raw: dict, cells: list[dict], oracle_k: int) -> list[dict]:
    """The measured goals of issue 9 as PASS/FAIL lines with their evidence."""
    lines = []
    systems = list(dict.fromkeys(c["system"] for c in cells))
    for m in METHODS:
        for s in systems:
            sel = [c for c in cells if c["system"] == s and c["K"] >= 10]
            if not sel:
                continue
            bad = [c for c in sel if c[m]["failed"] or c[m]["ratio_mean"] is None or c[m]["ratio_mean"] > RATIO_GOAL]
            worst = max(sel, key=lambda c: math.inf if c[m]["ratio_mean"] is None else c[m]["ratio_mean"])
            evidence = (
                f"worst cell K={worst['K']}, noise {_pct(worst['noise'])}: mean ratio "
                f"{fmt(worst[m]['ratio_mean'])} +- {fmt(worst[m]['ratio_se'])}"
            )
            if bad:
                evidence += "; failing cells: " + ", ".join(
                    f"K={c['K']}/{_pct(c['noise'])}" + (f" ({c[m]['failed']} failed runs)" if c[m]["failed"] else "")
                    for c in bad
                )
            lines.append(
                {
                    "goal": f"{m}: {s}, K >= 10, every noise level: mean ratio <= {RATIO_GOAL}",
                    "pass": not bad,
                    "evidence": evidence,
                }
            )
    violations, failures = [], []
    for r in raw["runs"]:
        for m in METHODS:
            res = r[m]
            if res["status"] != "ok":
                failures.append(f"{r['system']} K={r['K']} {_pct(r['noise'])} r={r['realization']} {m}")
                if not r.get("warning"):
                    violations.append(
                        f"{r['system']} K={r['K']} {_pct(r['noise'])} r={r['realization']} {m}: failed "
                        f"({res.get('error', '')[:80]})"
                    )
            elif not (res["ratio"] <= RATIO_NEVER) and not r.get("warning"):
                violations.append(
                    f"{r['system']} K={r['K']} {_pct(r['noise'])} r={r['realization']} {m}: ratio {fmt(res['ratio'])}"
                )
    n_runs = len(raw["runs"]) * len(METHODS)
    lines.append(
        {
            "goal": f"no run (auto or fit_trajectories) with ratio > {RATIO_NEVER} (or failed) without the warning",
            "pass": not violations,
            "evidence": f"{len(violations)} of {n_runs} runs violate"
            + (": " + "; ".join(violations[:12]) + (" ..." if len(violations) > 12 else "") if violations else ""),
        }
    )
    lines.append(
        {
            "goal": "no run raised an exception",
            "pass": not failures,
            "evidence": f"{len(failures)} of {n_runs} runs failed"
            + (": " + "; ".join(failures[:12]) + (" ..." if len(failures) > 12 else "") if failures else ""),
        }
    )
    ie = integrated_error_goal(raw, oracle_k)
    if ie is not None:
        for m in METHODS:
            lines.append(
                {
                    "goal": f"{m}: paper_linear integrated error of F_hat at {_pct(ORACLE_NOISE)} state noise, "
                    f"K = {oracle_k}, within {ORACLE_FACTOR:g}x of the oracle's",
                    "pass": ie[m]["pass"],
                    "evidence": f"{fmt(ie[m]['mean'])} +- {fmt(ie[m]['se'])} vs oracle {fmt(ie['oracle']['mean'])} "
                    f"+- {fmt(ie['oracle']['se'])}: ratio {fmt(ie[m]['ratio_to_oracle'])}",
                }
            )
    return lines


def _pct(level: float) -> str:
    return f"{100 * level:g} %"


# ------------------------------------------------------------------------------------------------- markdown
def _pm(mean, se) -> str:
    return "n/a" if mean is None else f"{fmt(mean)} ± {fmt(se, '.2g')}"


def _cell_ratio(c: dict, m: str) -> str:
    s = _pm(c[m]["ratio_mean"], c[m]["ratio_se"])
    if c[m]["failed"]:
        s += f" ({c[m]['failed']} failed)"
    return s


def summary_table(result: dict) -> str:
    """One row per system x K x noise: mean ± standard error of the RMSE ratio for both methods."""
    head = (
        "| system | K | state noise | auto: ratio | fit_trajectories: ratio | max ratio (auto / fit) | "
        "RMSE / RMS(truth) (auto / fit) | warnings | estimator chosen (count) |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    rows = []
    for c in result["summary"]["cells"]:
        est = ", ".join(f"{k} ({v})" for k, v in sorted(c["estimators"].items(), key=lambda kv: -kv[1]))
        rows.append(
            f"| {c['system']} | {c['K']} | {_pct(c['noise'])} | {_cell_ratio(c, 'auto')} | "
            f"{_cell_ratio(c, 'fit_trajectories')} | {fmt(c['auto']['ratio_max'])} / "
            f"{fmt(c['fit_trajectories']['ratio_max'])} | {fmt(c['auto']['relative_rmse_mean'])} / "
            f"{fmt(c['fit_trajectories']['relative_rmse_mean'])} | {c['warnings']}/{c['realizations']} | {est} |"
        )
    return head + "\n".join(rows) + "\n"


def estimator_table(result: dict) -> str:
    """Estimator self-check ratios per system and noise (mean over K and realizations) and how often each won."""
    runs = result["raw"]["runs"]
    out = ["| system | state noise | chosen (count over K and seeds) | self-check ratio of the choice (min..max) |"]
    out.append("|---|---|---|---|")
    for system in dict.fromkeys(r["system"] for r in runs):
        for level in dict.fromkeys(r["noise"] for r in runs):
            sel = [r for r in runs if r["system"] == system and r["noise"] == level]
            counts: dict[str, int] = {}
            for r in sel:
                counts[r["estimator"]["label"]] = counts.get(r["estimator"]["label"], 0) + 1
            ratios = [r["estimator_ratio"] for r in sel if r.get("estimator_ratio") is not None]
            ratios = [x for x in ratios if math.isfinite(x)]
            est = ", ".join(f"{k} ({v})" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))
            rng = f"{fmt(min(ratios))} .. {fmt(max(ratios))}" if ratios else "n/a"
            out.append(f"| {system} | {_pct(level)} | {est} | {rng} |")
    return "\n".join(out) + "\n"


def integrated_table(result: dict) -> str:
    ie = result["summary"]["integrated_error"]
    if ie is None:
        return "_not measured in this run_\n"
    rows = [
        "| observation model | integrated error of F_hat (mean ± s.e.) | ratio to oracle | paired ratio "
        "(mean ± s.e.) | corrected / misspecified RMSE (mean ± s.e.) |",
        "|---|---|---|---|---|",
        f"| oracle: exact derivatives + noise std {ie['oracle_noise_std']:g} (paper 5.1) | "
        f"{_pm(ie['oracle']['mean'], ie['oracle']['se'])} | 1 | 1 | "
        f"{_pm(ie['oracle'].get('trajectory_ratio_mean'), ie['oracle'].get('trajectory_ratio_se'))} |",
    ]
    for m in METHODS:
        rows.append(
            f"| states, {_pct(ie['noise'])} noise, {m} | {_pm(ie[m]['mean'], ie[m]['se'])} | "
            f"{fmt(ie[m]['ratio_to_oracle'])} | {_pm(ie[m]['paired_ratio_mean'], ie[m]['paired_ratio_se'])} | "
            f"{_pm(ie[m].get('trajectory_ratio_mean'), ie[m].get('trajectory_ratio_se'))} |"
        )
    return "\n".join(rows) + "\n"


def goal_lines(result: dict) -> str:
    return (
        "\n".join(
            f"- **{'PASS' if g['pass'] else 'FAIL'}** {g['goal']} ({g['evidence']})" for g in result["summary"]["goals"]
        )
        + "\n"
    )


def test_table(result: dict) -> str:
    rows = [
        "| system | T | span | IC box | misspecified RMSE on the test set | RMS of the true test states |",
        "|---|---|---|---|---|---|",
    ]
    cfg = {c["name"]: c for c in result["config"]["systems"]}
    for name, t in result["raw"]["test_sets"].items():
        c = cfg[name]
        rows.append(
            f"| {name} | {c['T']} | [0, {c['t_end']:g}] | {' x '.join(f'[{lo:g}, {hi:g}]' for lo, hi in c['box'])} | "
            f"{fmt(t['misspecified_rmse'])} | {fmt(t['true_rms'])} |"
        )
    return "\n".join(rows) + "\n"


def _commit(mach: dict) -> str:
    if not mach.get("git_commit"):
        return ""
    return f" (commit {mach['git_commit']}{', with local changes' if mach.get('library_modified') else ''})"


def render_page(result: dict) -> str:
    cfg, mach = result["config"], result["machine"]
    systems = "\n".join(f"- **{c['name']}**: {c['description']}" for c in cfg["systems"])
    return f"""# Study: learning the correction from noisy, sparsely sampled states

This page is written by `{result["command"]}` (issue 9, "Measured goals"); every number on it comes from that run,
whose raw per-run numbers are in `benchmarks/study_observations.json`. Machine: {mach["cpu"]}, {mach["logical_cpus"]}
logical CPUs, torch {mach["torch"]}, torchmisspec {mach["torchmisspec"]}{_commit(mach)}, Python {mach["python"]}. Wall
time of the run: {result["wall_seconds"] / 60:.1f} min.

## Set-up

What a user with recorded states would run, on four systems (the last three are defined in the study script, not
in the package):

{systems}

For each system, K = {", ".join(map(str, cfg["ks"]))} training experiments from initial conditions drawn uniformly
in the box below (the K experiments of a realization are the first K of {max(cfg["ks"])}), observed at T equally
spaced times, with Gaussian state noise of {", ".join(_pct(x) for x in cfg["noise_levels"])} of each component's
RMS added to the simulated true states; {cfg["realizations"]} realizations (seeds) per cell. Per run:

- **auto**: `fit_correction(trajectories, system)`: `correction_samples` with `derivative="auto"`, then the model
  chosen by cross-validation on held-out experiments among RBF GPs over a grid of lengthscales (output scale and
  noise by marginal likelihood) and a feature kernel over the monomials up to degree 3 with automatic relevance
  (term weights by evidence); a chosen feature kernel is refined through the ODE by `fit_trajectories`, which
  re-learns its term weights from the trajectories -> `CorrectedODE(system, gp).predict`;
- **fit_trajectories**: `fit_trajectories(gp, system, trajectories, max_iter={cfg["fit_max_iter"]})` from the auto
  fit; where auto chose the feature kernel, auto already is its trajectory fit and the two columns agree.

Metric: the corrected / misspecified trajectory RMSE ratio on {cfg["n_test"]} new initial conditions from the same
box (a separate seed), on {cfg["test_times"]} equally spaced times of the same span; truth from `simulate(system,
...)`, the misspecified model from `simulate(..., known_only=True)`. "warnings" counts the runs in which
`fit_correction` issued a `TorchMisspecWarning` that the data cannot support a correction: the estimator
self-check of `correction_samples` above {cfg["threshold"]}, or no cross-validated correction predicting held-out
experiments better than the known model. Where the misspecified model diverges (its test RMSE in the table below
far above the RMS of the true states), the ratio is small whatever the correction; the column "RMSE / RMS(truth)"
(corrected RMSE over the RMS
of the true test states) then tells how good the corrected model is. A run that raises (e.g. `IntegrationError` when
the corrected model blows up on a test initial condition) is counted as failed, with its message in the JSON.

{test_table(result)}
## Goals

{goal_lines(result)}
## Corrected / misspecified RMSE ratio (mean ± standard error over realizations)

{summary_table(result)}
## Estimator chosen by `derivative="auto"`

{estimator_table(result)}
## Integrated error of F_hat on paper_linear

K = {cfg["oracle_k"]}, state noise {_pct(cfg["oracle_noise"])} for the state-based methods; the oracle uses the
same initial conditions with the paper's observation model (exact derivatives plus Gaussian noise of std
{cfg["oracle_noise_std"]:g}, as in paper 5.1) and the same default GP fitted by marginal likelihood.

{integrated_table(result)}"""


def render_block(result: dict) -> str:
    return f"""{MARK_START}
## Study: correction from noisy, sparsely sampled states (issue 9)

Written by `{result["command"]}` on {result["machine"]["cpu"]} ({result["machine"]["logical_cpus"]} logical CPUs,
torch {result["machine"]["torch"]}) in {result["wall_seconds"] / 60:.1f} min; the full page, with the set-up and the
estimator choices, is `docs/studies/real-data.md`, the raw numbers `benchmarks/study_observations.json`.

{goal_lines(result)}
Corrected / misspecified trajectory RMSE ratio on {result["config"]["n_test"]} new initial conditions (mean ±
standard error over {result["config"]["realizations"]} realizations):

{summary_table(result)}
Integrated error of F_hat on paper_linear:

{integrated_table(result)}{MARK_END}
"""


def _finite_json(obj):
    """inf / nan -> strings, so that the JSON is standard."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if isinstance(obj, dict):
        return {str(k): _finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_json(v) for v in obj]
    return obj


def _from_json(obj):
    """Inverse of :func:`_finite_json`."""
    if isinstance(obj, str) and obj in ("inf", "-inf", "nan"):
        return float(obj)
    if isinstance(obj, dict):
        return {k: _from_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_from_json(v) for v in obj]
    return obj


def write_result(result: dict, path: Path) -> None:
    """The result as standard JSON (inf and nan as strings)."""
    path.write_text(json.dumps(_finite_json(result), indent=1, allow_nan=False) + "\n")


def write_markdown(result: dict) -> None:
    write_page(DOC_PAGE, render_page(result))
    update_benchmarks(render_block(result), MARK_START, MARK_END, BENCHMARKS_MD)
    print(f"wrote {DOC_PAGE} and the study block of {BENCHMARKS_MD}")


def merge(args) -> int:
    """``--merge``: join the JSONs of full runs on disjoint systems into one result (``args`` from the script)."""
    parser = args.parser
    parts = [_from_json(json.loads(Path(f).read_text())) for f in args.merge]
    if any(p["smoke"] for p in parts):
        parser.error("--merge: the JSONs must come from full runs, not --smoke")
    names = [c["name"] for p in parts for c in p["config"]["systems"]]
    if len(set(names)) != len(names):
        parser.error(f"--merge: expected runs on disjoint systems, got {names}")
    keys = [k for k in parts[0]["config"] if k != "systems"]
    if any(p["config"][k] != parts[0]["config"][k] for p in parts for k in keys):
        parser.error("--merge: the runs used different settings (config differs besides the systems)")
    order = [c.name for c in CASES]
    systems = sorted((c for p in parts for c in p["config"]["systems"]), key=lambda c: order.index(c["name"]))
    raw = {
        "runs": [r for p in parts for r in p["raw"]["runs"]],
        "oracle_runs": [r for p in parts for r in p["raw"]["oracle_runs"]],
        "test_sets": {k: v for p in parts for k, v in p["raw"]["test_sets"].items()},
    }
    result = dict(parts[0], raw=raw, config=dict(parts[0]["config"], systems=systems))
    result["command"] = (
        " ; ".join(p["command"] for p in parts)
        + " (in parallel), then "
        + ("python scripts/study_observations.py --merge " + " ".join(args.merge))
    )
    result["wall_seconds"] = max(p["wall_seconds"] for p in parts)
    cfg = result["config"]
    cases = [c for c in CASES if c.name in {x["name"] for x in systems}]
    result["summary"] = summarise(raw, cases, cfg["ks"], cfg["noise_levels"], cfg["oracle_k"])
    print(summary_table(result))
    print(goal_lines(result))
    write_result(result, Path(args.json) if args.json else DEFAULT_JSON)
    if args.markdown:
        write_markdown(result)
    return 0


def from_json(args) -> int:
    """``--from-json``: recompute the summary of a saved full run, print it, and with ``--markdown`` write the pages."""
    parser = args.parser
    result = _from_json(json.loads(Path(args.from_json).read_text()))
    if result["smoke"]:
        parser.error("--from-json: that JSON is from a --smoke run; the pages are written from full runs only")
    cfg = result["config"]
    cases = [c for c in CASES if c.name in {x["name"] for x in cfg["systems"]}]
    result["summary"] = summarise(result["raw"], cases, cfg["ks"], cfg["noise_levels"], cfg["oracle_k"])
    print(summary_table(result))
    print(goal_lines(result))
    print(integrated_table(result))
    if args.markdown:
        write_markdown(result)
    return 0


def run(args, command: str) -> int:
    """A fresh run (``args`` from the script; ``command`` how it was called): prints the summary, writes the JSON and
    with ``--markdown`` the pages."""
    cases = [c for c in CASES if not args.systems or c.name in args.systems]
    if args.smoke:
        ks, levels, realizations, n_test = (5,), (ORACLE_NOISE,), args.realizations or 1, 5
        fit_max_iter, oracle_k = args.fit_max_iter or 5, 5  # the oracle comparison at the one K that runs
    else:
        ks, levels, realizations, n_test = KS, NOISE_LEVELS, args.realizations or REALIZATIONS, N_TEST
        fit_max_iter, oracle_k = args.fit_max_iter or FIT_MAX_ITER, ORACLE_K
    t0 = time.perf_counter()
    raw = study(
        cases,
        ks,
        levels,
        realizations,
        n_test,
        fit_max_iter=fit_max_iter,
        oracle_k=oracle_k,
    )
    wall = time.perf_counter() - t0
    result = {
        "command": command.strip(),
        "machine": machine(),
        "smoke": args.smoke,
        "wall_seconds": wall,
        "config": {
            "ks": list(ks),
            "noise_levels": list(levels),
            "realizations": realizations,
            "n_test": n_test,
            "test_times": TEST_TIMES,
            "fit_max_iter": fit_max_iter,
            "threshold": ESTIMATOR_ERROR_THRESHOLD,
            "ratio_goal": RATIO_GOAL,
            "ratio_never": RATIO_NEVER,
            "oracle_k": oracle_k,
            "oracle_noise": ORACLE_NOISE,
            "oracle_noise_std": paper_setup.NOISE_STD,
            "oracle_factor": ORACLE_FACTOR,
            "seed": SEED,
            "test_seed": TEST_SEED,
            "systems": [
                {
                    "name": c.name,
                    "T": c.T,
                    "t_end": c.t_end,
                    "box": [list(b) for b in c.box],
                    "description": c.description,
                }
                for c in cases
            ],
        },
        "raw": raw,
    }
    result["summary"] = summarise(raw, cases, ks, levels, oracle_k)
    print(f"\nwall time {wall:.1f} s\n")
    print(summary_table(result))
    print(goal_lines(result))
    print(integrated_table(result))
    json_path = Path(args.json) if args.json else (None if args.smoke else DEFAULT_JSON)
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        write_result(result, json_path)
        print(f"wrote {json_path}")
    if args.markdown:
        write_markdown(result)
    return 0
