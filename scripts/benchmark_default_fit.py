"""Command line of :mod:`torchmisspec.benchmarks.default_fit` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_default_fit.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_default_fit.py --smoke        # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import default_fit
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return default_fit.run(benchmark_arguments(default_fit.__doc__ + __doc__, argv))


if __name__ == "__main__":
    raise SystemExit(main())
