"""Command line of :mod:`torchmisspec.paper.study_population_design` (``--help`` prints that docstring first).

Usage::

    python scripts/study_population_design.py --markdown          # full: JSON, docs/studies/absorbed.md, BENCHMARKS.md
    python scripts/study_population_design.py --smoke --json /tmp/p.json   # 1 realization, never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_population_design as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
