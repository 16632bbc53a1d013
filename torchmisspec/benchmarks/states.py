"""``scripts/benchmark.py --only realdata``: the costs of learning from states (issue 9's targets)."""

from __future__ import annotations

import torch

import torchmisspec as tms
from torchmisspec.design.candidates import uniform_box

from .reporting import timed


def bench_realdata(smoke: bool, repeats: int) -> dict:
    """Issue 9's cost targets: derivative="gp" on 40 experiments x 21 times (target < 1 s) and fit_trajectories on
    the same data (target < 30 s), paper 5.1's system with 1 % state noise."""
    from torchmisspec.learning.samples.observations import gp_derivative

    system = tms.systems.paper_linear()
    gen = torch.Generator().manual_seed(0)
    K, T = (8, 11) if smoke else (40, 21)
    times = torch.linspace(0.0, 6.0, T, dtype=torch.float64)
    clean = tms.simulate(system, uniform_box(K, system.domain, generator=gen), times)
    rms = clean.states.pow(2).mean(dim=(0, 1)).sqrt()
    noisy = tms.Trajectories(
        times, clean.states + 0.01 * rms * torch.randn(clean.states.shape, generator=gen, dtype=torch.float64)
    )
    gp_derivative(noisy.states[:2], times)  # warm-up (first-call imports)
    _, gp_seconds, gp_all = timed(lambda: gp_derivative(noisy.states, times), repeats)
    samples = tms.correction_samples(noisy, system, derivative="gp")
    start = tms.CorrectionGP().fit(samples)
    refined, fit_seconds, fit_all = timed(lambda: tms.fit_trajectories(start, system, noisy), 1 if smoke else 2)
    from torchmisspec.learning.refinement.trajectory_fit import shooting_misfit

    return {
        "experiments": K,
        "times": T,
        "gp_seconds": gp_seconds,
        "gp_all_seconds": gp_all,
        "fit_trajectories_seconds": fit_seconds,
        "fit_trajectories_all_seconds": fit_all,
        "iterations": refined.n_iterations_,
        "solves": refined.n_evaluations_,
        "misfit_before": shooting_misfit(start, system, noisy),
        "misfit_after": shooting_misfit(refined, system, noisy),
        "error_before": tms.correction_error(start, system),
        "error_after": tms.correction_error(refined, system),
    }
