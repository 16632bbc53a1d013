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

This module runs the study; :mod:`torchmisspec.paper.study_observations_report` summarises and writes it
(``scripts/study_observations.py`` is its command line).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import torch

import torchmisspec as tms
from torchmisspec.learning.samples.observations import choose_derivative

from . import _setup as paper_setup

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
    if gp.kernel_spec.terms:
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
    # fit_correction already refined the feature kernel through the ODE: (b) is (a)
    if gp.kernel_spec.terms and gp.kernel_spec.feature_space:
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


def fmt(x, spec=".3g") -> str:
    """A number for the tables (``nan`` for None or a non-finite value)."""
    return "nan" if x is None or not math.isfinite(x) else format(x, spec)


def _run_line(rec: dict) -> str:
    a, f = rec["auto"], rec["fit_trajectories"]
    ra = fmt(a["ratio"]) if a["status"] == "ok" else "ERR"
    rf = fmt(f["ratio"]) if f["status"] == "ok" else "ERR"
    return (
        f"  {rec['system']:16s} K={rec['K']:2d} noise={rec['noise']:<6g} r={rec['realization']} "
        f"est={rec['estimator']['label']:22s} ({fmt(rec.get('estimator_ratio'))}) warn={int(rec.get('warning', 0))} "
        f"auto={ra:>8s} fit={rf:>8s}  {rec['seconds']:.1f}s"
        + ("" if a["status"] == "ok" else f"  [auto: {a['error'][:120]}]")
        + ("" if f["status"] == "ok" else f"  [fit: {f['error'][:120]}]")
    )
