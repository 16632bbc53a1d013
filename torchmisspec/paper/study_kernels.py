"""Study of issue 12: CorrectionGP kernels (RBF, feature library, features+RBF, chosen by evidence) against sparse
polynomial regression (SINDy) and a small neural network, on the same correction samples.

Settings (the paper's observation model: exact derivatives + noise of std 1e-2):

* paper_linear (F = 0.01 y^2, a polynomial): K = 5, 12, 20, 40 experiments, T = 11 on [0, 6], either random
  (initial conditions uniform in D, new per realization) or designed (the paper's greedy design from its prior over
  the 13 x 13 grid, first K picks); error: the integral over D of ||F_hat - F||.
* paper_gravity (an inverse-square field): K = 1..10 random circular orbits (new per realization), T = 20 on
  [0, 3]; error: the mean over D of ||F_hat - F||^2.

Methods (every one sees the same samples; degree-2 monomials for every polynomial library):

* ``GP rbf``: ``CorrectionGP()`` (RBF, hyperparameters by marginal likelihood);
* ``GP features``: ``CorrectionGP(kernel="features")`` (automatic relevance);
* ``GP features+rbf``: ``CorrectionGP(kernel="features+rbf")``;
* ``GP auto``: ``CorrectionGP(kernel="auto")`` (the kernel of highest evidence score, log marginal likelihood less
  BIC's price of the learned hyperparameters, among those the library check allows: a stationary kernel when
  features+rbf outscores the feature kernel it nests; features+rbf itself is the test, never kept; and the RBF
  unless the Matern kernel, or a feature kernel against every eligible stationary one, outscores it by more than
  ``evidence_margin``, 3 nats by default);
* ``SINDy``: pysindy's polynomial library and STLSQ, the threshold by 5-fold cross-validation over experiments;
* ``MLP``: a 2 x 64 tanh network, Adam with weight decay, inputs and outputs standardised.

``scripts/study_kernels.py`` is its command line.
"""

from __future__ import annotations

import math
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.benchmarks.reporting import (
    BENCHMARKS_MD,
    ROOT,
    machine,
    run_json,
    update_benchmarks,
    write_json,
    write_page,
)
from torchmisspec.metrics import integrated_error, mean_and_standard_error, mean_squared_error

from . import _setup

DEFAULT_JSON = ROOT / "benchmarks" / "study_kernels.json"
DOC_PAGE = ROOT / "docs" / "studies" / "kernels.md"
MARK_START = "<!-- study:kernels:start -->"
MARK_END = "<!-- study:kernels:end -->"
DT = torch.float64
SEED = 12_000
DEGREE = 2
METHODS = ("GP rbf", "GP features", "GP features+rbf", "GP auto", "SINDy", "MLP")
FULL = {"realizations": 10, "linear_ks": [5, 12, 20, 40], "gravity_ks": list(range(1, 11)), "mlp_steps": 3000}
SMOKE = {"realizations": 2, "linear_ks": [5], "gravity_ks": [2], "mlp_steps": 200}
THRESHOLDS = [0.0] + [10.0 ** (e / 4) for e in range(-16, 1)]  # relative to the largest least-squares coefficient


