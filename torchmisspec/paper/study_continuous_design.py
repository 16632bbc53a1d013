"""Study of issue 24 (part 4): initial states refined by gradients of the criterion, beyond the candidate list.

The system is the two-compartment drug model of the sampling-times study (F(C) = -0.8 C / (0.5 + C) missing on
dC/dt, every state measured). A realization draws 12 candidate initial states at random in the box central in
[0.5, 4] x peripheral in [0, 2] and designs K experiments before any data, with a stated prior (RBF, lengthscale
0.5, output scale 0.1, noise 1e-3), observed at 20 times on [0, 8]:

* **greedy**: ``design.greedy`` among the candidates (information criterion);
* **refined**: the greedy's picks moved by ``design.refine`` (Adam on the information gain, 60 steps, inside the
  box);
* **random**: K candidates at random.

Each design's experiments are simulated with 1 % multiplicative noise and F is learned with ``fit_correction``
(defaults). Reported per K: the information gain of each design (the criterion) and the integrated error of F over
central in [0, 4] (mean ± standard error over realizations), and the refined/greedy ratio of each per realization.
"""

from __future__ import annotations

import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.benchmarks.reporting import ROOT, run_study
from torchmisspec.metrics import mean_and_standard_error
from torchmisspec.paper.study_sampling_times import DOMAIN, PRIOR, system

DEFAULT_JSON = ROOT / "benchmarks" / "study_continuous_design.json"
DOC_PAGE = ROOT / "docs" / "studies" / "continuous-design.md"
MARK_START = "<!-- study:continuous-design:start -->"
MARK_END = "<!-- study:continuous-design:end -->"
DT = torch.float64
SEED = 24_600
FULL = {"realizations": 10, "ks": [2, 4], "candidates": 12, "times": 20, "steps": 60}
SMOKE = {"realizations": 1, "ks": [2], "candidates": 6, "times": 10, "steps": 5}
BOX = [(0.5, 4.0), (0.0, 2.0)]


