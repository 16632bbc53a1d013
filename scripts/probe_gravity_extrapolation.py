"""Where on the gravity set-up the kernels' errors come from: near the samples or far from them (issue 12).

For one realization of the kernel study (``scripts/study_kernels.py``: K random orbits, its seeds), each kernel's
squared error of F over the 81 x 81 grid of D is split by the distance from the grid point to the nearest sample:
near (< 0.2) and far (>= 0.5). Prints each kernel's evidence score, errors and the fraction of D that is far.

Usage::

    python scripts/probe_gravity_extrapolation.py --k 10 --realization 2
"""

from __future__ import annotations

import argparse

from torchmisspec.paper.study_kernels import gravity_extrapolation


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--k", type=int, default=10, help="number of orbits")
    parser.add_argument("--realization", type=int, default=2, help="realization index of the kernel study")
    args = parser.parse_args(argv)
    gravity_extrapolation(args.k, args.realization)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
