"""Study of issue 9: learning the correction from noisy, sparsely sampled *states* instead of exact derivatives.

For four systems (the paper's linear system and three that are not in the package: a pendulum with unknown
friction, FitzHugh-Nagumo with its cubic term unknown, Lotka-Volterra with a missing logistic prey term), K = 5,
10, 20 training experiments from random initial conditions, and state noise of 0, 0.1 % and 1 % of each
component's RMS, every realization runs what a user would run:

* (a) ``fit_correction(trajectories, system)``: ``correction_samples`` with ``derivative="auto"``, then the model
  chosen by cross-validation on held-out experiments among RBF GPs over a grid of lengthscales and a feature kernel
  with automatic relevance (which ``fit_correction`` then refines through the ODE), the package's defaults ->
  ``CorrectedODE(system, gp).predict``;
* (b) ``fit_trajectories(gp, system, trajectories)`` starting from (a); where (a) chose the feature kernel, (a) is
  already its trajectory fit and (b) is (a).

It records which estimator ``auto`` chose (``choose_derivative``, deterministic, called again for the record) and
whether ``fit_correction`` issued a ``TorchMisspecWarning`` (data that cannot support a correction). The
metric is the corrected / misspecified trajectory RMSE ratio on 25 new initial conditions. On paper_linear the
integrated error of F_hat is also compared with the paper's oracle observation model (exact derivatives + noise).

Usage::

    python scripts/study_observations.py --markdown     # full study: JSON, docs/studies/real-data.md, BENCHMARKS.md
    python scripts/study_observations.py --smoke --json /tmp/s.json   # tiny, < 1 min, never writes docs

Every number in the written pages comes from the run.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine, replace_marked  # noqa: E402 (the scripts' shared helper)

import torchmisspec as tms  # noqa: E402
from torchmisspec.metrics import mean_and_standard_error
from torchmisspec.observations import ESTIMATOR_ERROR_THRESHOLD, choose_derivative
from torchmisspec.paper import _setup as paper_setup

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_JSON = ROOT / "benchmarks" / "study_observations.json"
DOC_PAGE = ROOT / "docs" / "studies" / "real-data.md"
BENCHMARKS_MD = ROOT / "BENCHMARKS.md"
MARK_START = "<!-- study:observations:start -->"
MARK_END = "<!-- study:observations:end -->"

DT = torch.float64
KS = (5, 10, 20)
NOISE_LEVELS = (0.0, 1e-3, 1e-2)  # state noise std relative to each component's RMS
REALIZATIONS = 5
N_TEST = 25
TEST_TIMES = 101  # output grid of the test predictions
RATIO_GOAL = 0.3  # mean corrected / misspecified RMSE at K >= 10
RATIO_NEVER = 1.0  # no run above this without the warning
ORACLE_FACTOR = 2.0  # paper_linear integrated error within this factor of the oracle's
ORACLE_K = 20
ORACLE_NOISE = 1e-2  # state noise level of the integrated-error goal
SEED = 20260
TEST_SEED = 90210
FIT_MAX_ITER = 30  # fit_trajectories' default

# ------------------------------------------------------------------------------------------------- systems
PENDULUM_G, PENDULUM_FRICTION = 9.81, 0.3
FHN = {"a": 0.7, "b": 0.8, "eps": 0.08, "I": 0.5}
LV = {"a": 1.0, "b": 0.5, "c": 1.0, "d": 0.5, "K_cap": 10.0}


def pendulum() -> tms.MisspecifiedSystem:
    """G = [w, -9.81 sin x], unknown friction F(w) = -0.3 w on the velocity equation."""
    return tms.MisspecifiedSystem(
        lambda y: torch.stack([y[..., 1], -PENDULUM_G * torch.sin(y[..., 0])], -1),
        2,
        correction=lambda w: -PENDULUM_FRICTION * w,
        correction_inputs=[1],
        correction_outputs=[1],
        domain=((-1.0, 1.0),),
        name="pendulum",
    )


def fitzhugh_nagumo() -> tms.MisspecifiedSystem:
    """v' = v - w + I + F(v), w' = eps (v + a - b w); unknown cubic F(v) = -v^3 / 3 on v'."""
    a, b, eps, current = FHN["a"], FHN["b"], FHN["eps"], FHN["I"]
    return tms.MisspecifiedSystem(
        lambda y: torch.stack([y[..., 0] - y[..., 1] + current, eps * (y[..., 0] + a - b * y[..., 1])], -1),
        2,
        correction=lambda v: -(v**3) / 3.0,
        correction_inputs=[0],
        correction_outputs=[0],
        domain=((-2.0, 2.0),),
        name="fitzhugh_nagumo",
    )


