"""Command line of :mod:`torchmisspec.benchmarks.large_design` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_large_design.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_large_design.py --smoke        # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import large_design
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return large_design.run(benchmark_arguments(large_design.__doc__ + __doc__, argv))


if __name__ == "__main__":
    raise SystemExit(main())
