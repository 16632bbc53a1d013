"""Study of issue 42 (item 3): a parameter F can stand in for, with inputs, held out.

A chemostat the package does not ship elsewhere, whose temperature the lab sets: biomass X (g/L) and substrate S
(g/L) over 24 h, two known inputs, the dilution rate D (1/h) and the temperature T (degrees C), each piecewise
constant on three 8 h blocks per experiment; Monod growth mu(S) = 0.6 S / (0.4 + S) per hour, and

    dX/dt = mu(S) X - D X - (ln 2 / h) X + F(X, T),        dS/dt = D (Sf - S) - mu(S) X / Y,

with three uncertain parameters of G: the cells' half-life h (true 20 h, prior 14 +- 6 h), the yield Y (true 0.5,
prior 0.4 +- 0.15) and the feed concentration Sf (true 3.0 g/L, prior 2.5 +- 0.8). G is nonlinear in h and Y. The
missing term is thermal death, F(X, T) = -0.02 exp(0.15 (T - 30)) X: a function of the states and the input that can
stand in for the half-life's term -(ln 2 / h) X exactly (both are a rate times X), so the data cannot tell h from F.
The fit must say so, and must never report h identified with the truth more than 3 posterior standard deviations
away. Y and Sf act on dS/dt, which F does not touch.

Each realization: 8 experiments x 13 times (every 2 h), 1 % multiplicative state noise, fitted with the defaults
(``fit_correction``); predictions on 20 new initial states under new dilution and temperature profiles, against the
true system, over the same 24 h and beyond it (to 36 h, the last block's inputs held). Reported: the share of
realizations that warned about h; those that reported h identified, and among them how far the truth was in posterior
standard deviations; each parameter's estimate; the corrected model's RMSE over G's alone at the priors' means (the
scientist's model as written), on the data's span and beyond it.

Two peers on the same data, scored the same way: the classical answer (G with h, Y and Sf fitted through the ODE to
the logs of the states, F = 0) and a parametric oracle (the truth's own form, with the thermal death's rate a as a
fourth coefficient, fitted the same way). The oracle shows what these data can give when the missing term's form is
known: the temperature profiles separate a from h, which a correction F(X, T) learned from the data must do too.
"""

from __future__ import annotations

import math
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.paper.oracle import fitted_through_ode

from ._ratios import describe, paired_ratio

DEFAULT_JSON = ROOT / "benchmarks" / "study_absorbed.json"
DOC_PAGE = ROOT / "docs" / "studies" / "absorbed.md"
MARK_START = "<!-- study:absorbed:start -->"
MARK_END = "<!-- study:absorbed:end -->"
DT = torch.float64
SEED = 42_300
MU_MAX, K_S = 0.6, 0.4
TRUE = {"h": 20.0, "Y": 0.5, "Sf": 3.0}
PRIORS = {"h": (14.0, 6.0), "Y": (0.4, 0.15), "Sf": (2.5, 0.8)}
FULL = {"realizations": 10, "experiments": 8, "times": 13, "n_test": 20}
SMOKE = {"realizations": 1, "experiments": 6, "times": 13, "n_test": 4}
GOALS = {"warned": 0.9, "rmse_vs_known": 0.1}
#: The peers measured on the same data: G with h, Y and Sf fitted through the ODE and F = 0 (the classical answer),
#: and the truth's own form with its four coefficients fitted the same way (the parametric oracle).
PEERS = {"classical": "G, parameters fitted, F = 0 (classical)", "oracle": "the truth's form fitted (oracle)"}
#: the forecast beyond the data: to this many hours (the data end at 24)
HORIZON = 36.0


def known(t, y, u, theta):
    """G(t, y, u; h, Y, Sf): Monod growth, dilution, death at half-life h; uptake through the yield Y, feed Sf."""
    X, S = y[..., 0], y[..., 1]
    mu = MU_MAX * S / (K_S + S)
    D = u[..., 0]
    return torch.stack([mu * X - D * X - math.log(2) / theta[0] * X, D * (theta[2] - S) - mu * X / theta[1]], -1)


def thermal_death(x):
    """F(X, T): the missing thermal death, ``x (..., 2)`` = (X, T)."""
    return -0.02 * torch.exp(0.15 * (x[..., 1:2] - 30.0)) * x[..., 0:1]


