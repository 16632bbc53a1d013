"""How ``kernel="auto"`` chooses among its fitted candidates: the library check and the evidence rule.

Pure functions of the candidates' evidence scores (:attr:`CorrectionGP.evidence_score
<torchmisspec.CorrectionGP.evidence_score>`: the log marginal likelihood less BIC's price of the learned
hyperparameters); :meth:`CorrectionGP.fit <torchmisspec.CorrectionGP.fit>` fits the candidates and calls
:func:`auto_choice`.
"""

from __future__ import annotations

import math
import time

from .._errors import FittingError, LinearAlgebraError
from ._kernels import REGISTRY

__all__ = ["AUTO_KERNELS", "EVIDENCE_MARGIN", "auto_choice", "fit_and_score", "fit_auto", "library_check"]

#: the candidates of kernel="auto", fitted in this order (:func:`auto_choice` chooses among them)
AUTO_KERNELS = ("rbf", "matern52", "features", "features+rbf")
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

    The feature kernel itself (one set of weights per output, not nested in ``features+rbf``'s shared weights) is a
    library-only model too: when it scores at least as high as ``features+rbf``, the RBF term does not earn its price
    either, and the library suffices (issue 41: a feature kernel of score 15.6 was refused because the shared-weight
    nested model scored 3.7 against features+rbf's 7.0).

    So ``features+rbf`` serves as the library's test and is never chosen (unless nothing else fitted). Without it
    (``per_output``, or a failed fit) there is nothing to test and every candidate competes; if it fitted but its
    nested model did not (``library_score`` is ``None``), nothing is tested either, unless the feature kernel itself
    scores at least as high as ``features+rbf``. :func:`auto_choice` then chooses
    among the eligible kernels.

    Returns the eligible kernels and whether the library sufficed (``None``: not tested).
    """
    everything = list(scores)
    if "features+rbf" not in scores:
        return everything, None
    others = [k for k in everything if k != "features+rbf"] or everything
    if scores.get("features", -math.inf) >= scores["features+rbf"]:  # a library-only model beats it: suffices
        return others, True
    if library_score is None:
        return others, None
    if library_score >= scores["features+rbf"]:
        return others, True
    return ([k for k in everything if REGISTRY[k].stationary] or everything), False


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
    stationary = [k for k in eligible if REGISTRY[k].stationary]
    others = [k for k in eligible if not REGISTRY[k].stationary]
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


def fit_and_score(candidate, inputs, targets=None, noise=None, **options) -> dict:
    """Fit one unfitted candidate by marginal likelihood, in place, and record it: kernel, log marginal likelihood,
    number of learned hyperparameters, :attr:`evidence_score`, seconds, and the error of a fit that failed
    numerically (bad input still raises). Shared by ``kernel="auto"`` and ``fit_correction(select="evidence")``."""
    start = time.perf_counter()
    try:
        candidate.fit(inputs, targets, noise=noise, **options)
    except (FittingError, LinearAlgebraError) as exc:
        return {
            "kernel": candidate.kernel,
            "log_marginal_likelihood": None,
            "hyperparameters": None,
            "score": None,
            "seconds": time.perf_counter() - start,
            "error": f"{type(exc).__name__}: {exc}",
        }
    return {
        "kernel": candidate.kernel,
        "log_marginal_likelihood": float(candidate.log_marginal_likelihood_),
        "hyperparameters": candidate.num_hyperparameters,
        "score": candidate.evidence_score,
        "seconds": time.perf_counter() - start,
        "error": None,
    }


def fit_auto(gp, inputs, targets, noise, **options):
    """``kernel="auto"``: fit every kernel of :data:`AUTO_KERNELS` by marginal likelihood, score each by
    :attr:`evidence_score` (its evidence given its own ML-II hyperparameters, less BIC's price of those) and keep
    the one :func:`auto_choice` chooses (the RBF unless another eligible candidate has strong evidence; a
    stationary kernel when the library misses part of F). The feature kernel is fitted with one weight per term
    and output (``per_output=True``); features+rbf is skipped when ``per_output`` (it is shared by the outputs),
    and then the library is not checked. Cost: about 5 fits (the candidates and the check's nested model).
    ``model_selection_`` records each candidate: kernel, log marginal likelihood, score, seconds, the error of a
    candidate that failed, whether it was eligible, whether it was chosen.
    Bad input raises at once; numerical failures of a candidate are recorded and the others still compete."""

    def candidate(kernel: str, per_output: bool):
        # the auto model's settings (degree, price of a term, noise if fixed, ...) with this kernel, all learned
        return gp.clone(kernel=REGISTRY[kernel](), per_output=per_output)

    def attempt(cand) -> dict:
        return fit_and_score(cand, inputs, targets, noise, **options)

    records, fitted = [], {}
    for kernel in AUTO_KERNELS:
        if gp._auto_per_output and REGISTRY[kernel].shared_only:
            continue
        # the feature kernel: one weight per term and output, each output its own sparse equation (as SINDy);
        # the shared-weight fit below is only the library check's reference (not a candidate)
        cls = REGISTRY[kernel]
        cand = candidate(kernel, gp._auto_per_output or (cls.terms and not cls.shared_only))
        records.append(attempt(cand))
        if records[-1]["error"] is None:
            fitted[kernel] = cand
    if not fitted:
        raise FittingError(
            "kernel='auto': every candidate kernel failed to fit: "
            + "; ".join(f"{r['kernel']}: {r['error']}" for r in records)
        )
    reference = None
    if "features+rbf" in fitted:  # the model features+rbf nests: the library with weights shared by the outputs
        fs = fitted.get("features")
        if fs is not None and fs.output_dim == 1:  # one output: the per-output fit is that model already
            reference = fs.evidence_score
        else:
            reference = attempt(candidate("features", False))["score"]  # None if it failed: untested
        records[[r["kernel"] for r in records].index("features+rbf")]["library_score"] = reference
    chosen, eligible, gp.library_suffices_ = auto_choice(
        {k: c.evidence_score for k, c in fitted.items()}, library_score=reference, margin=gp.evidence_margin
    )
    best = fitted[chosen]
    for r in records:
        r["eligible"] = r["kernel"] in eligible
        r["chosen"] = r["kernel"] == best.kernel
    gp.kernel_spec, gp._d_in, gp.fixed, gp.per_output = (
        best.kernel_spec,
        best._d_in,
        dict(best.fixed),
        best.per_output,
    )
    gp.model, gp._cache = best.model, None  # the posterior is rebuilt for gp at its first use
    gp.n_iterations_, gp.n_evaluations_ = best.n_iterations_, best.n_evaluations_
    gp.log_marginal_likelihood_ = best.log_marginal_likelihood_
    gp.model_selection_ = records
    return gp
