"""``scripts/benchmark.py --only predict``: ``CorrectedODE.predict`` against a solve whose right-hand side calls the
GPyTorch model at every step."""

from __future__ import annotations

import copy

import torch

import torchmisspec as tms
from torchmisspec.design.candidates import uniform_box

from .fitting import correction_data
from .reporting import timed


def bench_predict(smoke: bool, repeats: int) -> dict:
    import gpytorch
    from torchdiffeq import odeint

    n_traj, n_times = 40, 11
    system, samples = correction_data(n_traj, n_times)
    gp = tms.CorrectionGP().fit(samples.inputs, samples.targets)
    gen = torch.Generator().manual_seed(1)
    n_ic = 50 if smoke else 1000
    y0 = uniform_box(n_ic, system.domain, generator=gen)
    times = torch.linspace(0.0, 6.0, 61, dtype=torch.float64)
    ode = tms.CorrectedODE(system, gp)
    rtol, atol = 1e-7, 1e-9

    def ours():
        return ode.predict(y0, times, solver=tms.Solver(rtol=rtol, atol=atol))

    # the GPyTorch ExactGP (eval mode) with the same hyperparameters and data; one copy per peer so that each keeps
    # its own prediction strategy (GPyTorch caches the training solve on the first eval call)
    full_model, fast_model = gp.model, copy.deepcopy(gp.model)
    counter = {"nfe": 0}

    def full_rhs(t, y):
        counter["nfe"] += 1
        with gpytorch.settings.fast_pred_var(False):
            return system.known(y) + full_model(y).mean.T  # the predictive distribution at every step

    def fast_rhs(t, y):
        counter["nfe"] += 1
        with gpytorch.settings.skip_posterior_variances(True), gpytorch.settings.fast_pred_var():
            return system.known(y) + fast_model(y).mean.T  # mean only

    def peer(rhs):
        counter["nfe"] = 0
        with torch.no_grad():
            return odeint(rhs, y0, times, rtol=rtol, atol=atol).transpose(0, 1)

    with torch.no_grad():  # build both prediction strategies before timing (ours was built by fit)
        full_rhs(0.0, y0[:2])
        fast_rhs(0.0, y0[:2])
    pred, t_ours, all_ours = timed(ours, repeats)
    out = {
        "initial_conditions": n_ic,
        "output_times": times.numel(),
        "train_samples": samples.inputs.shape[0],
        "train_trajectories": n_traj,
        "train_times_per_trajectory": n_times,
        "ours_seconds": t_ours,
        "ours_all_seconds": all_ours,
        "ours_rhs_evaluations": ode.nfe,
    }
    for name, rhs in (("gpytorch", full_rhs), ("gpytorch_fast", fast_rhs)):
        ref, t, all_t = timed(lambda rhs=rhs: peer(rhs), repeats)
        out[name] = {
            "seconds": t,
            "all_seconds": all_t,
            "rhs_evaluations": counter["nfe"],
            "max_abs_difference": float((pred - ref).abs().max()),
            "speedup": t / t_ours,  # >= 10 required against the predictive distribution
        }
    return out
