"""Learning the correction F from observed trajectories: the pipeline behind :func:`fit_correction`.

Its stages, each a subpackage (the order the data pass through them):

1. :mod:`~torchmisspec.learning.samples`: samples of F from the trajectories (estimated dy/dt minus G, with their
   noise), :func:`correction_samples`.
2. :mod:`~torchmisspec.learning.choice`: candidate models of F scored on held-out experiments (or held-out time
   pieces of one trajectory) and the known model alone as the rival (do no harm), :func:`cross_validate`.
3. :mod:`~torchmisspec.learning.refinement`: the chosen model refined through the ODE on the observed states (no
   derivative estimates), partly measured states and their initial states, :func:`fit_trajectories`.
4. :mod:`~torchmisspec.learning.theta`: G's uncertain parameters, learned with F.

:class:`Pipeline` (:mod:`~torchmisspec.learning.pipeline`) holds one object per stage with its options
(:class:`Samples`, :class:`Candidates`, :class:`HeldOut` or :class:`Evidence`, :class:`Refinement`) and runs them
(:mod:`~torchmisspec.learning.fit` composes the stages); :func:`fit_correction` builds one from keywords. Every entry
point learns through it: ``fit_correction``, a campaign's ``tell``, the command line and the studies. The bands'
calibration on held-out experiments is a stage of the prediction (:mod:`torchmisspec.prediction.calibration`).
"""

from .choice.stage import Candidates, Evidence, HeldOut
from .fit import cross_validate
from .pipeline import Pipeline, fit_correction
from .refinement.stage import Refinement
from .refinement.trajectory_fit import fit_trajectories
from .samples.observations import CorrectionSamples, correction_samples, finite_difference, smoothed_derivative
from .samples.stage import Samples

__all__ = [
    "Candidates",
    "Evidence",
    "HeldOut",
    "Pipeline",
    "Refinement",
    "Samples",
    "CorrectionSamples",
    "correction_samples",
    "cross_validate",
    "finite_difference",
    "fit_correction",
    "fit_trajectories",
    "smoothed_derivative",
]
