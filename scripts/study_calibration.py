"""Study of issue 10: are the predicted uncertainty bands of ``CorrectedODE.posterior`` calibrated?

Settings (hyperparameters always fitted by marginal likelihood, ``CorrectionGP().fit``, as a user would):

* paper_linear (paper 5.1): K = 5, 10, 40 experiments from initial conditions uniform in D = [-1, 1]^2, observed
  at T = 11 times on [0, 6] with the paper's observation model (exact derivatives plus noise of std 1e-2);
* paper_gravity (paper 5.3): K = 7 experiments on circular orbits of the known mass (``design.candidates.orbits``),
  T = 20 times on [0, 3], the same observation model.

For each of R realizations: fit the GP, draw S posterior functions, integrate the paths from N new initial
conditions (drawn like the training ones) on the output times (the training span, t = 0 excluded: every draw starts
at the initial condition), and count how often the true trajectory lies in the central 50 %, 90 % and 95 % bands of
the sampled paths (every output time and component). Reported: mean coverage over realizations with its standard
error, the fraction of paths flagged as extrapolating, and the lengthscale ML-II chose.

Usage::

    python scripts/study_calibration.py --markdown          # full: JSON, docs/studies/calibration.md, BENCHMARKS.md
    python scripts/study_calibration.py --smoke --json /tmp/c.json   # tiny, never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_calibration as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(__doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
