"""Command line of :mod:`torchmisspec.paper.study_design_readout` (``--help`` prints that docstring first).

Usage::

    python scripts/study_design_readout.py --markdown --workers 2   # full: JSON, docs/studies/design-readout.md
    python scripts/study_design_readout.py --smoke --json /tmp/d.json   # 1 realization, K = 2, never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_design_readout as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
