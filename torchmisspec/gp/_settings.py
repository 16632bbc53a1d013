"""The settings of a :class:`~torchmisspec.gp.CorrectionGP`, checked once: what its constructor (and ``clone``) accept.

Each refusal names the argument, what was expected and what was received; combinations that make no sense (a
lengthscale for a kernel without one, a term price for the RBF, a margin without ``kernel="auto"``) are refused,
not ignored.
"""

from __future__ import annotations

import torch

from .._errors import InputError
from .._validation import check_device, check_flag, check_positive_int, check_real
from ._features import check_library
from ._kernels import Kernel, as_kernel
from ._selection import EVIDENCE_MARGIN

__all__ = ["check_settings"]


def check_settings(
    *,
    kernel,
    lengthscale,
    outputscale,
    noise_variance,
    per_output,
    degree,
    max_iter,
    dtype,
    device,
    library,
    library_names,
    min_gain,
    evidence_margin,
    exact=None,
) -> dict:
    """The constructor's arguments, checked and normalised (floats, a :class:`~torchmisspec.gp.Kernel` object, a
    device); ``auto`` says whether the kernel is ``"auto"`` (then ``kernel`` is the RBF it holds until a fit)."""
    auto = isinstance(kernel, str) and kernel == "auto"
    spec = as_kernel("rbf" if auto else kernel)  # the unfitted auto model holds an RBF until its first fit
    outputscale = _checked_kernel_fit(spec, auto, lengthscale, outputscale, per_output)
    degree = check_positive_int(degree, "degree")
    min_gain, evidence_margin = _checked_prices(spec, auto, min_gain, evidence_margin)
    library, library_names = _checked_library(spec, auto, library, library_names)
    fixed = _fixed(lengthscale, outputscale, noise_variance)
    exact = _checked_exact(exact, spec, auto, per_output)
    if dtype not in (torch.float32, torch.float64):  # half precision: torch's kernels (pdist, cholesky) refuse it
        raise InputError(
            f"dtype: expected a floating torch.dtype such as torch.float64, got {dtype!r} (torch.float64 or "
            "torch.float32: half precision is not supported)"
        )
    return {
        "auto": auto,
        "kernel": spec,
        "fixed": fixed,
        "min_gain": min_gain,
        "evidence_margin": evidence_margin,
        "library": library,
        "library_names": library_names,
        "per_output": check_flag(per_output, "per_output"),
        "degree": degree,
        "max_iter": check_positive_int(max_iter, "max_iter"),
        "exact": exact,
        "dtype": dtype,
        "device": check_device(device),
    }


def _checked_kernel_fit(spec: Kernel, auto: bool, lengthscale, outputscale, per_output):
    """``outputscale`` (1 for a kernel with terms, whose weights carry the scale), after refusing a lengthscale the
    kernel does not have, per-output copies of a shared-only kernel, and fixed hyperparameters with ``"auto"``."""
    if not spec.has_lengthscale and lengthscale is not None:
        raise InputError(
            f"lengthscale: expected None (the {spec.name} kernel {spec!r} has no lengthscale), got {lengthscale!r}"
        )
    if spec.terms and outputscale is None:
        outputscale = 1.0  # the weights carry the scale
    if spec.shared_only and per_output:
        raise InputError(
            f"per_output: expected False (the {spec.name} kernel is shared by the outputs), got {per_output!r}"
        )
    if auto and (lengthscale is not None or outputscale is not None):
        raise InputError(
            "kernel='auto': the candidates' hyperparameters are learned (only noise_variance may be fixed); got "
            f"lengthscale={lengthscale!r}, outputscale={outputscale!r}"
        )
    return outputscale


def _checked_prices(spec: Kernel, auto: bool, min_gain, evidence_margin) -> tuple[float | None, float | None]:
    """``(min_gain, evidence_margin)`` as floats: the price of a feature term (feature kernels or ``"auto"`` only)
    and ``"auto"``'s margin over the RBF (:data:`~torchmisspec.gp._selection.EVIDENCE_MARGIN` by default; ``None``
    for any other kernel, which refuses one)."""
    if min_gain is not None:
        if not (auto or spec.terms):
            raise InputError(
                f"min_gain: expected a kernel with feature terms (the price of a feature term is for the feature "
                f"kernels or 'auto', got {spec.name!r})"
            )
        min_gain = float(check_real(min_gain, "min_gain", minimum=0.0))
    if not auto:
        if evidence_margin is not None:
            raise InputError(
                f"evidence_margin: expected kernel='auto' (the margin over the RBF), got kernel={spec.name!r} with "
                f"evidence_margin={evidence_margin!r}"
            )
        return min_gain, None
    if evidence_margin is None:
        return min_gain, EVIDENCE_MARGIN
    return min_gain, float(check_real(evidence_margin, "evidence_margin", minimum=0.0))


def _checked_library(spec: Kernel, auto: bool, library, library_names) -> tuple:
    """``(library, library_names)`` checked (:func:`~torchmisspec.gp._features.check_library`), after refusing a
    library for a kernel without feature terms and names without a library."""
    if library is not None and not (spec.terms or auto):
        raise InputError(
            f"library: expected kernel 'features' or 'features+rbf' for a feature library, got kernel {spec.name!r}"
        )
    if library is None and library_names is not None:
        raise InputError("library_names: expected a library=[...] for these names to name, got library=None")
    return (None, None) if library is None else check_library(library, library_names)


def _fixed(lengthscale, outputscale, noise_variance) -> dict:
    """The hyperparameters held fixed, as positive floats (``None`` for those learned)."""
    given = {"lengthscale": lengthscale, "outputscale": outputscale, "noise_variance": noise_variance}
    return {
        name: None if value is None else float(check_real(value, name, positive=True)) for name, value in given.items()
    }


def _checked_exact(exact, spec: Kernel, auto: bool, per_output) -> bool | None:
    """``exact`` (``None``, ``True`` or ``False``), after refusing ``False`` for a kernel that is never computed in a
    feature space (only a shared RBF or Matern 5/2) and ``True`` for a feature-space kernel."""
    exact = check_flag(exact, "exact", none=True)
    spaced = ("rbf", "rbf-features", "matern52", "matern52-features")  # computed in a feature space when large
    if exact is False and not (spec.name in spaced and not per_output and not auto):
        raise InputError(
            "exact: expected None or True for this kernel (only a shared RBF or Matern 5/2 kernel is computed in a "
            f"feature space), got False with kernel {'auto' if auto else spec.name!r}"
            f"{' and per_output' if per_output else ''}"
        )
    if exact is True and spec.name.endswith("-features") and spec.name in spaced:
        raise InputError(f"exact: expected None or False with kernel {spec.name!r} (a feature space), got True")
    return exact
