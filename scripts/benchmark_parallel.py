"""Command line of :mod:`torchmisspec.benchmarks.parallel` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_parallel.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_parallel.py --smoke        # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import parallel
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return parallel.run(benchmark_arguments(parallel.__doc__ + __doc__, argv))


if __name__ == "__main__":
    raise SystemExit(main())
