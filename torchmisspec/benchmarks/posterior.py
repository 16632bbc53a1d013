"""Costs of issues 9 and 10 measured in one run, written as a block of BENCHMARKS.md.

* Issue 10: ``CorrectedODE.posterior`` with 1,000 initial conditions x 64 draws x 61 times on paper_linear (GP on 440
  samples: 40 trajectories x 11 times, oracle noise std 1e-2) against the mean-only ``predict`` on the same 1,000
  initial conditions (target: at most 20x its time); both timed in this process, medians of ``--repeats``. Also
  timed: the posterior with the previous default prior features (800 random Fourier features, ``num_features=800``)
  and two parts of the default posterior (building the draws; the support check along the mean paths).
* Issue 9: ``derivative="gp"`` on 40 experiments x 21 times (target < 1 s), ``fit_trajectories`` (single shooting,
  the default) and ``fit_correction`` (cross-validated lengthscale) on the same data with 1 % state noise (target
  for fit_trajectories < 30 s).

``scripts/benchmark_posterior.py`` is its command line.
"""

from __future__ import annotations

import warnings

import torch

import torchmisspec as tms
from torchmisspec.design.candidates import uniform_box
from torchmisspec.learning.samples.observations import gp_derivative
from torchmisspec.parallel import adaptive_threads

from .reporting import machine, timed, update_benchmarks

MARK_START = "<!-- study:costs:start -->"
MARK_END = "<!-- study:costs:end -->"
DT = torch.float64
#: The previous default prior features of the draws, timed for comparison: 400 random frequency pairs.
RANDOM_FEATURES = 800


def posterior_cost(smoke: bool, repeats: int) -> dict:
    system = tms.systems.paper_linear()
    gen = torch.Generator().manual_seed(0)
    train = tms.simulate(system, uniform_box(40, system.domain, generator=gen), torch.linspace(0, 6, 11, dtype=DT))
    samples = tms.correction_samples(train, system, derivative="oracle", noise_std=1e-2, generator=gen)
    gp = tms.CorrectionGP().fit(samples)
    n_ic, S = (50, 8) if smoke else (1000, 64)
    y0 = uniform_box(n_ic, system.domain, generator=gen)
    times = torch.linspace(0, 6, 61, dtype=DT)
    ode = tms.CorrectedODE(system, gp)
    ode.predict(y0[:2], times)  # warm-up
    _, t_mean, all_mean = timed(lambda: ode.predict(y0, times), repeats)
    nfe_mean = ode.nfe
    post, t_post, all_post = timed(
        lambda: ode.posterior(y0, times, num_samples=S, generator=torch.Generator().manual_seed(1)), repeats
    )
    nfe_post = ode.nfe
    _, t_random, all_random = timed(
        lambda: ode.posterior(
            y0, times, num_samples=S, num_features=RANDOM_FEATURES, generator=torch.Generator().manual_seed(1)
        ),
        repeats,
    )
    nfe_random = ode.nfe
    # parts of the default posterior: the draws (features, update, compression) and the support check (the exact
    # posterior variance at every state of the mean paths); the rest is the mean paths (predict) and the sampled solve.
    # Under the thread count posterior() itself would use (adaptive_threads: one thread when another process is busy)
    with adaptive_threads():
        _, t_draws, _ = timed(
            lambda: gp.sample_functions(
                S, update_error=tms.prediction.dynamics.UPDATE_ERROR, generator=torch.Generator().manual_seed(1)
            ),
            repeats,
        )
        _, t_support, _ = timed(lambda: ode._support(post.mean_path), repeats)
    features = gp.sample_functions(1).features
    return {
        "initial_conditions": n_ic,
        "draws": S,
        "times": times.numel(),
        "train_samples": samples.inputs.shape[0],
        "features": features.num_features,
        "feature_kind": features.kind,
        "feature_bound": features.error_bound,
        "basis": gp.sample_functions(S, update_error=tms.prediction.dynamics.UPDATE_ERROR)._X.shape[0],
        "mean_seconds": t_mean,
        "mean_all": all_mean,
        "mean_rhs_evaluations": nfe_mean,
        "posterior_seconds": t_post,
        "posterior_all": all_post,
        "posterior_rhs_evaluations": nfe_post,
        "ratio": t_post / t_mean,
        "random_seconds": t_random,
        "random_all": all_random,
        "random_rhs_evaluations": nfe_random,
        "random_ratio": t_random / t_mean,
        "draws_seconds": t_draws,
        "support_seconds": t_support,
    }


