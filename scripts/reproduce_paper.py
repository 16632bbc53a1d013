#!/usr/bin/env python
"""Regenerate the figures of the paper's §5 and the numbers behind them (logic: torchmisspec.paper.figures).

    python scripts/reproduce_paper.py --all                   # all eight figures into reproduction-output/
    python scripts/reproduce_paper.py --figure 1 --figure 2   # some figures
    python scripts/reproduce_paper.py --all --smoke           # tiny sizes, checks everything runs (CI)
    python scripts/reproduce_paper.py --all --out DIR --seed 3 --quiet
    python scripts/reproduce_paper.py --all --threads 0       # torch's default thread count (default: 1)

Writes figN.png (and a few figN_<panel>.png) and results.json (figure -> measured numbers, timings, smoke flag,
realization counts) into --out, and prints each figure's time and key numbers unless --quiet.
"""

from __future__ import annotations

import argparse
import sys
import time

from torchmisspec.paper.figures import FIGURES, reproduce
from torchmisspec.paper.reproduction import summary


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="reproduce_paper.py",
        description="Regenerate the figures of paper §5 (Numerical Experiments) with the numbers behind them.",
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--figure",
        type=int,
        action="append",
        choices=sorted(FIGURES),
        metavar="N",
        help="figure number 1-8 (repeatable)",
    )
    which.add_argument("--all", action="store_true", help="all eight figures")
    p.add_argument("--out", default="reproduction-output", help="output folder (default: %(default)s)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes: checks that everything runs, in seconds")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads (default: %(default)s; the problems are small, one thread is fastest on a "
        "shared machine; 0 keeps torch's default)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    figures = sorted(FIGURES) if args.all else args.figure
    t0 = time.perf_counter()
    if args.threads < 0:
        _parser().error(f"argument --threads: expected an integer >= 0, got {args.threads}")
    results = reproduce(
        figures, args.out, smoke=args.smoke, seed=args.seed, progress=not args.quiet, threads=args.threads or None
    )
    if not args.quiet:
        print(summary(results))
        print(f"wrote {args.out}/results.json in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
