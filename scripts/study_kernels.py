"""Study of issue 12: CorrectionGP kernels (RBF, feature library, features+RBF, chosen by evidence) against sparse
polynomial regression (SINDy) and a small neural network, on the same correction samples.

Settings (the paper's observation model: exact derivatives + noise of std 1e-2):

* paper_linear (F = 0.01 y^2, a polynomial): K = 5, 12, 20, 40 experiments, T = 11 on [0, 6], either random
  (initial conditions uniform in D, new per realization) or designed (the paper's greedy design from its prior over
  the 13 x 13 grid, first K picks); error: the integral over D of ||F_hat - F||.
* paper_gravity (an inverse-square field): K = 1..10 random circular orbits (new per realization), T = 20 on
  [0, 3]; error: the mean over D of ||F_hat - F||^2.

Methods (every one sees the same samples; degree-2 monomials for every polynomial library):

* ``GP rbf``: ``CorrectionGP()`` (RBF, hyperparameters by marginal likelihood);
* ``GP features``: ``CorrectionGP(kernel="features")`` (automatic relevance);
* ``GP features+rbf``: ``CorrectionGP(kernel="features+rbf")``;
* ``GP auto``: ``CorrectionGP(kernel="auto")`` (the kernel of highest evidence score, log marginal likelihood less
  BIC's price of the learned hyperparameters, among those the library check allows: a stationary kernel when
  features+rbf outscores the feature kernel it nests; features+rbf itself is the test, never kept; and the RBF
  unless the Matern kernel, or a feature kernel against every eligible stationary one, outscores it by more than
  ``evidence_margin``, 3 nats by default);
* ``SINDy``: pysindy's polynomial library and STLSQ, the threshold by 5-fold cross-validation over experiments;
* ``MLP``: a 2 x 64 tanh network, Adam with weight decay, inputs and outputs standardised.

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
    args = study_arguments(__doc__, argv, study.DEFAULT_JSON)
    try:
        import pysindy  # noqa: F401
    except ImportError:
        args.parser.error('pysindy is needed for the SINDy baseline: pip install -e ".[bench]"')
    return study.run(args)


if __name__ == "__main__":
    raise SystemExit(main())
