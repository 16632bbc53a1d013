"""How ``kernel="auto"`` chooses among its fitted candidates: the library check and the evidence rule.

Pure functions of the candidates' evidence scores (:attr:`CorrectionGP.evidence_score
<torchmisspec.CorrectionGP.evidence_score>`: the log marginal likelihood less BIC's price of the learned
hyperparameters); :meth:`CorrectionGP.fit <torchmisspec.CorrectionGP.fit>` fits the candidates and calls
:func:`auto_choice`.
"""

from __future__ import annotations

__all__ = ["AUTO_KERNELS", "EVIDENCE_MARGIN", "auto_choice", "library_check"]

#: the candidates of kernel="auto", fitted in this order (:func:`auto_choice` chooses among them)
AUTO_KERNELS = ("rbf", "matern52", "features", "features+rbf")
STATIONARY_KERNELS = ("rbf", "matern52")
#: kernel="auto" keeps this kernel (the package's default, the paper's) unless another eligible candidate outscores it
#: by at least ``evidence_margin`` nats
AUTO_DEFAULT = "rbf"
#: the default ``evidence_margin``: a Bayes factor of e^3 (about 20), "strong" evidence on Kass and Raftery's scale
#: (2 log B > 6; J. Am. Stat. Assoc. 90, 773, 1995)
EVIDENCE_MARGIN = 3.0


def library_check(scores: dict[str, float], *, library_score: float | None = None) -> tuple[list[str], bool | None]:
    """Which fitted candidates of ``kernel="auto"`` may be chosen, given their evidence scores.

    ``library_score`` is the score of the model ``features+rbf`` nests: the feature kernel with the same shared
    weights and noise (its RBF term removed). Comparing the two tests the library:

    * the nested model scores at least as high: F lies in the library's span as far as the samples can tell, and
      the RBF term does not earn its price, so ``features+rbf`` is dominated by its nested model and not eligible;
      the others are eligible (the library extrapolates as SINDy's equation would);
    * ``features+rbf`` scores higher: its RBF term earns its price, so part of F lies outside the library. The
      library's coefficients are then only a local fit, confounded with the residual the RBF term carries, and
      nothing supports their extrapolation away from the samples. Neither feature candidate is eligible, only the
      stationary kernels are: their prior falls back to F = 0 away from the samples, i.e. to the known model, which
      the scientist trusts wherever no data say otherwise. (If no stationary kernel fitted, every candidate is
      eligible: a fit beats none.)

    So ``features+rbf`` serves as the library's test and is never chosen (unless nothing else fitted). Without it
    (``per_output``, or a failed fit) there is nothing to test and every candidate competes; if it fitted but its
    nested model did not (``library_score`` is ``None``), nothing is tested either. :func:`auto_choice` then chooses
    among the eligible kernels.

    Returns the eligible kernels and whether the library sufficed (``None``: not tested).
    """
    everything = list(scores)
    if "features+rbf" not in scores:
        return everything, None
    others = [k for k in everything if k != "features+rbf"] or everything
    if library_score is None:
        return others, None
    if library_score >= scores["features+rbf"]:
        return others, True
    return ([k for k in everything if k in STATIONARY_KERNELS] or everything), False


def auto_choice(
    scores: dict[str, float], *, library_score: float | None = None, margin: float = EVIDENCE_MARGIN
) -> tuple[str, list[str], bool | None]:
    """The kernel ``kernel="auto"`` keeps, given the fitted candidates' evidence scores.

    The candidates :func:`library_check` allows are eligible. Leaving the default takes strong evidence:

    * among the stationary kernels, the RBF (:data:`AUTO_DEFAULT`, the package's and the paper's kernel) is kept
      unless the Matern kernel outscores it by more than ``margin`` nats (the better one if the RBF did not fit);
    * a feature kernel is kept only if it outscores every eligible stationary kernel by more than ``margin``.

    The stake is not symmetric. A stationary kernel's prior falls back to F = 0, i.e. to the known model, wherever no
    samples are, while a library equation chosen on weak evidence is trusted across the whole domain. Few samples
    (one or two short trajectories) rarely separate the candidates by much, and then a few nats of evidence along
    the samples say little about the rest of the domain. The default, :data:`EVIDENCE_MARGIN`, asks for "strong"
    evidence (a Bayes factor above about 20); with 0 the highest score wins, ties going to the default. Without an
    eligible stationary kernel the highest score wins.

    Returns the kernel chosen, the eligible kernels and whether the library sufficed (``None``: not tested).
    """
    eligible, suffices = library_check(scores, library_score=library_score)
    stationary = [k for k in eligible if k in STATIONARY_KERNELS]
    others = [k for k in eligible if k not in STATIONARY_KERNELS]
    if not stationary:
        return max(others, key=scores.__getitem__), eligible, suffices
    top = max(scores[k] for k in stationary)
    if AUTO_DEFAULT in stationary and top <= scores[AUTO_DEFAULT] + margin:
        best = AUTO_DEFAULT
    else:
        best = max(stationary, key=scores.__getitem__)
    if others:
        rival = max(others, key=scores.__getitem__)
        if scores[rival] > top + margin:
            best = rival
    return best, eligible, suffices
