"""Costs of issues 9 and 10 measured in one run, written as a block of BENCHMARKS.md.

* Issue 10: ``CorrectedODE.posterior`` with 1,000 initial conditions x 64 draws x 61 times on paper_linear (GP on 440
  samples: 40 trajectories x 11 times, oracle noise std 1e-2) against the mean-only ``predict`` on the same 1,000
  initial conditions (target: at most 20x its time); both timed in this process, medians of ``--repeats``. Also
  timed: the posterior with the previous default prior features (800 random Fourier features, ``num_features=800``)
  and two parts of the default posterior (building the draws; the support check along the mean paths).
* Issue 9: ``derivative="gp"`` on 40 experiments x 21 times (target < 1 s), ``fit_trajectories`` (single shooting,
  the default) and ``fit_correction`` (cross-validated lengthscale) on the same data with 1 % state noise (target
  for fit_trajectories < 30 s).

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
    args = benchmark_arguments(__doc__, argv, extra=_posterior_only)
    if args.posterior_only and args.markdown:
        args.parser.error("--posterior-only never writes BENCHMARKS.md (the block needs issue 9's rows too)")
    return posterior.run(args)


if __name__ == "__main__":
    raise SystemExit(main())
