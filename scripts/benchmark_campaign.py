"""Command line of :mod:`torchmisspec.benchmarks.campaign` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_campaign.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_campaign.py --smoke        # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import campaign
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return campaign.run(benchmark_arguments(campaign.__doc__ + __doc__, argv))


if __name__ == "__main__":
    raise SystemExit(main())
