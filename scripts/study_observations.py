"""Command line of :mod:`torchmisspec.paper.study_observations` (``--help`` prints that docstring first).

Usage::

    python scripts/study_observations.py --markdown     # full study: JSON, docs/studies/real-data.md, BENCHMARKS.md
    python scripts/study_observations.py --smoke --json /tmp/s.json   # tiny, < 1 min, never writes docs

Every number in the written pages comes from the run.
"""

from __future__ import annotations

import argparse
import sys

from torchmisspec.benchmarks.reporting import ROOT
from torchmisspec.paper import study_observations as study
from torchmisspec.paper import study_observations_report as report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=study.__doc__ + __doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--smoke", action="store_true", help="tiny: every system, K = 5, one noise level, 1 realization"
    )
    parser.add_argument(
        "--json",
        help=f"write raw runs and summary here (default {report.DEFAULT_JSON.relative_to(ROOT)}; "
        "with --smoke only when given)",
    )
    parser.add_argument(
        "--markdown",
        action="store_true",
        help="rewrite docs/studies/real-data.md and the study block of BENCHMARKS.md (not with --smoke)",
    )
    parser.add_argument(
        "--realizations", type=int, default=None, help=f"realizations per cell (default {study.REALIZATIONS})"
    )
    parser.add_argument(
        "--fit-max-iter", type=int, default=None, help=f"fit_trajectories max_iter (default {study.FIT_MAX_ITER})"
    )
    parser.add_argument("--systems", nargs="+", choices=[c.name for c in study.CASES], help="only these systems")
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="do not run: join the JSONs of full runs on disjoint --systems (run in parallel processes) into one "
        "result, written to --json (default the study's JSON) and, with --markdown, to the pages",
    )
    parser.add_argument(
        "--from-json",
        help="do not run: recompute the summary from this JSON of a full run and rewrite the pages (with --markdown)",
    )
    args = parser.parse_args(argv)
    args.parser = parser
    if args.merge:
        return report.merge(args)
    if args.from_json:
        return report.from_json(args)
    if args.smoke and args.markdown:
        parser.error("--markdown writes the docs and BENCHMARKS.md: not with --smoke")
    return report.run(
        args, "python scripts/study_observations.py " + " ".join(argv if argv is not None else sys.argv[1:])
    )


if __name__ == "__main__":
    raise SystemExit(main())
