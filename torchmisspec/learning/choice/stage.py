"""The choice stage as objects: the candidate models of F (:class:`Candidates`) and the rule that chooses among
them, a variant each: held-out experiments (:class:`HeldOut`, the default) or the evidence (:class:`Evidence`)."""

from __future__ import annotations

from dataclasses import dataclass

from ..._errors import InputError
from ..._validation import check_positive_int
from ...gp import CorrectionGP
from .cross_validation import _check_candidates

__all__ = ["Candidates", "Evidence", "HeldOut"]


@dataclass(frozen=True)
class Candidates:
    """Stage 2 of :class:`~torchmisspec.Pipeline`: the models of F the choice is made among.

    Args:
        gp: a template :class:`~torchmisspec.CorrectionGP`: an RBF or Matern kernel with a free lengthscale is tried
            at each of :func:`~torchmisspec.learning.fit.lengthscale_candidates`, any other template as it is.
        models: the unfitted templates to choose among (a list; not with ``gp``).

    With neither (the default): RBF kernels over a grid of lengthscales and a feature kernel with automatic
    relevance, a sparse polynomial correction (:func:`~torchmisspec.learning.fit.default_candidates`), and the known
    model alone as the rival the correction must beat (do no harm); given candidates have no such rival.
    """

    gp: CorrectionGP | None = None
    models: tuple | None = None

    def __post_init__(self):
        if self.gp is not None and not isinstance(self.gp, CorrectionGP):
            raise InputError(f"gp: expected a CorrectionGP template or None, got {type(self.gp).__name__}")
        if self.models is not None:
            if self.gp is not None:
                raise InputError("candidates: expected either a gp template or a list of candidates, got both")
            object.__setattr__(self, "models", tuple(_check_candidates(self.models)))

    @property
    def given(self) -> bool:
        """Whether the user chose the candidates (the known model is then not their rival)."""
        return self.gp is not None or self.models is not None


@dataclass(frozen=True)
class HeldOut:
    """Stage 3 of :class:`~torchmisspec.Pipeline` (the default rule): each candidate scored by the error of the
    corrected model's predictions of experiments it was not fitted on (:func:`~torchmisspec.cross_validate`);
    experiment k is in fold ``k % folds``. One experiment: the pieces of its time are held out instead
    (:func:`~torchmisspec.learning.choice._time_pieces.time_pieces`); too short for two, the evidence chooses."""

    folds: int = 5
    #: the name :func:`~torchmisspec.fit_correction`'s ``select`` gives this rule
    select = "cv"

    def __post_init__(self):
        check_positive_int(self.folds, "folds", minimum=2)


@dataclass(frozen=True)
class Evidence:
    """Stage 3 of :class:`~torchmisspec.Pipeline`: the candidate of highest evidence (marginal likelihood of the
    samples, :attr:`~torchmisspec.CorrectionGP.evidence_score`), no held-out data (one fit per candidate: faster,
    but blind to the derivative estimator's correlated errors)."""

    select = "evidence"
    folds = 5  # not used: kept so every rule gives fit_correction the same keywords


#: The rules by the name ``fit_correction(select=...)`` gives them.
RULES = {"cv": HeldOut, "evidence": Evidence}