def lotka_volterra() -> tms.MisspecifiedSystem:
    """x' = a x - b x y + F(x), y' = -c y + d x y; unknown logistic F(x) = -a x^2 / K_cap on x'."""
    a, b, c, d, cap = LV["a"], LV["b"], LV["c"], LV["d"], LV["K_cap"]
    return tms.MisspecifiedSystem(
        lambda y: torch.stack(
            [a * y[..., 0] - b * y[..., 0] * y[..., 1], -c * y[..., 1] + d * y[..., 0] * y[..., 1]], -1
        ),
        2,
        correction=lambda x: -a * x**2 / cap,
        correction_inputs=[0],
        correction_outputs=[0],
        domain=((0.5, 3.0),),
        name="lotka_volterra",
    )


@dataclass(frozen=True)
class Case:
    """A system of the study with its initial-condition box (per state component) and observation grid."""

    name: str
    make: object  # () -> MisspecifiedSystem
    box: tuple[tuple[float, float], ...]
    t_end: float
    T: int
    description: str

    @property
    def system(self) -> tms.MisspecifiedSystem:
        return self.make()

    def times(self) -> torch.Tensor:
        return torch.linspace(0.0, self.t_end, self.T, dtype=DT)

    def test_times(self) -> torch.Tensor:
        return torch.linspace(0.0, self.t_end, TEST_TIMES, dtype=DT)


CASES = (
    Case(
        "paper_linear",
        tms.systems.paper_linear,
        ((-1.0, 1.0), (-1.0, 1.0)),
        6.0,
        11,
        "paper 5.1: G(y) = A y, F(y) = 0.01 [y1^2, y2^2] on both components",
    ),
    Case(
        "pendulum",
        pendulum,
        ((-1.0, 1.0), (-1.0, 1.0)),
        4.0,
        21,
        f"G = [w, -{PENDULUM_G} sin x], F(w) = -{PENDULUM_FRICTION} w on w'",
    ),
    Case(
        "fitzhugh_nagumo",
        fitzhugh_nagumo,
        ((-2.0, 2.0), (-0.5, 1.5)),
        20.0,
        21,
        f"G = [v - w + I, eps (v + a - b w)], F(v) = -v^3/3 on v' (a={FHN['a']}, b={FHN['b']}, eps={FHN['eps']}, "
        f"I={FHN['I']}); one excitation (a fast jump of v) within the span",
    ),
    Case(
        "lotka_volterra",
        lotka_volterra,
        ((0.5, 3.0), (0.5, 3.0)),
        15.0,
        21,
        f"G = [a x - b x y, -c y + d x y], F(x) = -a x^2 / K_cap on x' (a={LV['a']}, b={LV['b']}, c={LV['c']}, "
        f"d={LV['d']}, K_cap={LV['K_cap']}); about two predator-prey cycles, states positive",
    ),
)


def _uniform(box, n: int, gen: torch.Generator) -> torch.Tensor:
    lo = torch.tensor([b[0] for b in box], dtype=DT)
    hi = torch.tensor([b[1] for b in box], dtype=DT)
    return lo + (hi - lo) * torch.rand(n, len(box), generator=gen, dtype=DT)


