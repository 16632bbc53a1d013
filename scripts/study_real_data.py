"""Command line of :mod:`torchmisspec.paper.study_real_data` (``--help`` prints that docstring first).

Usage::

    OMP_NUM_THREADS=1 python scripts/study_real_data.py --markdown   # full: JSON and docs/studies/real-data-suite.md
    python scripts/study_real_data.py --smoke --json /tmp/r.json     # 2 data sets, 1 fold each; never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_real_data as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