def system(*, truth: bool = False) -> tms.MisspecifiedSystem:
    """The chemostat as the scientist declares it (theta uncertain, F unknown), or the truth (``truth``)."""
    kw = dict(
        num_controls=2,
        control_names=["D", "T"],
        state_names=["X", "S"],
        correction_inputs=["X", "T"],
        correction_outputs=[0],
        name="chemostat with temperature",
    )
    if truth:
        theta = torch.tensor(list(TRUE.values()), dtype=DT)
        return tms.MisspecifiedSystem(lambda t, y, u: known(t, y, u, theta), 2, correction=thermal_death, **kw)
    return tms.MisspecifiedSystem(known, 2, parameters=PRIORS, **kw)


def experiments(n: int, g: torch.Generator) -> tuple[torch.Tensor, tms.Controls]:
    """``n`` initial states, dilution levels in [0.05, 0.3] and temperatures in [24, 36] on [0, 8), [8, 16) and
    [16, 24)."""
    y0 = torch.stack(
        [0.2 + 1.0 * torch.rand(n, generator=g, dtype=DT), 0.5 + 2.0 * torch.rand(n, generator=g, dtype=DT)], -1
    )
    D = 0.05 + 0.25 * torch.rand(n, 3, 1, generator=g, dtype=DT)
    T = 24.0 + 12.0 * torch.rand(n, 3, 1, generator=g, dtype=DT)
    return y0, tms.Controls(torch.tensor([0.0, 8.0, 16.0], dtype=DT), torch.cat([D, T], -1), names=["D", "T"])


def oracle_system() -> tms.MisspecifiedSystem:
    """The truth's own form with its four coefficients uncertain: G's h, Y and Sf (their priors) and the thermal
    death's rate at 30 degrees C, a (true 0.02, prior 0 +- 0.05): what a scientist who knew the missing term's form
    would fit, F = 0."""

    def rhs(t, y, u, theta):
        base = known(t, y, u, theta[:3])
        death = -theta[3] * torch.exp(0.15 * (u[..., 1] - 30.0)) * y[..., 0]
        return torch.stack([base[..., 0] + death, base[..., 1]], -1)

    kw = dict(num_controls=2, control_names=["D", "T"], state_names=["X", "S"], name="chemostat, the truth's form")
    return tms.MisspecifiedSystem(rhs, 2, parameters={**PRIORS, "a": (0.0, 0.05)}, **kw)


def _fit(data, sys_):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        gp = tms.fit_correction(data, sys_, progress=False)
        seconds = time.perf_counter() - t0
    return gp, seconds, [str(w.message) for w in caught if issubclass(w.category, tms.TorchMisspecWarning)]


def run_one(task: tuple[int, dict]) -> dict:
    """One realization ``(seed, config)``: simulate, fit with defaults, predict held out."""
    seed, cfg = task
    g = torch.Generator().manual_seed(seed)
    truth, declared = system(truth=True), system()
    t = torch.linspace(0, 24, cfg["times"], dtype=DT)
    y0, u = experiments(cfg["experiments"], g)
    clean = tms.simulate(truth, y0, t, controls=u).states
    noisy = clean * (1 + 0.01 * torch.randn(clean.shape, generator=g, dtype=DT))
    data = tms.Trajectories(t, noisy, controls=u, state_names=["X", "S"])
    gp, seconds, seen = _fit(data, declared)
    post = gp.parameters_
    y0n, un = experiments(cfg["n_test"], g)
    out = {"seed": seed, "fit_seconds": seconds, "names": list(post.names), "mean": post.mean.tolist()}
    out |= {"sd": post.stddev.tolist(), "identified": list(post.identified), "moved": post.moved.tolist()}
    larger = post.sd_larger_correction
    out["sd_larger_correction"] = None if larger is None else larger.tolist()
    true = torch.tensor(list(TRUE.values()), dtype=DT)
    out["truth_sd"] = ((post.mean - true).abs() / post.stddev).tolist()
    out["warned_h"] = any("h: " in w and "not determined" in w for w in seen)
    out["known_model"] = bool(gp.known_model_)  # do no harm returned G alone (F = 0)
    model = tms.CorrectedODE(declared, gp)
    classical = fitted_through_ode(declared, data, "relative")
    oracle = fitted_through_ode(oracle_system(), data, "relative")
    for label, span in (("rmse", (0.0, 24.0)), ("rmse_beyond", (24.0, HORIZON))):
        tt = torch.linspace(0.0, span[1], 4 * int(span[1] / 2) + 1, dtype=DT)
        keep = tt >= span[0]
        ref = tms.simulate(truth, y0n, tt, controls=un).states[:, keep]
        known_only = tms.simulate(declared, y0n, tt, controls=un, known_only=True).states[:, keep]
        predicted = model.predict(y0n, tt, controls=un)[:, keep]
        out[label] = float(tms.trajectory_rmse(predicted, ref))
        out[label + "_known"] = float(tms.trajectory_rmse(known_only, ref))
        for peer, sys_ in (("classical", classical), ("oracle", oracle)):
            path = tms.simulate(sys_, y0n, tt, controls=un, known_only=True).states[:, keep]
            out[f"{label}_{peer}"] = float(tms.trajectory_rmse(path, ref))
    out["warnings"] = seen
    return out