def realdata_cost(smoke: bool, repeats: int) -> dict:
    system = tms.systems.paper_linear()
    gen = torch.Generator().manual_seed(0)
    K, T = (8, 11) if smoke else (40, 21)
    times = torch.linspace(0.0, 6.0, T, dtype=DT)
    clean = tms.simulate(system, uniform_box(K, system.domain, generator=gen), times)
    rms = clean.states.pow(2).mean(dim=(0, 1)).sqrt()
    noisy = tms.Trajectories(
        times, clean.states + 0.01 * rms * torch.randn(clean.states.shape, generator=gen, dtype=DT)
    )
    gp_derivative(noisy.states[:2], times)  # warm-up
    _, t_gp, all_gp = timed(lambda: gp_derivative(noisy.states, times), repeats)
    fitted, t_cv, all_cv = timed(lambda: tms.fit_correction(noisy, system), 1 if smoke else repeats)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)  # the estimator self-check at 1 % noise
        rbf = tms.fit_correction(noisy, system, gp=tms.CorrectionGP())  # the starting point of the RBF refit
        samples = tms.correction_samples(noisy, system)
    refined, t_fit, all_fit = timed(lambda: tms.fit_trajectories(rbf, system, noisy), 1 if smoke else repeats)
    features = tms.CorrectionGP(kernel="features", degree=3, per_output=True).fit(samples)
    relevant, t_rel, all_rel = timed(lambda: tms.fit_trajectories(features, system, noisy), 1 if smoke else repeats)
    return {
        "experiments": K,
        "times": T,
        "gp_seconds": t_gp,
        "gp_all": all_gp,
        "fit_correction_seconds": t_cv,
        "fit_correction_all": all_cv,
        "fit_trajectories_seconds": t_fit,
        "fit_trajectories_all": all_fit,
        "iterations": refined.n_iterations_,
        "evaluations": refined.n_evaluations_,
        "rhs_evaluations": refined.n_rhs_evaluations_,
        "relevance_rhs_evaluations": relevant.n_rhs_evaluations_,
        "chosen": fitted.cross_validation_.best if fitted.cross_validation_ is not None else fitted.kernel,
        "relevance_seconds": t_rel,
        "relevance_all": all_rel,
        "relevance_iterations": relevant.n_iterations_,
        "relevance_evaluations": relevant.n_evaluations_,
    }


