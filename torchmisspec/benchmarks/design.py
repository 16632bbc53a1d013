"""``scripts/benchmark.py --only design`` and ``--only naive``: greedy design of 10,000 candidates (each case in a
fresh process, for its peak memory), and lazy vs plain vs the naive greedy of Algorithm 1."""

from __future__ import annotations

import torch

import torchmisspec as tms
from torchmisspec.design.candidates import uniform_box

from .reporting import peak_rss_mb, run_worker, timed, worker_main


def _design_worker(
    n: int, T: int, K: int, outputscale: float, lengthscale: float, repeats: int, method: str = "lazy", seed: int = 0
) -> dict:
    """A design of ``n`` uniform candidates (their proxies included), run in a fresh process so that its peak memory is
    its own; ``seed`` seeds the draws of ``method="stochastic"``."""
    from torchmisspec import design

    system = tms.systems.paper_linear()
    gen = torch.Generator().manual_seed(0)
    candidates = uniform_box(n, system.domain, generator=gen)
    times = torch.linspace(0.0, 6.0, T, dtype=torch.float64)
    gp = tms.CorrectionGP(lengthscale=lengthscale, outputscale=outputscale, noise_variance=1e-4)
    design.greedy(candidates[:50], 3, system=system, times=times, gp=gp)  # warm-up: first-call overheads
    before = peak_rss_mb()

    def run():
        stochastic = method == "stochastic"
        draws = {"engine": design.Engine(generator=torch.Generator().manual_seed(seed))} if stochastic else {}
        return design.greedy(candidates, K, system=system, times=times, gp=gp, method=method, **draws)

    plan, seconds, all_seconds = timed(run, repeats)
    return {
        "candidates": n,
        "T": T,
        "K": K,
        "lengthscale": lengthscale,
        "outputscale": outputscale,
        "seconds": seconds,
        "all_seconds": all_seconds,
        "method": method,
        "seed": seed,
        "gain_evaluations": plan.evaluations,
        "information_gain_nats": plan.information_gain,
        "diagnostics": plan.diagnostics,
        "peak_rss_mb": peak_rss_mb(),
        "rss_after_imports_and_warmup_mb": before,
    }


def bench_design(smoke: bool, repeats: int) -> dict:
    n, K = (1000, 10) if smoke else (10_000, 50)
    out = {}
    # the target case (lengthscale 1, two output scales), and a rough kernel where the screening cannot help
    cases = ((1.0, 1e-2),) if smoke else ((1.0, 4e-5), (1.0, 1e-2), (0.3, 1e-2))
    for lengthscale, outputscale in cases:
        args = [n, 20, K, outputscale, lengthscale, 1 if lengthscale < 1 else repeats]
        key = f"lengthscale={lengthscale},outputscale={outputscale}"
        out[key] = run_worker("torchmisspec.benchmarks.design", args, torch.get_num_threads())
    return out


def bench_naive(smoke: bool, repeats: int) -> dict:
    from torchmisspec import design

    system = tms.systems.paper_linear()
    n, T, K = (100, 11, 5) if smoke else (500, 11, 15)
    candidates = uniform_box(n, system.domain, generator=torch.Generator().manual_seed(1))
    times = torch.linspace(0.0, 6.0, T, dtype=torch.float64)
    out = {}
    for outputscale in (4e-5, 1e-2):
        gp = tms.CorrectionGP(lengthscale=1.0, outputscale=outputscale, noise_variance=1e-4)
        design.greedy(candidates[:30], 3, system=system, times=times, gp=gp, method="naive")  # warm-up
        runs = {
            m: timed(
                lambda m=m, gp=gp: design.greedy(candidates, K, system=system, times=times, gp=gp, method=m), repeats
            )
            for m in ("naive", "plain", "lazy")
        }
        picks = {m: r[0].indices.tolist() for m, r in runs.items()}
        out[f"outputscale={outputscale}"] = {
            "candidates": n,
            "T": T,
            "K": K,
            **{f"{m}_seconds": r[1] for m, r in runs.items()},
            **{f"{m}_all_seconds": r[2] for m, r in runs.items()},
            **{f"{m}_evaluations": r[0].evaluations for m, r in runs.items()},
            "identical_picks": picks["naive"] == picks["plain"] == picks["lazy"],
            "picks": picks["lazy"],
            "speedup_lazy_vs_naive": runs["naive"][1] / runs["lazy"][1],  # >= 20 required
        }
    return out


if __name__ == "__main__":  # the worker of bench_design (reporting.run_worker)
    worker_main(_design_worker)
