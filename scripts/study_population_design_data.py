"""Command line of :mod:`torchmisspec.paper.study_population_design_data` (``--help`` prints that docstring first).

Usage::

    python scripts/study_population_design_data.py --markdown --workers 2   # full: JSON, docs page, BENCHMARKS.md
    python scripts/study_population_design_data.py --smoke --json /tmp/d.json   # 1 subject left out, never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_population_design_data as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
