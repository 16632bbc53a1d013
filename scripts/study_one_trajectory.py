"""Command line of :mod:`torchmisspec.paper.study_one_trajectory` (``--help`` prints that docstring first).

Usage::

    OMP_NUM_THREADS=1 python scripts/study_one_trajectory.py            # full: 10 realizations per protocol, JSON
    python scripts/study_one_trajectory.py --smoke --json /tmp/o.json   # 1 realization per protocol
    python scripts/study_one_trajectory.py --realizations 5             # fewer realizations (seeds 0..4)
    python scripts/study_one_trajectory.py --protocols gpode_van_der_pol --json /tmp/v.json   # one protocol
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_one_trajectory as study


def _extra(parser) -> None:
    parser.add_argument("--realizations", type=int, help="realizations per protocol (seeds 0..n-1; default 10)")
    parser.add_argument("--protocols", nargs="+", help="run only these protocols (default: all)")


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON, extra=_extra))


if __name__ == "__main__":
    raise SystemExit(main())
