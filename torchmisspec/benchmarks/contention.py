"""``scripts/benchmark.py --only contention``: fit, prediction and design on a quiet machine and beside a busy
process, with the package's adaptive thread count and with torch's own setting (each in a fresh process)."""

from __future__ import annotations

import subprocess
import sys
import time

import torch

import torchmisspec as tms
from torchmisspec.design.candidates import uniform_box

from .reporting import run_worker, timed, worker_main


def _contention_worker(smoke: bool, repeats: int) -> dict:
    """Fit, prediction and design timings in this process (run by bench_contention with and without a busy peer)."""
    system = tms.systems.paper_linear()
    gen = torch.Generator().manual_seed(0)
    times = torch.linspace(0.0, 6.0, 11, dtype=torch.float64)
    n_traj, n_ic, n_cand, K = (10, 50, 500, 5) if smoke else (40, 1000, 10_000, 50)
    trajs = tms.simulate(system, uniform_box(n_traj, system.domain, generator=gen), times)
    s = tms.correction_samples(trajs, system, derivative="oracle", noise_std=1e-2, generator=gen)
    gp = tms.CorrectionGP().fit(s.inputs, s.targets)
    ode = tms.CorrectedODE(system, gp)
    y0 = uniform_box(n_ic, system.domain, generator=gen)
    fine = torch.linspace(0.0, 6.0, 61, dtype=torch.float64)
    cands = uniform_box(n_cand, system.domain, generator=gen)
    t20 = torch.linspace(0.0, 6.0, 20, dtype=torch.float64)
    prior = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4)
    tms.design.greedy(cands[:50], 3, system=system, times=t20, gp=prior)  # warm-up
    out = {"threads": torch.get_num_threads()}
    out["fit"] = timed(lambda: tms.CorrectionGP().fit(s.inputs, s.targets), repeats)[1]
    out["predict"] = timed(lambda: ode.predict(y0, fine), repeats)[1]
    out["design"] = timed(lambda: tms.design.greedy(cands, K, system=system, times=t20, gp=prior), repeats)[1]
    return out


def bench_contention(smoke: bool, repeats: int) -> dict:
    """Quiet vs beside one busy process (a pure-Python spin loop), with the package's adaptive thread count and
    with torch's own thread setting (``TORCHMISSPEC_THREADS=torch``), each in a fresh process."""
    policies = {"adaptive (default)": {}, "torch's setting": {"TORCHMISSPEC_THREADS": "torch"}}
    out = {"sizes": "smoke" if smoke else "fit N = 440, predict 1000 x 61, design 10,000 candidates K = 50"}
    for busy in (False, True):
        spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
        try:
            if spinner is not None:
                time.sleep(0.5)
            for name, env in policies.items():
                out[f"{name}, {'busy' if busy else 'quiet'}"] = run_worker(
                    "torchmisspec.benchmarks.contention", [smoke, repeats], torch.get_num_threads(), env
                )
        finally:
            if spinner is not None:
                spinner.kill()
                spinner.wait()
    return out


if __name__ == "__main__":  # the worker of bench_contention (reporting.run_worker)
    worker_main(_contention_worker)