# ------------------------------------------------------------------------------------------------- one run
def _err(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def _gp_info(gp: tms.CorrectionGP) -> dict:
    def number(value):
        return None if value is None else _number_or_list(value)

    info = {
        "kernel": gp.kernel,
        "lengthscale": number(gp.lengthscale),
        "outputscale": number(gp.outputscale),
        "noise_variance": number(gp.noise_variance),
        "n_iterations": int(gp.n_iterations_),
    }
    if gp.kernel == "features":
        info["terms"] = [f"{t.output}: {t}" for t in gp.terms()]
    return info


def _evaluate(system, gp, test) -> dict:
    """Ratio of the corrected to the misspecified RMSE on the test set, and the corrected RMSE / RMS(truth)."""
    pred = tms.CorrectedODE(system, gp).predict(test["y0"], test["times"])
    rmse = float(tms.trajectory_rmse(pred, test["true"]))
    return {
        "ratio": rmse / test["misspecified_rmse"],
        "rmse": rmse,
        "relative_rmse": rmse / test["true_rms"],
    }


def run_one(case: Case, system, train: tms.Trajectories, test: dict, *, fit_max_iter: int) -> dict:
    """Methods (a) auto -> GP -> predict and (b) fit_trajectories on one data set; errors are recorded."""
    out: dict = {"auto": {"status": "error"}, "fit_trajectories": {"status": "error"}}
    # which estimator auto picks (choose_derivative is deterministic: the same choice correction_samples makes)
    try:
        t0 = time.perf_counter()
        name, options, errors = choose_derivative(train, system)
        out["estimator"] = {"name": name, "options": options, "label": _label(name, options)}
        out["estimator_errors"] = {_label(n, dict(o)): v for (n, o), v in errors.items()}
        out["estimator_ratio"] = errors[(name, tuple(sorted(options.items())))]
        out["choose_seconds"] = time.perf_counter() - t0
    except Exception as exc:  # noqa: BLE001 - recorded, the study goes on
        out["estimator"] = {"name": None, "options": {}, "label": "error"}
        out["estimator_error_message"] = _err(exc)
    gp = None
    try:
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            # derivative="auto" and the lengthscale by cross-validation on held-out experiments: the defaults
            gp = tms.fit_correction(train, system)
        data_warnings = [str(w.message) for w in caught if w.category is tms.TorchMisspecWarning]
        out["warning"] = bool(data_warnings)
        out["warning_messages"] = data_warnings
        cv = gp.cross_validation_
        out["auto"] = {"status": "ok", "fit_seconds": time.perf_counter() - t0, "gp": _gp_info(gp)}
        if cv is not None:
            out["auto"]["cross_validation"] = {"best": cv.best, "baseline": cv.baseline, "improves": cv.improves}
        out["auto"].update(_evaluate(system, gp, test))
        if system.domain is not None:
            out["auto"]["correction_error"] = tms.correction_error(gp, system)
        out["auto"]["warnings"] = _other(caught)
    except Exception as exc:  # noqa: BLE001
        out.setdefault("warning", False)
        out["auto"] = {"status": "error", "error": _err(exc)}
    if gp is None or not gp.is_fitted:
        out["fit_trajectories"] = {"status": "error", "error": "skipped: method (a) failed"}
        return out
    if gp.kernel == "features":  # fit_correction already refined it through the ODE: (b) is (a)
        out["fit_trajectories"] = dict(
            out["auto"],
            iterations=int(gp.n_iterations_),
            evaluations=int(gp.n_evaluations_),
            state_noise=_number_or_list(gp.state_noise_),
            note="the feature kernel: fit_correction's own trajectory fit",
        )
        return out
    try:
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            refined = tms.fit_trajectories(gp, system, train, max_iter=fit_max_iter)
        res = {
            "status": "ok",
            "fit_seconds": time.perf_counter() - t0,
            "iterations": int(refined.n_iterations_),
            "evaluations": int(refined.n_evaluations_),
            "state_noise": _number_or_list(refined.state_noise_),
            "warnings": _other(caught),
        }
        res.update(_evaluate(system, refined, test))
        if system.domain is not None:
            res["correction_error"] = tms.correction_error(refined, system)
        out["fit_trajectories"] = res
    except Exception as exc:  # noqa: BLE001
        out["fit_trajectories"] = {"status": "error", "error": _err(exc)}
    return out


def _number_or_list(value):
    """A float, or a list for a per-component tensor (fit_trajectories' state_noise_)."""
    if isinstance(value, torch.Tensor) and value.numel() != 1:
        return value.detach().tolist()
    return float(value)


def _other(caught) -> list[str]:
    """Recorded warnings other than correction_samples' data warning (e.g. NumericalWarning), de-duplicated."""
    return sorted({f"{w.category.__name__}: {w.message}" for w in caught if w.category is not tms.TorchMisspecWarning})


def _label(name: str, options: dict) -> str:
    if not options:
        return name
    return name + " " + ",".join(f"{k}={v}" for k, v in sorted(options.items()))


def make_test_set(case: Case, system, n_test: int) -> dict:
    gen = torch.Generator().manual_seed(TEST_SEED + CASES.index(case))
    y0 = _uniform(case.box, n_test, gen)
    times = case.test_times()
    true = tms.simulate(system, y0, times).states
    mis = tms.simulate(system, y0, times, known_only=True).states
    return {
        "y0": y0,
        "times": times,
        "true": true,
        "misspecified_rmse": float(tms.trajectory_rmse(mis, true)),
        "true_rms": float(true.pow(2).mean().sqrt()),
    }


def oracle_run(case: Case, system, clean: tms.Trajectories, seed: int, test: dict) -> dict:
    """The paper's observation model at the same initial conditions: exact derivatives + noise of std 1e-2."""
    try:
        gen = torch.Generator().manual_seed(seed)
        samples = tms.correction_samples(
            clean, system, derivative="oracle", noise_std=paper_setup.NOISE_STD, generator=gen
        )
        gp = tms.CorrectionGP().fit(samples)
        out = {"status": "ok", "correction_error": tms.correction_error(gp, system), "gp": _gp_info(gp)}
        out.update(_evaluate(system, gp, test))  # the trajectory ratio the oracle's correction reaches
        return out
    except Exception as exc:  # noqa: BLE001
        return {"status": "error", "error": _err(exc)}


# ------------------------------------------------------------------------------------------------- study
def study(
    cases,
    ks,
    noise_levels,
    realizations: int,
    n_test: int,
    *,
    fit_max_iter: int,
    oracle_k: int | None,
    log=print,
) -> dict:
    runs, oracle_runs, tests = [], [], {}
    kmax = max(ks)
    for case in cases:
        system = case.system
        t0 = time.perf_counter()
        test = make_test_set(case, system, n_test)
        tests[case.name] = {
            "n_test": n_test,
            "misspecified_rmse": test["misspecified_rmse"],
            "true_rms": test["true_rms"],
        }
        times = case.times()
        for r in range(realizations):
            seed = SEED + 1000 * CASES.index(case) + r
            gen = torch.Generator().manual_seed(seed)
            # nested data: the K experiments of a realization are the first K of kmax; one standard normal draw
            # serves every noise level (common random numbers across K and noise)
            y0 = _uniform(case.box, kmax, gen)
            clean_all = tms.simulate(system, y0, times)
            eps_all = torch.randn(clean_all.states.shape, generator=gen, dtype=DT)
            for K in ks:
                clean = clean_all[list(range(K))]
                rms = clean.states.pow(2).mean(dim=(0, 1)).sqrt()  # (d,) each component's RMS
                for level in noise_levels:
                    states = clean.states + level * rms * eps_all[:K]
                    train = tms.Trajectories(times, states)
                    t1 = time.perf_counter()
                    record = {
                        "system": case.name,
                        "K": K,
                        "noise": level,
                        "realization": r,
                        "seed": seed,
                    }
                    record.update(run_one(case, system, train, test, fit_max_iter=fit_max_iter))
                    record["seconds"] = time.perf_counter() - t1
                    runs.append(record)
                    log(_run_line(record))
                if case.name == "paper_linear" and K == oracle_k:
                    rec = {"system": case.name, "K": K, "realization": r, "seed": seed}
                    rec.update(oracle_run(case, system, clean, seed + 500, test))
                    oracle_runs.append(rec)
                    log(f"  oracle {case.name} K={K} r={r}: {rec.get('correction_error', rec.get('error'))}")
        log(f"--- {case.name}: {time.perf_counter() - t0:.1f} s")
    return {"runs": runs, "oracle_runs": oracle_runs, "test_sets": tests}


def _fmt(x, spec=".3g") -> str:
    return "nan" if x is None or not math.isfinite(x) else format(x, spec)


def _run_line(rec: dict) -> str:
    a, f = rec["auto"], rec["fit_trajectories"]
    ra = _fmt(a["ratio"]) if a["status"] == "ok" else "ERR"
    rf = _fmt(f["ratio"]) if f["status"] == "ok" else "ERR"
    return (
        f"  {rec['system']:16s} K={rec['K']:2d} noise={rec['noise']:<6g} r={rec['realization']} "
        f"est={rec['estimator']['label']:22s} ({_fmt(rec.get('estimator_ratio'))}) warn={int(rec.get('warning', 0))} "
        f"auto={ra:>8s} fit={rf:>8s}  {rec['seconds']:.1f}s"
        + ("" if a["status"] == "ok" else f"  [auto: {a['error'][:120]}]")
        + ("" if f["status"] == "ok" else f"  [fit: {f['error'][:120]}]")
    )


# ------------------------------------------------------------------------------------------------- summary
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
                f"{_fmt(worst[m]['ratio_mean'])} +- {_fmt(worst[m]['ratio_se'])}"
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
                    f"{r['system']} K={r['K']} {_pct(r['noise'])} r={r['realization']} {m}: ratio {_fmt(res['ratio'])}"
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
                    "evidence": f"{_fmt(ie[m]['mean'])} +- {_fmt(ie[m]['se'])} vs oracle {_fmt(ie['oracle']['mean'])} "
                    f"+- {_fmt(ie['oracle']['se'])}: ratio {_fmt(ie[m]['ratio_to_oracle'])}",
                }
            )
    return lines


