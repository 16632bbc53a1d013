"""Cost of one round of the design loop (issue 11): refit on 500 samples + design 3 from 10,000 candidates, T = 20.

Set-up: paper_gravity (paper 5.3), 10,000 candidates from ``design.candidates.orbits`` (seed 0), observation times
T = 20 on [0, 3]; 25 experiments already run (500 correction samples, oracle derivatives with noise std 1e-2).
One round is ``Campaign.tell`` of those experiments (correction samples + hyperparameters learned by marginal
likelihood on the 500 samples) followed by ``Campaign.ask(3)`` (corrected proxies of all 10,000 candidates, gains
conditioned on the 500 samples). Target: under 5 s. Timed in the same run: the same round with the exact data term
(``GPKernel(exact_data=True)``, every kernel block solving against the 500 x 500 factor, the previous
implementation) as the reference, and the domain criterion. Medians of ``--repeats``.

``scripts/benchmark_campaign.py`` is its command line.
"""

from __future__ import annotations

import statistics
import time

import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.design import _common, _greedy
from torchmisspec.paper import _setup

from .reporting import publish, run_sentence, timed

MARK_START = "<!-- bench:campaign:start -->"
MARK_END = "<!-- bench:campaign:end -->"
FULL = {"candidates": 10_000, "experiments": 25, "batch": 3}
SMOKE = {"candidates": 300, "experiments": 4, "batch": 2}


class _ExactKernel(_common.GPKernel):
    """The reference: the data term solved exactly in every kernel block."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, exact_data=True, **kwargs)


def one_round(cfg: dict, criterion: str, exact: bool) -> dict:
    system = tms.systems.paper_gravity()
    times = _setup.gravity_times()
    cand = design.candidates.orbits(cfg["candidates"], generator=torch.Generator().manual_seed(0))
    ran = torch.randperm(cfg["candidates"], generator=torch.Generator().manual_seed(1))[: cfg["experiments"]]
    measured = tms.simulate(system, cand[ran], times)  # the experiments already run (not timed)
    prior = tms.CorrectionGP(**_setup.GRAVITY_PRIOR)
    camp = design.Campaign(
        system, cand, times, prior, criterion=criterion, derivative="oracle", noise_std=_setup.NOISE_STD, refit_after=40
    )
    original = _greedy.GPKernel
    if exact:
        _greedy.GPKernel = _ExactKernel
    try:
        t0 = time.perf_counter()
        camp.tell(measured)
        t1 = time.perf_counter()
        camp.ask(cfg["batch"])
        t2 = time.perf_counter()
    finally:
        _greedy.GPKernel = original
    ask = camp.history[-1]
    return {
        "tell": t1 - t0,
        "ask": t2 - t1,
        "selection": ask["design"]["selection_seconds"],
        "round": t2 - t0,
        "samples": camp.num_samples,
        "learned": camp.history[-2]["learned"],
        "picks": ask["indices"],
    }


def mean_blocks(cfg: dict, repeats: int) -> tuple[float, float]:
    """Median seconds of the posterior mean at the candidates' positions (GP on the round's samples), in row blocks
    and as one block (``MEAN_BLOCK`` raised past the size)."""
    from torchmisspec.gp import _posterior

    system = tms.systems.paper_gravity()
    times = _setup.gravity_times()
    cand = design.candidates.orbits(cfg["candidates"], generator=torch.Generator().manual_seed(0))
    ran = torch.randperm(cfg["candidates"], generator=torch.Generator().manual_seed(1))[: cfg["experiments"]]
    samples = tms.correction_samples(
        tms.simulate(system, cand[ran], times), system, derivative="oracle", noise_std=_setup.NOISE_STD
    )
    gp = tms.CorrectionGP(**_setup.GRAVITY_PRIOR).fit(samples)
    x = system.select_inputs(cand)
    posterior = gp.posterior()

    def median() -> float:
        return timed(lambda: posterior.mean(x, check=False), max(repeats, 3))[1]

    blocked = median()
    saved, _posterior.MEAN_BLOCK = _posterior.MEAN_BLOCK, 10**15
    try:
        whole = median()
    finally:
        _posterior.MEAN_BLOCK = saved
    return blocked, whole


def median_of(runs: list[dict]) -> dict:
    out = dict(runs[-1])
    for key in ("tell", "ask", "selection", "round"):
        out[key] = statistics.median(r[key] for r in runs)
    return out


def run(args) -> int:
    """The benchmark, with the arguments of :func:`~torchmisspec.benchmarks.reporting.benchmark_arguments`: prints
    its block, and with ``args.markdown`` writes it into BENCHMARKS.md."""
    cfg = SMOKE if args.smoke else FULL
    repeats = 1 if args.smoke else args.repeats
    one_round(SMOKE, "information", False)  # warm-up (first calls pay for imports and allocations): not recorded
    rows = {}
    for label, criterion, exact, n in (
        ("information (default)", "information", False, repeats),
        ("domain", "domain", False, repeats),
        ("information, exact data term (reference)", "information", True, 1),
    ):
        rows[label] = median_of([one_round(cfg, criterion, exact) for _ in range(n)])
        print(label, rows[label])
    same = rows["information (default)"]["picks"] == rows["information, exact data term (reference)"]["picks"]
    blocked, whole = mean_blocks(cfg, repeats)
    lines = [
        "## One round of the design loop (`scripts/benchmark_campaign.py`)",
        "",
        run_sentence(args) + " "
        f"paper_gravity, {cfg['candidates']} candidate orbits, T = 20, {rows['domain']['samples']} samples from "
        f"{cfg['experiments']} experiments; a round = `tell` (samples + hyperparameters learned by marginal "
        f"likelihood) + `ask({cfg['batch']})` (corrected proxies of every candidate, gains conditioned on the data). "
        f"Medians of {repeats} (the reference: 1 run). Target: a round under 5 s.",
        "",
        "| round | tell (refit) s | ask s | of which selection s | round s |",
        "|---|---|---|---|---|",
    ]
    for label, r in rows.items():
        lines.append(f"| {label} | {r['tell']:.2f} | {r['ask']:.2f} | {r['selection']:.2f} | {r['round']:.2f} |")
    ref = rows["information, exact data term (reference)"]["selection"]
    new = rows["information (default)"]["selection"]
    lines += [
        "",
        f"Selection {ref / new:.1f}x faster than with the exact data term; same picks as the reference: {same}.",
        f"The posterior mean at all {cfg['candidates']} candidates' initial positions (the corrected proxies' "
        f"right-hand side): {blocked * 1e3:.1f} ms in row blocks of `MEAN_BLOCK` kernel entries, {whole * 1e3:.1f} ms "
        f"as one block ({whole / blocked:.1f}x).",
    ]
    publish(lines, args.markdown, MARK_START, MARK_END)
    return 0
