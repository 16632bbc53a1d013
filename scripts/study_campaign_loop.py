"""Command line of :mod:`torchmisspec.paper.study_campaign_loop` (``--help`` prints that docstring first).

Usage::

    python scripts/study_campaign_loop.py --markdown          # full: JSON, docs/studies/end-to-end.md, BENCHMARKS.md
    python scripts/study_campaign_loop.py --smoke --json /tmp/e.json   # 2 realizations, never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_campaign_loop as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