def _pct(level: float) -> str:
    return f"{100 * level:g} %"


# ------------------------------------------------------------------------------------------------- markdown
def _pm(mean, se) -> str:
    return "n/a" if mean is None else f"{_fmt(mean)} ± {_fmt(se, '.2g')}"


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
            f"{_cell_ratio(c, 'fit_trajectories')} | {_fmt(c['auto']['ratio_max'])} / "
            f"{_fmt(c['fit_trajectories']['ratio_max'])} | {_fmt(c['auto']['relative_rmse_mean'])} / "
            f"{_fmt(c['fit_trajectories']['relative_rmse_mean'])} | {c['warnings']}/{c['realizations']} | {est} |"
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
            rng = f"{_fmt(min(ratios))} .. {_fmt(max(ratios))}" if ratios else "n/a"
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
            f"{_fmt(ie[m]['ratio_to_oracle'])} | {_pm(ie[m]['paired_ratio_mean'], ie[m]['paired_ratio_se'])} | "
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
            f"{_fmt(t['misspecified_rmse'])} | {_fmt(t['true_rms'])} |"
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


def replace_block(text: str, block: str) -> str:
    """Replace this script's block of BENCHMARKS.md (markers included), or append it."""
    return replace_marked(text, block, MARK_START, MARK_END)


