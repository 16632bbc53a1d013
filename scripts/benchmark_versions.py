"""Command line of :mod:`torchmisspec.benchmarks.versions` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_versions.py --base REV --markdown   # writes the block of BENCHMARKS.md
    python scripts/benchmark_versions.py --base HEAD --smoke      # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import versions
from torchmisspec.benchmarks.reporting import benchmark_arguments


def _extra(parser) -> None:
    parser.add_argument("--base", required=True, help="the revision to compare with (a commit, tag or branch)")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each version, alternating which goes first")
    parser.add_argument("--json", help="also write every repeat here")


def main(argv: list[str] | None = None) -> int:
    return versions.run(benchmark_arguments(versions.__doc__ + __doc__, argv, extra=_extra))


if __name__ == "__main__":
    raise SystemExit(main())
