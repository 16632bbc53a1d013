"""Cost of one round of the design loop (issue 11): refit on 500 samples + design 3 from 10,000 candidates, T = 20.

Set-up: paper_gravity (paper 5.3), 10,000 candidates from ``design.candidates.orbits`` (seed 0), observation times
T = 20 on [0, 3]; 25 experiments already run (500 correction samples, oracle derivatives with noise std 1e-2).
One round is ``Campaign.tell`` of those experiments (correction samples + hyperparameters learned by marginal
likelihood on the 500 samples) followed by ``Campaign.ask(3)`` (corrected proxies of all 10,000 candidates, gains
conditioned on the 500 samples). Target: under 5 s. Timed in the same run: the same round with the exact data term
(``GPKernel(exact_data=True)``, every kernel block solving against the 500 x 500 factor, the previous
implementation) as the reference, and the domain criterion. Medians of ``--repeats``.

Usage::

    python scripts/benchmark_campaign.py --markdown     # writes the block of BENCHMARKS.md
    python scripts/benchmark_campaign.py --smoke        # tiny sizes, prints only
"""

from __future__ import annotations

from torchmisspec.benchmarks import campaign
from torchmisspec.benchmarks.reporting import benchmark_arguments


def main(argv: list[str] | None = None) -> int:
    return campaign.run(benchmark_arguments(__doc__, argv))


if __name__ == "__main__":
    raise SystemExit(main())
