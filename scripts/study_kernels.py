"""Command line of :mod:`torchmisspec.paper.study_kernels` (``--help`` prints that docstring first).

Usage::

    python scripts/study_kernels.py --markdown                  # full: JSON, docs/studies/kernels.md, BENCHMARKS
    python scripts/study_kernels.py --smoke --json /tmp/k.json  # tiny, never writes the docs
    python scripts/study_kernels.py --from-json benchmarks/study_kernels.json --markdown

pysindy is an optional benchmark dependency: ``pip install -e ".[bench]"``.
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_kernels as study


def main(argv: list[str] | None = None) -> int:
    args = study_arguments(study.__doc__ + __doc__, argv, study.DEFAULT_JSON)
    try:
        import pysindy  # noqa: F401
    except ImportError:
        args.parser.error('pysindy is needed for the SINDy baseline: pip install -e ".[bench]"')
    return study.run(args)


if __name__ == "__main__":
    raise SystemExit(main())
