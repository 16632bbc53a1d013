"""Command line of :mod:`torchmisspec.benchmarks.large_fit` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_large_fit.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_large_fit.py --smoke        # tiny sizes, prints only
    python scripts/benchmark_large_fit.py --kernel matern52 --markdown   # the Matern 5/2 kernel's block
"""

from __future__ import annotations

from torchmisspec.benchmarks import large_fit
from torchmisspec.benchmarks.reporting import benchmark_arguments


def _kernel(parser) -> None:
    parser.add_argument(
        "--kernel", choices=["rbf", "matern52"], default="rbf", help="the kernel measured (its own block)"
    )


def main(argv: list[str] | None = None) -> int:
    return large_fit.run(benchmark_arguments(large_fit.__doc__ + __doc__, argv, extra=_kernel))


if __name__ == "__main__":
    raise SystemExit(main())