def _error(y0: torch.Tensor, t: torch.Tensor, g: torch.Generator) -> float:
    clean = tms.simulate(system(truth=True), y0, t).states
    data = tms.Trajectories(t, clean * (1 + 0.01 * torch.randn(clean.shape, generator=g, dtype=DT)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, system(), progress=False)
    return float(tms.correction_error(gp, system(truth=True), domain=DOMAIN))


def run_one(K: int, seed: int, cfg: dict) -> dict:
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([b[0] for b in BOX], dtype=DT)
    hi = torch.tensor([b[1] for b in BOX], dtype=DT)
    candidates = lo + (hi - lo) * torch.rand(cfg["candidates"], 2, generator=g, dtype=DT)
    t = torch.linspace(0, 8, cfg["times"], dtype=DT)
    prior = tms.CorrectionGP(**PRIOR)
    plan = design.greedy(candidates, K, system=system(), times=t, gp=prior)
    t0 = time.perf_counter()
    refined = design.refine(plan.points, system=system(), times=t, gp=prior, box=BOX, steps=cfg["steps"])
    seconds = time.perf_counter() - t0
    pick = torch.randperm(cfg["candidates"], generator=g)[:K]
    chance = design.information_gain(
        system().select_inputs(design.proxy_trajectories(system(), candidates[pick], t)).reshape(-1, 1),
        prior,
        d_out=1,
    )
    return {
        "seed": seed,
        "gain": {"greedy": plan.information_gain, "refined": refined.information_gain, "random": chance},
        "error": {
            "greedy": _error(plan.points, t, g),
            "refined": _error(refined.points, t, g),
            "random": _error(candidates[pick], t, g),
        },
        "refine_seconds": seconds,
        "moved": float((refined.points - plan.points).abs().max()),
    }


def study(cfg: dict, log=print) -> dict:
    runs = {}
    for K in cfg["ks"]:
        runs[str(K)] = []
        for r in range(cfg["realizations"]):
            one = run_one(K, SEED + 100 * K + r, cfg)
            runs[str(K)].append(one)
            log(
                f"K={K} {r}: gain greedy {one['gain']['greedy']:.2f} refined {one['gain']['refined']:.2f} random "
                f"{one['gain']['random']:.2f}; error greedy {one['error']['greedy']:.4f} refined "
                f"{one['error']['refined']:.4f} random {one['error']['random']:.4f}"
            )
    return {"config": cfg, "prior": PRIOR, "box": BOX, "runs": runs}


def _summary(values, digits: int = 4) -> str:
    x = torch.tensor(values, dtype=DT)
    m, se = mean_and_standard_error(x)
    return f"{float(m):.{digits}f} ± {float(se):.{digits}f}"


def _range(values) -> str:
    x = torch.tensor(values, dtype=DT)
    m, se = mean_and_standard_error(x)
    spread = f"({float(x.min()):.3f}-{float(x.max()):.3f})"
    return f"{float(m):.3f} ± {float(se):.3f}, median {float(x.median()):.3f} {spread}"


def table(result: dict) -> str:
    lines = [
        "| K | information gain: greedy | refined | random | refined / greedy | error of F: greedy | refined | random "
        "| refined / greedy |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for K, runs in result["runs"].items():
        gains = [_summary([r["gain"][a] for r in runs], 2) for a in ("greedy", "refined", "random")]
        errors = [_summary([r["error"][a] for r in runs]) for a in ("greedy", "refined", "random")]
        gain_ratio = _range([r["gain"]["refined"] / r["gain"]["greedy"] for r in runs])
        error_ratio = _range([r["error"]["refined"] / r["error"]["greedy"] for r in runs])
        lines.append(f"| {K} | {' | '.join(gains)} | {gain_ratio} | {' | '.join(errors)} | {error_ratio} |")
    secs = sorted(r["refine_seconds"] for runs in result["runs"].values() for r in runs)
    lines += [
        "",
        f"Seconds of one `design.refine` ({result['config']['steps']} steps): median {secs[len(secs) // 2]:.1f}.",
    ]
    return "\n".join(lines) + "\n"


def render_block(result: dict, wall: float) -> str:
    info = result["machine"]
    return f"""{MARK_START}
## Refining a design by gradients (`scripts/study_continuous_design.py`)

Written by `python scripts/study_continuous_design.py --markdown` ({wall / 60:.1f} min, {info["cpu"]},
{info["logical_cpus"]} logical CPUs): greedy among 12 candidates, the same picks refined by gradients, and random,
{result["config"]["realizations"]} realizations per K; see
[docs/studies/continuous-design.md](docs/studies/continuous-design.md).

{table(result)}{MARK_END}
"""


def render_page(result: dict, wall: float) -> str:
    info = result["machine"]
    rows = [
        "| K | seed | gain greedy / refined | error greedy / refined / random | largest move |",
        "|---|---|---|---|---|",
    ]
    for K, runs in result["runs"].items():
        for r in runs:
            rows.append(
                f"| {K} | {r['seed']} | {r['gain']['greedy']:.2f} / {r['gain']['refined']:.2f} | "
                f"{r['error']['greedy']:.4f} / {r['error']['refined']:.4f} / {r['error']['random']:.4f} | "
                f"{r['moved']:.2f} |"
            )
    return f"""# Study: refining a design by gradients

This page is written by `python scripts/study_continuous_design.py --markdown`; every number on it comes from that
run (raw numbers: `benchmarks/study_continuous_design.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical
CPUs, torch {info["torch"]}, commit {info["git_commit"]}; wall time {wall / 60:.1f} min.

{__doc__.strip()}

{table(result)}
Per realization:

{chr(10).join(rows)}
"""


def run(args) -> int:
    """The study's command line run (:func:`~torchmisspec.benchmarks.reporting.run_study`)."""
    import sys

    return run_study(args, sys.modules[__name__])
