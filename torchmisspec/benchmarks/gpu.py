"""The scale benchmarks on a GPU against the same machine's CPU (issue 26), in one process, the same calls on each.

Rows, each timed after a warm-up on its device (a GPU's times include ``torch.cuda.synchronize``):

* many samples: the default ``CorrectionGP`` on 10^5 samples of paper 5.1's correction (2-D, 0.1 % noise; above
  ``LARGE_N`` it fits in a feature space), then the corrected trajectories of 1,000 initial states at 61 times;
  the integrated error of F against the truth;
* an exact fit: ``CorrectionGP(exact=True)`` on 3,000 samples (dense Cholesky factorizations);
* many candidates: ``design.greedy`` among 10^5 uniform candidates, K = 50, T = 20, RBF prior (lengthscale 1,
  output scale 4e-5, noise variance 1e-4), ``method="stochastic"`` (seed 0) and ``"lazy"``: time and gain.

The peer is the CPU of the same machine, with torch's default threads, in the same run. ``--smoke`` runs tiny
sizes (on the CPU alone where there is no GPU).

``scripts/benchmark_gpu.py`` is its command line.
"""

from __future__ import annotations

import time

import torch

import torchmisspec as tms

from .large_fit import samples
from .reporting import publish, run_sentence

MARK_START = "<!-- bench:gpu:start -->"
MARK_END = "<!-- bench:gpu:end -->"
FULL = {"large": 100_000, "trajectories": 1000, "exact": 3000, "candidates": 100_000, "K": 50, "T": 20}
SMOKE = {"large": 4000, "trajectories": 20, "exact": 300, "candidates": 2000, "K": 5, "T": 6}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _clock(device, fn):
    _sync(device)
    t0 = time.perf_counter()
    out = fn()
    _sync(device)
    return out, time.perf_counter() - t0


def _large(device, cfg) -> dict:
    system = tms.systems.paper_linear()
    x, y = samples(system, cfg["large"])
    x, y = x.to(device), y.to(device)
    tms.CorrectionGP(device=device).fit(x[:200], y[:200])  # warm-up
    gp, fit_s = _clock(device, lambda: tms.CorrectionGP(device=device).fit(x, y))
    g = torch.Generator().manual_seed(1)
    lo, hi = torch.tensor(system.domain, dtype=torch.float64).T
    y0 = (lo + (hi - lo) * torch.rand(cfg["trajectories"], 2, generator=g, dtype=torch.float64)).to(device)
    times = torch.linspace(0.0, 6.0, 61, dtype=torch.float64, device=device)
    model = tms.CorrectedODE(system, gp)
    _, predict_s = _clock(device, lambda: model.predict(y0, times))
    return {
        "fit_seconds": fit_s,
        "predict_seconds": predict_s,
        "error": tms.correction_error(gp, system),
        "features": None if gp.approximation is None else gp.approximation["num_features"],
    }


def _exact(device, cfg) -> dict:
    system = tms.systems.paper_linear()
    x, y = samples(system, cfg["exact"])
    x, y = x.to(device), y.to(device)
    tms.CorrectionGP(exact=True, device=device).fit(x[:200], y[:200])  # warm-up
    gp, seconds = _clock(device, lambda: tms.CorrectionGP(exact=True, device=device).fit(x, y))
    return {"seconds": seconds, "error": tms.correction_error(gp, system)}


def _design(device, cfg, method: str) -> dict:
    from torchmisspec import design

    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(0)
    candidates = design.candidates.uniform_box(cfg["candidates"], system.domain, generator=g).to(device)
    times = torch.linspace(0.0, 6.0, cfg["T"], dtype=torch.float64, device=device)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4, device=device)
    design.greedy(candidates[:50], 3, system=system, times=times, gp=gp)  # warm-up

    def run():
        stochastic = method == "stochastic"
        draws = {"engine": design.Engine(generator=torch.Generator(device).manual_seed(0))} if stochastic else {}
        return design.greedy(candidates, cfg["K"], system=system, times=times, gp=gp, method=method, **draws)

    plan, seconds = _clock(device, run)
    return {"seconds": seconds, "information_gain_nats": plan.information_gain}


def _row(fn, *args) -> dict:
    try:
        return fn(*args)
    except Exception as exc:  # a failure on one device is a row of the report, not the end of the run
        return {"error_message": f"{type(exc).__name__}: {exc}"[:300]}


def measure(cfg: dict) -> dict:
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    out = {}
    for device in devices:
        out[device.type] = {
            "large": _row(_large, device, cfg),
            "exact": _row(_exact, device, cfg),
            "stochastic": _row(_design, device, cfg, "stochastic"),
            "lazy": _row(_design, device, cfg, "lazy"),
        }
    return out


def _cell(row: dict, key: str, fmt: str) -> str:
    return f"failed: {row['error_message']}" if "error_message" in row else format(row[key], fmt)


def lines(result: dict, cfg: dict) -> list[str]:
    out = [
        "| device | what | wall time | accuracy |",
        "|---|---|---|---|",
    ]
    for device, rows in result.items():
        large, exact = rows["large"], rows["exact"]
        feats = "" if "error_message" in large else f", {large['features']} features"
        out.append(
            f"| {device} | fit, {cfg['large']} samples{feats} | {_cell(large, 'fit_seconds', '.2f')} s | "
            f"error of F {_cell(large, 'error', '.3g')} |"
        )
        out.append(
            f"| {device} | predict {cfg['trajectories']} trajectories (61 times) | "
            f"{_cell(large, 'predict_seconds', '.2f')} s | |"
        )
        out.append(
            f"| {device} | exact fit, {cfg['exact']} samples | {_cell(exact, 'seconds', '.2f')} s | "
            f"error of F {_cell(exact, 'error', '.3g')} |"
        )
        for method in ("stochastic", "lazy"):
            row = rows[method]
            out.append(
                f"| {device} | design, {cfg['candidates']} candidates, K = {cfg['K']}, T = {cfg['T']}, {method} | "
                f"{_cell(row, 'seconds', '.2f')} s | gain {_cell(row, 'information_gain_nats', '.4f')} nats |"
            )
    return out


def run(args) -> int:
    cfg = SMOKE if args.smoke else FULL
    result = measure(cfg)
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    block = [
        "## On a GPU (`scripts/benchmark_gpu.py`)",
        "",
        run_sentence(args) + f" GPU: {gpu}.",
        "The same calls on the machine's CPU (the peer, torch's default threads) and on its GPU, in one process, each "
        "timed once after a warm-up; float64 throughout.",
        "",
        *lines(result, cfg),
    ]
    publish(block, args.markdown, MARK_START, MARK_END)
    failed = [f"{d}/{k}" for d, rows in result.items() for k, row in rows.items() if "error_message" in row]
    return 1 if failed else 0
