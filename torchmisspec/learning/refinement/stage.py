"""The refinement stage as an object: whether the chosen model is refined through the ODE (:class:`Refinement`)."""

from __future__ import annotations

from dataclasses import dataclass

from ..._validation import check_flag

__all__ = ["Refinement"]


@dataclass(frozen=True)
class Refinement:
    """Stage 4 of :class:`~torchmisspec.Pipeline`: the chosen model refined through the ODE on the observed states
    (:func:`~torchmisspec.fit_trajectories`: no derivative estimates).

    Args:
        through_ode: ``True``: always; ``False``: never; ``None`` (default): when the derivative estimator's
            self-check says its error is a large share of the correction samples (above
            ``ESTIMATOR_ERROR_THRESHOLD``, where the package used to warn that the correction would mostly fit
            estimator error and advise fitting through the ODE: the advice is now taken), and when the feature
            kernel (a sparse polynomial correction) is chosen on an autonomous system, where its terms' weights are
            what the derivative estimates bias most. Partly measured data are always learned through the ODE.
    """

    through_ode: bool | None = None

    def __post_init__(self):
        check_flag(self.through_ode, "through_ode", none=True)