def study(cfg: dict, log=print, executor=None) -> dict:
    from torchmisspec.parallel import map_tasks

    seeds = [SEED + r for r in range(cfg["realizations"])]
    runs = map_tasks(run_one, [(s, cfg) for s in seeds], executor=executor)
    for r, one in enumerate(runs):
        est = ", ".join(f"{n} {m:.3g} +- {s:.2g}" for n, m, s in zip(one["names"], one["mean"], one["sd"], strict=True))
        log(f"{r}: {est}; warned h {one['warned_h']}; rmse / known {one['rmse'] / one['rmse_known']:.3f}")
    return {"config": cfg, "runs": runs, "priors": PRIORS, "true": TRUE, "goals": GOALS}


def table(result: dict) -> str:
    runs, n = result["runs"], len(result["runs"])
    warned = sum(r["warned_h"] for r in runs)
    ident = [r for r in runs if r["identified"][0]]
    far = [r for r in ident if r["truth_sd"][0] > 3]
    ratio = describe(paired_ratio([r["rmse"] for r in runs], [r["rmse_known"] for r in runs]))
    beyond = describe(paired_ratio([r["rmse_beyond"] for r in runs], [r["rmse_beyond_known"] for r in runs]))
    lines = [
        "| measure | value | goal |",
        "|---|---|---|",
        f"| h warned not determined | {warned} of {n} | >= {GOALS['warned']:.0%} |",
        f"| h reported identified | {len(ident)} of {n}, {len(far)} with the truth > 3 sd away | none > 3 sd |",
        f"| a correction kept (not the known model alone) | {sum(not r.get('known_model', True) for r in runs)} of {n} "
        "| |",
        f"| corrected / known RMSE, new inputs, 0-24 h | {ratio} | <= {GOALS['rmse_vs_known']} |",
        f"| corrected / known RMSE, beyond the data, 24-{HORIZON:.0f} h | {beyond} | |",
        *[
            f"| {what} / known RMSE, new inputs, 0-24 h | "
            f"{describe(paired_ratio([r['rmse_' + peer] for r in runs], [r['rmse_known'] for r in runs]))} | |"
            for peer, what in PEERS.items()
            if all("rmse_" + peer in r for r in runs)
        ],
        f"| fit seconds (median) | {sorted(r['fit_seconds'] for r in runs)[n // 2]:.1f} | |",
    ]
    return "\n".join(lines) + "\n"


def per_realization(result: dict) -> str:
    names = list(result["priors"])
    head = " | ".join(
        f"{k} (true {result['true'][k]}, prior {result['priors'][k][0]} +- {result['priors'][k][1]})" for k in names
    )
    lines = [f"| seed | {head} | h sd, F allowed larger | h warned | RMSE / known |", "|---" * (len(names) + 4) + "|"]
    for r in result["runs"]:
        ests = " | ".join(f"{m:.3g} +- {s:.2g}" for m, s in zip(r["mean"], r["sd"], strict=True))
        larger = r.get("sd_larger_correction")
        absorbed = "-" if larger is None else f"{larger[0]:.2g}"
        lines.append(f"| {r['seed']} | {ests} | {absorbed} | {r['warned_h']} | {r['rmse'] / r['rmse_known']:.3f} |")
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""{MARK_START}
## A parameter F can stand in for, with inputs, held out (`scripts/study_absorbed.py`)

Written by `python scripts/study_absorbed.py --markdown` ({wall / 60:.1f} min, {info["cpu"]}, {info["logical_cpus"]}
logical CPUs): a chemostat with dilution and temperature inputs, three uncertain parameters of G, thermal death
missing, {result["config"]["realizations"]} realizations; see [docs/studies/absorbed.md](docs/studies/absorbed.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""# Study: a parameter F can stand in for, with inputs, held out

This page is written by `python scripts/study_absorbed.py --markdown`; every number on it comes from that run (raw
numbers: `benchmarks/study_absorbed.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs, torch
{info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
{per_realization(result)}"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
