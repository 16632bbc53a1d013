"""``scripts/benchmark.py``: every benchmark family against its peers in one run, the results as JSON and the page
BENCHMARKS.md (:func:`torchmisspec.benchmarks.page.render_markdown`)."""

from __future__ import annotations

import json
import os
import platform
import re
import time

import torch

from . import contention, design, fitting, prediction, states
from .page import load_line, render_markdown
from .reporting import cpu_model, load_average, memory_gb, version

BENCHMARKS = {
    "fit": fitting.bench_fit,
    "gradient": fitting.bench_gradient,
    "predict": prediction.bench_predict,
    "design": design.bench_design,
    "naive": design.bench_naive,
    "contention": contention.bench_contention,
    "realdata": states.bench_realdata,
}
WORKERS = {"design": design._design_worker, "contention": contention._contention_worker}
STUDY_BLOCK = re.compile(r"<!-- (study|bench):([\w-]+):start -->.*?<!-- \1:\2:end -->", re.S)


def machine() -> dict:
    """The machine and the versions of the package's peers, as the page reports them."""
    return {
        "cpu": cpu_model(),
        "logical_cpus": os.cpu_count(),
        "memory_gb": memory_gb(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "gpytorch": version("gpytorch"),
        "scikit-learn": version("sklearn"),
        "gpu": torch.cuda.is_available(),
    }


def run(names: list[str], smoke: bool, repeats: int, command: str) -> dict:
    """Run the benchmarks ``names`` (printing each result as it comes); every result, the machine and the load."""
    results = {
        "command": command,
        "machine": machine(),
        "load_before": load_average(),
        "smoke": smoke,
        "repeats": repeats,
    }
    for name in names:
        print(f"--- {name}", flush=True)
        t0 = time.perf_counter()
        results[name] = BENCHMARKS[name](smoke, repeats)
        print(json.dumps(results[name], indent=2), flush=True)
        print(f"--- {name}: {time.perf_counter() - t0:.1f} s, load {load_line(load_average())}", flush=True)
    results["load_after"] = load_average()
    return results


def write_results(results: dict, path: str) -> None:
    """The results as JSON (indented, every repeat)."""
    with open(path, "w") as fh:
        json.dump(results, fh, indent=2)
        fh.write("\n")


def write_page(results: dict, path: str) -> None:
    """Write the page to ``path``, keeping the blocks that the other scripts maintain there (``study:*``)."""
    page = render_markdown(results)
    if os.path.exists(path):
        with open(path) as fh:
            old = fh.read()
        blocks = [m.group(0) for m in STUDY_BLOCK.finditer(old)]
        page = page.rstrip("\n") + "".join(f"\n\n{block}" for block in blocks) + "\n"
    with open(path, "w") as fh:
        fh.write(page)