def block(r: dict | None, p: dict, info: dict, command: str, load: str) -> str:
    """The markdown block (``r`` None: issue 10 only, ``--posterior-only``); ``info`` is
    :func:`~torchmisspec.benchmarks.reporting.machine`."""
    ok = "met" if p["ratio"] <= 20 else "**not met**"
    lines = [
        MARK_START,
        "## Costs of predictions with bands (issue 10) and of learning from states (issue 9)",
        "",
        f"Written by `{command}` on {info['cpu']}, {info['logical_cpus']} logical CPUs, torch {info['torch']}, "
        f"{info['torch_threads']} torch threads, commit {info['git_commit']}; load average before the run {load}. "
        "Medians of the repeats listed.",
        "",
        "| what | wall time (median) | repeats (s) | right-hand-side evaluations |",
        "|---|---|---|---|",
        f"| `predict`, {p['initial_conditions']} initial conditions x {p['times']} times (GP on {p['train_samples']} "
        f"samples) | {p['mean_seconds']:.3f} s | {', '.join(f'{x:.3f}' for x in p['mean_all'])} | "
        f"{p['mean_rhs_evaluations']} |",
        f"| `posterior`, the same x {p['draws']} draws (defaults: {p['features']} {p['feature_kind']} Fourier "
        f"features per draw) | {p['posterior_seconds']:.2f} s | "
        f"{', '.join(f'{x:.2f}' for x in p['posterior_all'])} | {p['posterior_rhs_evaluations']} |",
        f"| `posterior`, the same, {RANDOM_FEATURES} random Fourier features per draw (`num_features="
        f"{RANDOM_FEATURES}`, the previous default) | {p['random_seconds']:.2f} s | "
        f"{', '.join(f'{x:.2f}' for x in p['random_all'])} | {p['random_rhs_evaluations']} |",
        *(_issue9_rows(r) if r is not None else []),
        "",
        f"- posterior / predict: **{p['ratio']:.1f}x** (target: at most 20x: {ok}); with {RANDOM_FEATURES} random "
        f"features: {p['random_ratio']:.1f}x. Each draw is evaluated at every state of its path: {p['features']} prior "
        f"features ({p['feature_kind']}: certified uniform prior-covariance error {p['feature_bound']:.2g} of the "
        "prior variance over the data's box widened by its width on each side) plus the update on "
        f"{p['basis']} of the {p['train_samples']} training inputs (certified compression), for {p['draws']} times "
        f"as many states as `predict`, whose one kernel row has {p['train_samples']} entries. Of the default "
        f"posterior's {p['posterior_seconds']:.2f} s: building the draws {p['draws_seconds']:.3f} s, the support "
        "check (posterior variance, to a certified 1e-3 of the prior's, at the "
        f"{p['initial_conditions'] * p['times']} states of the mean paths) "
        f"{p['support_seconds']:.2f} s ({p['support_seconds'] / p['mean_seconds']:.1f}x `predict`), the mean paths "
        "one `predict`, the rest the sampled solve.",
        *(_issue9_bullet(r) if r is not None else []),
        MARK_END,
        "",
    ]
    return "\n".join(lines)


def _issue9_rows(r: dict) -> list[str]:
    return [
        f"| `gp_derivative`, {r['experiments']} experiments x {r['times']} times | {r['gp_seconds']:.3f} s | "
        f"{', '.join(f'{x:.3f}' for x in r['gp_all'])} | |",
        f"| `fit_correction` (defaults: model chosen by cross-validation, here {r.get('chosen', '?')}; a chosen "
        f"feature kernel refined through the ODE), same data, 1 % state noise | "
        f"{r['fit_correction_seconds']:.2f} s | {', '.join(f'{x:.2f}' for x in r['fit_correction_all'])} | |",
        f"| `fit_trajectories` (single shooting) from an RBF fit with a cross-validated lengthscale | "
        f"{r['fit_trajectories_seconds']:.2f} s | "
        f"{', '.join(f'{x:.2f}' for x in r['fit_trajectories_all'])} | {r['rhs_evaluations']} "
        f"({r['evaluations']} objective evaluations, {r['iterations']} L-BFGS iterations) |",
        f"| `fit_trajectories` of a feature kernel (degree 3, per output: relevance re-learned through the ODE) | "
        f"{r['relevance_seconds']:.2f} s | {', '.join(f'{x:.2f}' for x in r['relevance_all'])} | "
        f"{r['relevance_rhs_evaluations']} ({r['relevance_evaluations']} objective evaluations, "
        f"{r['relevance_iterations']} L-BFGS iterations) |",
    ]


def _issue9_bullet(r: dict) -> list[str]:
    return [
        f"- `gp_derivative` target < 1 s: {'met' if r['gp_seconds'] < 1 else '**not met**'}; `fit_trajectories` "
        f"target < 30 s: RBF {'met' if r['fit_trajectories_seconds'] < 30 else '**not met**'}, feature kernel "
        f"{'met' if r['relevance_seconds'] < 30 else '**not met**'}.",
    ]


def run(args) -> int:
    """The benchmark, with the arguments of :func:`~torchmisspec.benchmarks.reporting.benchmark_arguments` plus
    ``args.posterior_only``: prints the block, and with ``args.markdown`` writes it into BENCHMARKS.md."""
    repeats = 1 if args.smoke else args.repeats
    p = posterior_cost(args.smoke, repeats)
    r = None if args.posterior_only else realdata_cost(args.smoke, repeats)
    text = block(r, p, machine(), args.command.strip(), args.load)
    print(text)
    if args.markdown:
        update_benchmarks(text, MARK_START, MARK_END)
    return 0
