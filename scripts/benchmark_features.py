"""Fit cost of the feature kernel on many samples (issue 12): p <= 50 features, N = 10,000 samples, target < 1 s.

``CorrectionGP(kernel="features", degree=8)`` on 2 inputs has p = 45 monomials; also degree 2 (p = 6), weights shared
by the two outputs and one set per output. The samples are F(x) = (0.01 x1^2, 0.01 x2^2 + 0.003 x1) plus noise of
std 1e-2 at N points uniform in [-1, 1]^2. A fit is the sparse Bayesian learning of the weights and the noise plus
the feature-space posterior. The reference, timed in the same run: the dense factorization of the same N x N
covariance (what the posterior cost before, one Cholesky of K + D). Medians of ``--repeats``.

Usage::

    python scripts/benchmark_features.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_features.py --smoke        # N = 2,000, prints only
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import benchmark_arguments, publish, run_sentence  # noqa: E402 (the scripts' shared helper)

import torchmisspec as tms  # noqa: E402
from torchmisspec.gp import _mll  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MARK_START = "<!-- bench:features:start -->"
MARK_END = "<!-- bench:features:end -->"
DT = torch.float64


def data(n: int):
    g = torch.Generator().manual_seed(0)
    X = torch.rand(n, 2, dtype=DT, generator=g) * 2 - 1
    F = torch.stack([0.01 * X[:, 0] ** 2, 0.01 * X[:, 1] ** 2 + 0.003 * X[:, 0]], -1)
    return X, F + 1e-2 * torch.randn(n, 2, dtype=DT, generator=g)


def timed(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    args = benchmark_arguments(__doc__, argv, smoke_help="N = 2,000; never writes BENCHMARKS.md")
    n = 2_000 if args.smoke else 10_000
    repeats = 1 if args.smoke else args.repeats
    X, Y = data(n)
    tms.CorrectionGP(kernel="features", degree=2).fit(X[:200], Y[:200])  # warm-up, not recorded
    rows = []
    gp = None
    for degree in (2, 8):
        for per_output in (False, True):
            gp, seconds = timed(
                lambda d=degree, po=per_output: tms.CorrectionGP(kernel="features", degree=d, per_output=po).fit(X, Y),
                repeats,
            )
            p = gp.covar_module.base_kernel.powers.shape[0]
            active = int((gp.weights > 0).sum())
            rows.append((degree, p, per_output, seconds, active))
            print(rows[-1])
    # the reference: the dense factorization of the last model's covariance
    with torch.no_grad():
        K, diag = gp._kernel_parts(gp.train_inputs_)
        Yb = gp._targets_batched(gp.train_targets_)
        _, dense = timed(lambda: _mll.factorize(K, diag, Yb), 1)
    lines = [
        "## Feature kernel fit on many samples (`scripts/benchmark_features.py`)",
        "",
        run_sentence(args) + " "
        f"N = {n} samples of a 2-input, 2-output polynomial F with noise; medians of {repeats}. Target: p <= 50 "
        "features in under 1 s.",
        "",
        "| degree | features p | weights | fit s | terms kept (all outputs) |",
        "|---|---|---|---|---|",
    ]
    for degree, p, per_output, seconds, active in rows:
        lines.append(f"| {degree} | {p} | {'per output' if per_output else 'shared'} | {seconds:.3f} | {active} |")
    lines += [
        "",
        f"Reference in the same run: the dense factorization of the same {n} x {n} covariance (the posterior's cost "
        f"before it moved to feature space) takes {dense:.2f} s on its own.",
    ]
    publish(lines, args.markdown, MARK_START, MARK_END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
