"""Command line of :mod:`torchmisspec.benchmarks.posterior` (``--help`` prints that docstring first).

Usage::

    python scripts/benchmark_posterior.py --markdown      # writes the block of BENCHMARKS.md
    python scripts/benchmark_posterior.py --smoke         # tiny sizes, prints only
    python scripts/benchmark_posterior.py --posterior-only  # issue 10 only, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import posterior
from torchmisspec.benchmarks.reporting import benchmark_arguments


def _posterior_only(parser) -> None:
    parser.add_argument(
        "--posterior-only", action="store_true", help="time issue 10 only (prints; never writes BENCHMARKS.md)"
    )


def main(argv: list[str] | None = None) -> int:
    args = benchmark_arguments(posterior.__doc__ + __doc__, argv, extra=_posterior_only)
    if args.posterior_only and args.markdown:
        args.parser.error("--posterior-only never writes BENCHMARKS.md (the block needs issue 9's rows too)")
    return posterior.run(args)


if __name__ == "__main__":
    raise SystemExit(main())
