"""Study of issue 22: the scientist's whole loop, with defaults only, on a system the package does not ship.

The system is the one of the issue's user trial: an epidemic with three states (S, I, R), whose known model has
mass-action incidence beta S I while the truth saturates, beta S I / (1 + a I); the correction is declared on two
inputs (S, I) and two outputs (dS/dt, dI/dt), and its true form is never given to the package. Each realization is a
lab's CSV (columns ``experiment, day, S, I, R``): 8 experiments of 9 to 25 irregular days on [0, 40], states with
2 % multiplicative noise. Then, with defaults only, as the README shows:

``Trajectories.load`` -> ``fit_correction`` -> ``CorrectedODE.predict`` (new initial conditions) ->
``calibrate`` -> ``posterior`` -> ``design.greedy`` -> ``design.Campaign`` (ask 3, tell noisy results, ask 2).

Reported per realization and as mean ± standard error: the corrected model's trajectory RMSE over the known model's
on 50 new initial conditions (against the true system), the coverage of the true states by the calibrated central
90 % band (every time after the first and every component), the seconds of ``fit_correction`` and of ``calibrate``,
whether greedy and the campaign returned their experiments, and the warnings a user saw.

Usage::

    python scripts/study_end_to_end.py --markdown          # full: JSON, docs/studies/end-to-end.md, BENCHMARKS.md
    python scripts/study_end_to_end.py --smoke --json /tmp/e.json   # 2 realizations, never writes docs
"""

from __future__ import annotations

from torchmisspec.benchmarks.reporting import study_arguments
from torchmisspec.paper import study_end_to_end as study


def main(argv: list[str] | None = None) -> int:
    return study.run(study_arguments(__doc__, argv, study.DEFAULT_JSON))


if __name__ == "__main__":
    raise SystemExit(main())