# ------------------------------------------------------------------------------------------------- main
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


def write_markdown(result: dict) -> None:
    DOC_PAGE.parent.mkdir(parents=True, exist_ok=True)
    DOC_PAGE.write_text(render_page(result))
    text = BENCHMARKS_MD.read_text() if BENCHMARKS_MD.exists() else ""
    BENCHMARKS_MD.write_text(replace_block(text, render_block(result)))
    print(f"wrote {DOC_PAGE} and the study block of {BENCHMARKS_MD}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--smoke", action="store_true", help="tiny: every system, K = 5, one noise level, 1 realization"
    )
    parser.add_argument(
        "--json",
        help=f"write raw runs and summary here (default {DEFAULT_JSON.relative_to(ROOT)}; "
        "with --smoke only when given)",
    )
    parser.add_argument(
        "--markdown",
        action="store_true",
        help="rewrite docs/studies/real-data.md and the study block of BENCHMARKS.md (not with --smoke)",
    )
    parser.add_argument(
        "--realizations", type=int, default=None, help=f"realizations per cell (default {REALIZATIONS})"
    )
    parser.add_argument(
        "--fit-max-iter", type=int, default=None, help=f"fit_trajectories max_iter (default {FIT_MAX_ITER})"
    )
    parser.add_argument("--systems", nargs="+", choices=[c.name for c in CASES], help="only these systems")
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="do not run: join the JSONs of full runs on disjoint --systems (run in parallel processes) into one "
        "result, written to --json (default the study's JSON) and, with --markdown, to the pages",
    )
    parser.add_argument(
        "--from-json",
        help="do not run: recompute the summary from this JSON of a full run and rewrite the pages (with --markdown)",
    )
    args = parser.parse_args(argv)
    if args.merge:
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
        json_path = Path(args.json) if args.json else DEFAULT_JSON
        json_path.write_text(json.dumps(_finite_json(result), indent=1, allow_nan=False) + "\n")
        if args.markdown:
            write_markdown(result)
        return 0
    if args.from_json:
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
    if args.smoke and args.markdown:
        parser.error("--markdown writes the docs and BENCHMARKS.md: not with --smoke")
    command = "python scripts/study_observations.py " + " ".join(argv if argv is not None else sys.argv[1:])
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
        json_path.write_text(json.dumps(_finite_json(result), indent=1, allow_nan=False) + "\n")
        print(f"wrote {json_path}")
    if args.markdown:
        write_markdown(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
