"""The default ``fit_correction`` on a lab's ragged file as it grows (issue 26): what a user who calls it with no
options waits for, before and after the model choice on a subsample and the vectorised solver output.

Data (as a lab's sensors give them): a predator-prey system the package does not ship (logistic prey growth known,
a Holling type II predation missing: F = (-h, 0.8 h), h = prey predator / (1 + prey)), K cultures, each observed at
60-89 irregular times on [0, 12] (sorted uniform draws, seed 3), 1 % multiplicative state noise. Timed, each in a fresh
process after a warm-up fit on 4 cultures: ``fit_correction(data, system, progress=False)``, its defaults (GP-in-time
derivatives, 13 candidate models by 5-fold cross-validation, the chosen feature kernel refined through the ODE); the
integrated error of F over the domain (``correction_error``) and the model chosen.

The peer in the same run is the same call with the earlier behaviour restored in the worker (``SELECTION_SAMPLES``
and the solver's vectorised output switched off: every candidate fitted on all samples, torchdiffeq's output loop),
at the sizes where it finishes in minutes.

``scripts/benchmark_default_fit.py`` is its command line.
"""

from __future__ import annotations

import math
import time

import torch

import torchmisspec as tms

from .reporting import peak_rss_mb, publish, run_sentence, run_worker, worker_main

MARK_START = "<!-- bench:default-fit:start -->"
MARK_END = "<!-- bench:default-fit:end -->"
FULL = {"cultures": [20, 60, 200], "before": [20]}
SMOKE = {"cultures": [3], "before": [3]}
DOMAIN = ((0.0, 3.0), (0.0, 2.0))


def _known(y):
    prey, pred = y[..., 0], y[..., 1]
    return torch.stack([prey * (1.0 - prey / 3.0), -0.6 * pred], dim=-1)


def _missing(y):
    prey, pred = y[..., 0], y[..., 1]
    h = prey * pred / (1.0 + prey)
    return torch.stack([-h, 0.8 * h], dim=-1)


def predator_prey(with_truth: bool = False) -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        _known, 2, correction=_missing if with_truth else None, name="predator_prey", domain=DOMAIN
    )


def lab_data(cultures: int, seed: int = 3) -> tms.Trajectories:
    """``cultures`` ragged experiments of the true system, as a lab's file holds them."""
    truth = predator_prey(True)
    g = torch.Generator().manual_seed(seed)
    times, states = [], []
    for _ in range(cultures):
        n = int(torch.randint(60, 90, (1,), generator=g))
        hours = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 12).values
        hours[0] = 0.0
        y0 = torch.tensor([0.5, 0.3], dtype=torch.float64) + torch.rand(
            2, generator=g, dtype=torch.float64
        ) * torch.tensor([2.0, 1.2], dtype=torch.float64)
        s = tms.simulate(truth, y0[None], hours).states[0]
        times.append(hours)
        states.append(s * (1 + 0.01 * torch.randn(s.shape, generator=g, dtype=torch.float64)))
    return tms.Trajectories(times, states)


def _worker(cultures: int, before: bool) -> dict:
    import warnings

    from torchmisspec import _ode
    from torchmisspec.learning import fit as learning

    if before:  # the earlier behaviour: every candidate on all samples, torchdiffeq's one-by-one output
        learning.SELECTION_SAMPLES = 2**40  # more than any file: an integer, as thinned() asks
        _ode._VECTOR_OUTPUTS = math.inf
    system = predator_prey()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tms.fit_correction(lab_data(4, seed=11), system, progress=False)  # warm-up
        data = lab_data(cultures)
        t0 = time.perf_counter()
        gp = tms.fit_correction(data, system, progress=False)
        seconds = time.perf_counter() - t0
    truth = predator_prey(True)
    return {
        "cultures": cultures,
        "samples": int(gp.train_inputs_.shape[0]),
        "before": before,
        "seconds": seconds,
        "chosen": gp.cross_validation_.best,
        "scored_on": gp.cross_validation_.samples,
        "error": tms.correction_error(gp, truth),
        "known_only_error": tms.integrated_norm(truth.true_correction, DOMAIN),
        "peak_rss_mb": peak_rss_mb(),
    }


def measure(cfg: dict) -> list[dict]:
    threads = torch.get_num_threads()
    rows = []
    for k in cfg["cultures"]:
        for before in (False, True) if k in cfg["before"] else (False,):
            rows.append(run_worker("torchmisspec.benchmarks.default_fit", [k, before], threads))
    return rows


def lines(rows: list[dict]) -> list[str]:
    out = [
        "| cultures | samples | version | wall time | peak memory | model chosen (scored on) | error of F (known model "
        "alone) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        version = "before (all samples, one-by-one output)" if r["before"] else "now"
        out.append(
            f"| {r['cultures']} | {r['samples']} | {version} | {r['seconds']:.1f} s | {r['peak_rss_mb']:.0f} MB | "
            f"{r['chosen']} ({r['scored_on']} samples) | {r['error']:.3g} ({r['known_only_error']:.3g}) |"
        )
    return out


def run(args) -> int:
    cfg = SMOKE if args.smoke else FULL
    rows = measure(cfg)
    block = [
        "## The default fit on a growing lab file (`scripts/benchmark_default_fit.py`)",
        "",
        run_sentence(args),
        "`fit_correction(data, system)` with its defaults on K ragged cultures of a predator-prey system the package "
        "does not ship (60-89 irregular times each, 1 % noise), each size in a fresh process; the earlier version "
        "(every candidate fitted on all samples, torchdiffeq's output loop on the union of the cultures' times; the "
        "memory fixes of the same day in both) in the same run where it finishes in minutes.",
        "",
        *lines(rows),
    ]
    publish(block, args.markdown, MARK_START, MARK_END)
    return 0


if __name__ == "__main__":  # the workers of measure (reporting.run_worker)
    worker_main(_worker)