# ------------------------------------------------------------------------------------------------- methods
def sindy(samples, experiments: torch.Tensor):
    """pysindy STLSQ on a degree-2 library, threshold by 5-fold cross-validation over experiments."""
    import numpy as np
    import pysindy as ps

    X, Y = samples.inputs.numpy(), samples.targets.numpy()
    lib = ps.PolynomialLibrary(degree=DEGREE, include_bias=True)
    theta = lib.fit_transform(X)
    scale = float(np.abs(np.linalg.lstsq(theta, Y, rcond=None)[0]).max())
    exp = experiments.numpy()
    ids = np.unique(exp)
    folds = [ids[i::5] for i in range(min(5, len(ids)))] if len(ids) > 1 else []

    def fit(t, rows):
        opt = ps.STLSQ(threshold=t * scale, alpha=1e-8 * float((theta**2).sum() / len(theta)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            opt.fit(theta[rows], Y[rows])
        return opt.coef_  # (d_out, p)

    best_t, best = 0.0, math.inf
    if folds:
        for t in THRESHOLDS:
            err = 0.0
            for f in folds:
                test = np.isin(exp, f)
                coef = fit(t, ~test)
                err += float(((theta[test] @ coef.T - Y[test]) ** 2).sum())
            if err < best:
                best_t, best = t, err
    coef = fit(best_t, np.ones(len(X), dtype=bool))
    coef_t = torch.as_tensor(coef, dtype=DT)

    def estimate(x):
        return torch.as_tensor(lib.transform(x.numpy()), dtype=DT) @ coef_t.T

    return estimate, {"threshold": best_t * scale, "terms": int((coef != 0).sum())}


def mlp(samples, steps: int, seed: int):
    """A 2 x 64 tanh MLP on standardised inputs and outputs; Adam (lr 1e-2, weight decay 1e-4), full batch."""
    X, Y = samples.inputs, samples.targets
    xm, xs = X.mean(0), X.std(0).clamp_min(1e-12)
    ym, ys = Y.mean(0), Y.std(0).clamp_min(1e-12)
    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(X.shape[1], 64), torch.nn.Tanh(), torch.nn.Linear(64, 64), torch.nn.Tanh(),
        torch.nn.Linear(64, Y.shape[1]),
    ).to(DT)  # fmt: skip
    opt = torch.optim.Adam(net.parameters(), lr=1e-2, weight_decay=1e-4)
    xn, yn = (X - xm) / xs, (Y - ym) / ys
    for _ in range(steps):
        opt.zero_grad()
        loss = (net(xn) - yn).pow(2).mean()
        loss.backward()
        opt.step()

    def estimate(x):
        with torch.no_grad():
            return net((x - xm) / xs) * ys + ym

    return estimate, {}


def gp_method(kernel: str, samples):
    gp = tms.CorrectionGP(kernel=kernel, degree=DEGREE).fit(samples)

    def estimate(x):
        with torch.no_grad():
            return gp.predict_mean(x)

    info = {"kernel": gp.kernel}
    if gp.auto:  # the chooser: what it compared
        info["selection"] = {r["kernel"]: r["log_marginal_likelihood"] for r in gp.model_selection_}
        info["score"] = {r["kernel"]: r["score"] for r in gp.model_selection_}
        info["library_suffices"] = gp.library_suffices_
        info["eligible"] = [r["kernel"] for r in gp.model_selection_ if r.get("eligible")]
        info["margin"] = gp.evidence_margin
    return estimate, info


# ------------------------------------------------------------------------------------------------- runs
def run_one(system, y0, times, seed: int, cfg: dict, squared: bool) -> dict:
    traj = tms.simulate(system, y0, times)
    samples = tms.correction_samples(
        traj, system, derivative="oracle", noise_std=_setup.NOISE_STD, generator=torch.Generator().manual_seed(seed)
    )
    out = {}
    for name in METHODS:
        start = time.perf_counter()
        try:
            if name == "SINDy":
                est, info = sindy(samples, samples.experiment)
            elif name == "MLP":
                est, info = mlp(samples, cfg["mlp_steps"], seed)
            else:
                est, info = gp_method(name.removeprefix("GP "), samples)
            fn = mean_squared_error if squared else integrated_error
            err = fn(est, system.true_correction, system.domain, resolution=81 if squared else 101)
            out[name] = {"error": err, "seconds": time.perf_counter() - start, **info}
        except tms.TorchMisspecError as exc:
            out[name] = {"error": None, "failed": f"{type(exc).__name__}: {exc}"}
    return out


def study(cfg: dict, log=print) -> dict:
    R = cfg["realizations"]
    result = {"config": cfg, "linear": {}, "gravity": {}}
    system = tms.systems.paper_linear()
    times = _setup.linear_times()
    grid = design.candidates.grid(system.domain, _setup.LINEAR_GRID_SIZE)
    prior = tms.CorrectionGP(**_setup.LINEAR_PRIOR)
    plan = design.greedy(grid, max(cfg["linear_ks"]), system=system, times=times, gp=prior)
    for K in cfg["linear_ks"]:
        for kind in ("random", "designed"):
            runs = []
            for r in range(R):
                gen = torch.Generator().manual_seed(SEED + 1000 * K + r)
                y0 = design.candidates.uniform_box(K, system.domain, generator=gen) if kind == "random" else None
                y0 = grid[plan.indices[:K]] if y0 is None else y0
                runs.append(run_one(system, y0, times, SEED + 7 * r + K, cfg, squared=False))
            result["linear"][f"{kind} K={K}"] = runs
            log(f"linear {kind} K={K}: done")
    system = tms.systems.paper_gravity()
    times = _setup.gravity_times()
    for K in cfg["gravity_ks"]:
        runs = []
        for r in range(R):
            y0 = design.candidates.orbits(K, generator=torch.Generator().manual_seed(SEED + 100 * K + r))
            runs.append(run_one(system, y0, times, SEED + 11 * r + K, cfg, squared=True))
        result["gravity"][f"K={K}"] = runs
        log(f"gravity K={K}: done")
    return result


# ------------------------------------------------------------------------------------------------- reporting
def _errors(runs: list[dict], name: str) -> torch.Tensor:
    return torch.tensor([r[name]["error"] if r[name]["error"] is not None else math.nan for r in runs], dtype=DT)


def _ratios(runs, a, b) -> torch.Tensor:
    """Per realization: the error of ``a`` over that of ``b`` (where both succeeded)."""
    x = _errors(runs, a) / _errors(runs, b)
    return x[torch.isfinite(x)]


def _ratio(runs, a, b) -> tuple[float, float]:
    m, s = mean_and_standard_error(_ratios(runs, a, b))
    return float(m), float(s)


def _ratio_of_means(runs, a, b) -> tuple[float, float]:
    """mean error of ``a`` / mean error of ``b`` over the realizations where both succeeded, with its standard
    error by the delta method (the errors are paired, so their covariance enters)."""
    ea, eb = _errors(runs, a), _errors(runs, b)
    ok = torch.isfinite(ea) & torch.isfinite(eb)
    ea, eb = ea[ok], eb[ok]
    n = ea.numel()
    ma, mb = float(ea.mean()), float(eb.mean())
    r = ma / mb
    if n < 2:
        return r, math.nan
    va, vb = float(ea.var()) / n, float(eb.var()) / n
    cov = float(((ea - ma) * (eb - mb)).sum()) / (n - 1) / n
    return r, r * math.sqrt(max(va / ma**2 + vb / mb**2 - 2 * cov / (ma * mb), 0.0))


def table(section: dict) -> str:
    head = (
        "| setting | " + " | ".join(METHODS) + " | auto / SINDy (paired) | auto / SINDy per realization (min - max) "
        "| auto / SINDy (of means) | auto / rbf | auto chose |"
    )
    lines = [head, "|" + "---|" * (len(METHODS) + 6)]
    for setting, runs in section.items():
        cells = []
        for name in METHODS:
            e = _errors(runs, name)
            ok = e[torch.isfinite(e)]
            m, s = mean_and_standard_error(ok) if ok.numel() > 1 else (ok.mean(), torch.tensor(math.nan))
            failed = len(runs) - ok.numel()
            cells.append(f"{float(m):.3g} ± {float(s):.2g}" + (f" ({failed} failed)" if failed else ""))
        chose = {}
        for r in runs:
            k = r["GP auto"].get("kernel", "failed")
            chose[k] = chose.get(k, 0) + 1
        a_s, a_r = _ratio(runs, "GP auto", "SINDy"), _ratio(runs, "GP auto", "GP rbf")
        a_m = _ratio_of_means(runs, "GP auto", "SINDy")
        each = _ratios(runs, "GP auto", "SINDy")
        picks = ", ".join(f"{k} {v}" for k, v in sorted(chose.items()))
        lines.append(
            f"| {setting} | " + " | ".join(cells) + f" | {a_s[0]:.3f} ± {a_s[1]:.3f} "
            f"| {float(each.min()):.2f} - {float(each.max()):.2f} | {a_m[0]:.3g} ± {a_m[1]:.2g} "
            f"| {a_r[0]:.3f} ± {a_r[1]:.3f} | {picks} |"
        )
    return "\n".join(lines) + "\n"


def goals(result: dict) -> list[str]:
    out = []
    lin = result["linear"]
    worst = max((_ratio(runs, "GP auto", "SINDy")[0], s) for s, runs in lin.items())
    out.append(
        f"- paper_linear: auto / SINDy, paired mean of the ratios, at most **{worst[0]:.3f}** (at {worst[1]}; goal "
        "<= 1.2 at every K)"
    )
    means = {s: _ratio_of_means(runs, "GP auto", "SINDy") for s, runs in lin.items()}
    worst = max((m, s) for s, (m, _) in means.items())
    within = [s for s, (m, _) in means.items() if m <= 1.2]
    out.append(
        f"- paper_linear: auto's mean error / SINDy's at most **{worst[0]:.3f}** (at {worst[1]}); within 1.2 in "
        f"**{len(within)} of {len(means)}** settings"
    )
    each = {s: _ratios(runs, "GP auto", "SINDy") for s, runs in lin.items()}
    worst = max((float(x.max()), s) for s, x in each.items())
    over = sum(int((x > 2.0).sum()) for x in each.values())
    out.append(
        f"- paper_linear: auto / SINDy in a single realization at most **{worst[0]:.2f}** (at {worst[1]}); "
        f"realizations worse than 2x: **{over}** of {sum(x.numel() for x in each.values())} (goal: none)"
    )
    feats = [s for s, runs in lin.items() if _ratio_of_means(runs, "GP features", "SINDy")[0] < 1.0]
    out.append(
        f"- paper_linear: the feature kernel's mean error below SINDy's in **{len(feats)} of {len(lin)}** settings"
    )
    late = [(s, _ratio(runs, "GP auto", "GP rbf")) for s, runs in lin.items() if int(s.split("K=")[1]) >= 12]
    bad = [s for s, (m, se) in late if not m + se < 1.0]
    out.append(
        "- paper_linear, K >= 12: auto better than the RBF GP (ratio + s.e. < 1) in "
        f"**{len(late) - len(bad)} of {len(late)}** settings" + (f" (not in {bad})" if bad else "")
    )
    grav = result["gravity"]
    vs_rbf = {s: _ratio(runs, "GP auto", "GP rbf") for s, runs in grav.items()}
    # ratio - 1 <= s.e., with room for rounding: when auto and the RBF differ in a single realization, the mean
    # excess equals its standard error exactly, and the floating-point difference must not decide
    worse = {s: (m, se) for s, (m, se) in vs_rbf.items() if m - 1.0 > se * (1 + 1e-9)}
    at_edge = [s for s, (m, se) in vs_rbf.items() if m > 1.0 and s not in worse and m - 1.0 >= se * (1 - 1e-9)]
    out.append(
        f"- paper_gravity: auto no worse than the RBF GP within one s.e. in **{len(grav) - len(worse)} of "
        f"{len(grav)}** values of K"
        + (f" (not at {', '.join(f'{s}: {m:.3f} ± {se:.3f}' for s, (m, se) in worse.items())})" if worse else "")
        + (
            f"; exactly one s.e. above at {', '.join(at_edge)} (one realization differs from the RBF's choice, "
            "and then the mean excess equals its standard error)"
            if at_edge
            else ""
        )
    )
    for other in ("SINDy", "MLP"):
        ratios = {s: _ratio(runs, "GP auto", other) for s, runs in grav.items()}
        missed = ", ".join(f"{s}: {m:.3f} ± {se:.3f}" for s, (m, se) in ratios.items() if not m + se < 1.0)
        of_means = {s: _ratio_of_means(runs, "GP auto", other) for s, runs in grav.items()}
        missed_means = ", ".join(f"{s}: {m:.3f} ± {se:.3f}" for s, (m, se) in of_means.items() if not m + se < 1.0)
        paired = sum(m + se < 1.0 for m, se in ratios.values())
        means = sum(m + se < 1.0 for m, se in of_means.values())
        out.append(
            f"- paper_gravity: auto better than {other} (paired ratio + s.e. < 1) in **{paired} of {len(grav)}** "
            "values of K" + (f" (not at {missed})" if missed else "") + "; by the ratio of mean errors (+ s.e. < 1) "
            f"in **{means} of {len(grav)}**" + (f" (not at {missed_means})" if missed_means else "")
        )
    for name, section in (("paper_linear", lin), ("paper_gravity", grav)):
        checks = [r["GP auto"].get("library_suffices") for runs in section.values() for r in runs]
        yes, no = checks.count(True), checks.count(False)
        out.append(
            f"- {name}: the library check found the library sufficient in **{yes}**, insufficient in **{no}** of "
            f"{len(checks)} fits (not made: {len(checks) - yes - no})"
        )
        held = [h for runs in section.values() for r in runs if (h := _held_by_margin(r["GP auto"])) is not None]
        if held:
            out.append(
                f"- {name}: the margin kept a stationary kernel (the RBF, or the Matern kernel against a feature "
                f"kernel) over a higher-scoring eligible candidate in **{sum(held)}** of {len(held)} fits"
            )
    return out


def _held_by_margin(info: dict) -> bool | None:
    """Whether auto kept a kernel other than the highest-scoring eligible one (None: not recorded)."""
    if "eligible" not in info or "score" not in info:
        return None
    score = info["score"]
    return any(score[k] > score[info["kernel"]] for k in info["eligible"])


def gravity_extrapolation(K: int, r: int, log=print) -> None:
    """Where on the gravity set-up the kernels' errors come from (``scripts/probe_gravity_extrapolation.py``): for
    realization ``r`` of this study at ``K`` random orbits (its seeds), each kernel's squared error of F over the
    81 x 81 grid of D, split by the distance from the grid point to the nearest sample: near (< 0.2) and far
    (>= 0.5); logs each kernel's evidence score, errors and the fraction of D that is far."""
    system, times = tms.systems.paper_gravity(), _setup.gravity_times()
    y0 = design.candidates.orbits(K, generator=torch.Generator().manual_seed(SEED + 100 * K + r))
    samples = tms.correction_samples(
        tms.simulate(system, y0, times),
        system,
        derivative="oracle",
        noise_std=_setup.NOISE_STD,
        generator=torch.Generator().manual_seed(SEED + 11 * r + K),
    )
    g = torch.linspace(-2, 2, 81, dtype=torch.float64)
    X = torch.cartesian_prod(g, g)
    truth = system.true_correction(X)
    distance = torch.cdist(X, samples.inputs).min(1).values
    near, far = distance < 0.2, distance >= 0.5
    log(f"K = {K}, realization {r}: {float(far.double().mean()):.2f} of D is >= 0.5 from every sample")
    for kernel, per_output in (("rbf", False), ("matern52", False), ("features", True), ("features+rbf", False)):
        gp = tms.CorrectionGP(kernel=kernel, per_output=per_output).fit(samples)
        with torch.no_grad():
            err = (gp.predict_mean(X) - truth).pow(2).sum(1)
        log(
            f"{kernel:13s} score {gp.evidence_score:9.1f}  mean squared error {float(err.mean()):.2e}  "
            f"near {float(err[near].mean()):.2e}  far {float(err[far].mean()):.2e}"
        )


def render_page(result: dict, info: dict) -> str:
    cfg = result["config"]
    return f"""# Study: kernels chosen by evidence against sparse regression and a neural network (issue 12)

Written by `python scripts/study_kernels.py --markdown` (from a saved run with `--from-json F --markdown`); every
number below is computed by the script. {cfg["realizations"]} realizations per setting; mean ± standard error over
realizations, ratios paired per realization. Machine: {info.get("cpu")}, torch {info.get("torch")}, commit
{info.get("git_commit")}.

Every method sees the same correction samples (the paper's observation model: exact derivatives plus noise of std
1e-2), with degree-2 monomials for every polynomial library. See the script's docstring for the settings and methods.

## Goals

{chr(10).join(goals(result))}

The feature kernels charge a price per term (`min_gain`, by default log(N) / 2 nats) and `auto` keeps the candidate
of highest evidence score (log marginal likelihood less log(N) / 2 per learned hyperparameter) among those its
library check allows: when `features+rbf` outscores the feature kernel it nests, the library misses part of F and
only the stationary kernels are eligible (`features+rbf` is the test and never kept). Leaving the RBF takes strong
evidence: the Matern kernel must outscore it, and a feature kernel every eligible stationary kernel, by more than
`evidence_margin` (3 nats, "strong" on Kass and Raftery's scale); see the tutorial "Choose the kernel by evidence".
"auto / SINDy (paired)" is the mean over realizations of the ratio of the two errors; "(of means)" the ratio of the
mean errors, with a delta-method standard error; "per realization" the smallest and largest single ratio, where a
mean can hide a failure.

An independent comparison (issue 27: its own seeds, `CorrectionGP(kernel="auto").fit(samples.inputs,
samples.targets)`, SINDy's threshold by 5-fold cross-validation grouped by experiment, as here) found SINDy ahead at
random K = 20 in single realizations by up to 2.5x. Rerun on this study's seeds with its exact calls the same
setting gave a mean ratio of 0.97 but a worst realization of 2.04, with the feature kernel holding exactly the true
terms: the loss was shrinkage, not spurious terms. MacKay's evidence-optimal weight of a kept term is about its
coefficient squared, which pulls a moderately measured coefficient toward 0 by 1 / (1 + 1/SNR) (there 0.00949
against least squares' 0.01009), while SINDy refits plain least squares on its terms. Since then a kept term's
prior is at least the unit-information prior (see `torchmisspec.gp._features`), and the table above is with it.

## paper_linear (F = 0.01 y^2): integral over D of ||F_hat - F||

{table(result["linear"])}
## paper_gravity (inverse-square field): mean over D of ||F_hat - F||^2

{table(result["gravity"])}
On the gravity set-up the candidates with a polynomial part often have the higher score: along the observed orbits a
quadratic in the positions fits the field about as well as a stationary kernel, with fewer effective degrees of
freedom. The error is a mean over the whole square D, much of which no orbit visits, and there the polynomial part
extrapolates while a stationary kernel falls back to its prior. The library check catches this when the library plus
an RBF term outscores the library alone. With one or two orbits the RBF term cannot earn its price on so few samples,
and the library alone can win by a few nats; the margin keeps the RBF then, unless the evidence is strong ("auto
chose" shows what was kept). When auto's choice differs from the RBF in a single realization of a setting, the mean
excess of "auto / rbf" over 1 equals its standard error exactly (the goal line says where).
"""


def run(args) -> int:
    """The study's command line run (``args`` from :func:`~torchmisspec.benchmarks.reporting.study_arguments`):
    the study, or the saved run of ``--from-json``; its JSON, its summary printed, and with ``--markdown`` the
    docs page and the block of BENCHMARKS.md."""
    if args.saved is not None:
        result, json_path = args.saved, None
    else:
        t0 = time.perf_counter()
        result = study(SMOKE if args.smoke else FULL)
        result["machine"], result["wall_seconds"], result["smoke"] = machine(), time.perf_counter() - t0, args.smoke
        json_path = run_json(args, DEFAULT_JSON)
    write_json(result, json_path)
    print("\n".join(goals(result)))
    if args.markdown:
        write_page(DOC_PAGE, render_page(result, result["machine"]))
        block = f"""{MARK_START}
## Kernels against SINDy and an MLP (`scripts/study_kernels.py`)

Written by `python scripts/study_kernels.py --markdown`; tables in [docs/studies/kernels.md](docs/studies/kernels.md).

{chr(10).join(goals(result))}

{MARK_END}
"""
        update_benchmarks(block, MARK_START, MARK_END, BENCHMARKS_MD)
        print(f"wrote {DOC_PAGE} and the kernels block of {BENCHMARKS_MD}")
    return 0
