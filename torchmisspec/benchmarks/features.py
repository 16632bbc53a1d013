"""Fit cost of the feature kernel on many samples (issue 12): p <= 50 features, N = 10,000 samples, target < 1 s.

``CorrectionGP(kernel="features", degree=8)`` on 2 inputs has p = 45 monomials; also degree 2 (p = 6), weights shared
by the two outputs and one set per output. The samples are F(x) = (0.01 x1^2, 0.01 x2^2 + 0.003 x1) plus noise of
std 1e-2 at N points uniform in [-1, 1]^2. A fit is the sparse Bayesian learning of the weights and the noise plus
the feature-space posterior. The reference, timed in the same run: the dense factorization of the same N x N
covariance (what the posterior cost before, one Cholesky of K + D). Medians of ``--repeats``.

``scripts/benchmark_features.py`` is its command line.
"""

from __future__ import annotations

import torch

import torchmisspec as tms
from torchmisspec.gp import _mll

from .reporting import publish, run_sentence, timed

MARK_START = "<!-- bench:features:start -->"
MARK_END = "<!-- bench:features:end -->"
DT = torch.float64


def data(n: int):
    g = torch.Generator().manual_seed(0)
    X = torch.rand(n, 2, dtype=DT, generator=g) * 2 - 1
    F = torch.stack([0.01 * X[:, 0] ** 2, 0.01 * X[:, 1] ** 2 + 0.003 * X[:, 0]], -1)
    return X, F + 1e-2 * torch.randn(n, 2, dtype=DT, generator=g)


def run(args) -> int:
    """The benchmark, with the arguments of :func:`~torchmisspec.benchmarks.reporting.benchmark_arguments`: prints
    its block, and with ``args.markdown`` writes it into BENCHMARKS.md."""
    n = 2_000 if args.smoke else 10_000
    repeats = 1 if args.smoke else args.repeats
    X, Y = data(n)
    tms.CorrectionGP(kernel="features", degree=2).fit(X[:200], Y[:200])  # warm-up, not recorded
    rows = []
    gp = None
    for degree in (2, 8):
        for per_output in (False, True):
            gp, seconds, _ = timed(
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
        _, dense, _ = timed(lambda: _mll.factorize(K, diag, Yb), 1)
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
