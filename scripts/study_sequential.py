"""Study of issue 11: designing experiments in rounds, given the data, against one-shot designs and random sets.

Runs :func:`torchmisspec.paper.studies.sequential_study` on paper 5.2 (paper_linear, 13 x 13 grid, K = 1-20) and on
the gravity set-up (paper 5.3, 300 orbits, K = 1-10) with fixed seeds, and reports the error vs K of every strategy
with standard errors, the paired ratios to random sets and to the paper's one-shot design, and the issue's goals:

* paper 5.2: ``domain design`` / random <= 1.0 within one standard error at every K = 1-20, and <= 0.85 on average
  over K = 5-20;
* gravity: a sequential design below the paper's one-shot (aided) design on average over K = 1-10.

Usage::

    python scripts/study_sequential.py --markdown                 # full: JSON, docs/studies/sequential.md, figures
    python scripts/study_sequential.py --smoke --json /tmp/s.json  # tiny, never writes the docs
    python scripts/study_sequential.py --from-json benchmarks/study_sequential.json --markdown
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_sequential as study


def _add_single(parser) -> None:
    parser.add_argument(
        "--add-single", action="store_true", help="with --from-json: compute the K = 1 brute force and add it"
    )


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(__doc__, argv, study.DEFAULT_JSON, _add_single))


if __name__ == "__main__":
    raise SystemExit(main())
