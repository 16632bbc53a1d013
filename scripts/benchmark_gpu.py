"""Command line of :mod:`torchmisspec.benchmarks.gpu` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_gpu.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_gpu.py --smoke        # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import gpu
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return gpu.run(benchmark_arguments(gpu.__doc__ + __doc__, argv))


if __name__ == "__main__":
    raise SystemExit(main())
