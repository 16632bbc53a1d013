"""Studies through an executor (issue 26): the sampling-times study's realizations serially and in a local pool of
2 processes (``torchmisspec.parallel.process_pool``, one torch thread each), on this machine's cores.

Set-up: ``study_sampling_times`` at its full size (T = 20, 41 candidate times) for K = 2 and 4, ``realizations``
each, with the serial run given torch's own thread count. Reported: both wall times, the throughput ratio
(target >= 1.7x with 2 workers on 2 cores) and whether every number of the two runs is the same.

``scripts/benchmark_parallel.py`` is its command line.
"""

from __future__ import annotations

import time

import torch

from ..paper import study_sampling_times as study
from ..parallel import process_pool
from .reporting import publish, run_sentence

MARK_START = "<!-- bench:parallel:start -->"
MARK_END = "<!-- bench:parallel:end -->"
FULL = {**study.FULL, "realizations": 4}
SMOKE = {**study.SMOKE, "realizations": 2}


def run(args) -> int:
    cfg = SMOKE if args.smoke else FULL
    quiet = lambda *a, **k: None  # noqa: E731
    t0 = time.perf_counter()
    serial = study.study(cfg, log=quiet)
    serial_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    with process_pool(2) as pool:
        pooled = study.study(cfg, log=quiet, executor=pool)
    pooled_s = time.perf_counter() - t0
    same = serial["runs"] == pooled["runs"]
    speed = serial_s / pooled_s
    tasks = len(cfg["ks"]) * cfg["realizations"]
    block = [
        "## Studies through an executor (`scripts/benchmark_parallel.py`)",
        "",
        run_sentence(args),
        f"`study_sampling_times` at T = {cfg['times']}, {cfg['candidates']} candidate times, K in {cfg['ks']}, "
        f"{cfg['realizations']} realizations each ({tasks} independent tasks); serial with {torch.get_num_threads()} "
        "torch threads, then `process_pool(2)` (spawned processes, one torch thread each, start-up included).",
        "",
        "| run | wall time | tasks per minute |",
        "|---|---|---|",
        f"| serial | {serial_s:.1f} s | {60 * tasks / serial_s:.2f} |",
        f"| 2 processes | {pooled_s:.1f} s | {60 * tasks / pooled_s:.2f} |",
        "",
        f"Throughput {speed:.2f}x the serial run's (target >= 1.7x: {'met' if speed >= 1.7 else 'not met'}); every "
        f"number the same: {same}.",
    ]
    publish(block, args.markdown, MARK_START, MARK_END)
    return 0 if same else 1
