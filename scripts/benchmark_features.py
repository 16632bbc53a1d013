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

from torchmisspec.benchmarks import features
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return features.run(benchmark_arguments(__doc__, argv, smoke_help="N = 2,000; never writes BENCHMARKS.md"))


if __name__ == "__main__":
    raise SystemExit(main())
