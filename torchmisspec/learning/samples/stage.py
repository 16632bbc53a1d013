"""The samples stage as an object: how dy/dt is estimated from the observed states (:class:`Samples`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..._errors import InputError
from ..._validation import check_positive_int
from .observations import CorrectionSamples, correction_samples

__all__ = ["Samples"]


@dataclass(frozen=True)
class Samples:
    """Stage 1 of :class:`~torchmisspec.Pipeline`: samples of F = dy/dt - G(y) at the observed states.

    Args:
        derivative: the estimator of dy/dt (:func:`~torchmisspec.correction_samples`): ``"auto"`` (default: a
            self-check on the data chooses), ``"central"``, ``"smooth"``, ``"gp"``, ``"forward"``, ``"oracle"``.
        noise_std: standard deviation of noise added to the samples' targets (a simulation's device; 0: none).
        order: the central stencil's order.
        window: the smoother's window (observations).
        degree: the smoother's polynomial degree.
        generator: the random generator of ``noise_std``'s noise (``None``: torch's global one).
        in_noise_space: estimate dy/dt in the fit's noise model's space (``log y`` under relative errors) and bring it
            back by the chain rule (:mod:`~torchmisspec.learning.samples._noise_space`): each sample's noise then
            follows its state's size. Off by default for one experiment's fit: on the real-data suite
            (``scripts/study_real_data.py``) it made Loblolly's coarse growth curves (6 ages) and the hare-lynx
            pelts (21 years) worse (default / classical 0.61 -> 0.84 and 0.70 -> 1.06); a population fits with it
            (:func:`~torchmisspec.population.fit_population`: on nlme's Remifentanil, concentrations over three
            decades, F's spread at low concentrations fell below the elimination it corrects).

    Calling it gives the samples: ``Samples(derivative="gp")(trajectories, system)``.
    """

    derivative: str = "auto"
    noise_std: float = 0.0
    order: int = 2
    window: int = 7
    degree: int = 2
    generator: torch.Generator | None = None
    in_noise_space: bool = False

    def __post_init__(self):
        if not isinstance(self.derivative, str):
            raise InputError(
                f"derivative: expected the name of an estimator of dy/dt (e.g. 'auto', 'central', 'gp'), got "
                f"{self.derivative!r:.60} ({type(self.derivative).__name__})"
            )
        if isinstance(self.noise_std, bool) or not isinstance(self.noise_std, (int, float)) or self.noise_std < 0:
            raise InputError(f"noise_std: expected a standard deviation >= 0, got {self.noise_std!r:.60}")
        for name in ("order", "window", "degree"):
            check_positive_int(getattr(self, name), name)
        if not isinstance(self.in_noise_space, bool):
            raise InputError(f"in_noise_space: expected True or False, got {self.in_noise_space!r:.60}")
        if self.generator is not None and not isinstance(self.generator, torch.Generator):
            raise InputError(f"generator: expected a torch.Generator or None, got {type(self.generator).__name__}")

    def __call__(self, trajectories, system, noise=None) -> CorrectionSamples:
        """The correction samples of ``trajectories`` under ``system`` (:func:`~torchmisspec.correction_samples`);
        with ``in_noise_space``, in the space of ``noise`` (a :class:`~torchmisspec.noise.NoiseModel`, required)."""
        options = {k: v for k, v in self.estimator.items() if k != "in_noise_space"}
        if self.in_noise_space:
            if noise is None:
                raise InputError(
                    "noise: Samples(in_noise_space=True) estimates dy/dt in a noise model's space, got none; pass "
                    "noise=torchmisspec.noise.Relative() (or the fit's gp.noise_), or in_noise_space=False"
                )
            options["noise"] = noise
        return correction_samples(trajectories, system, derivative=self.derivative, **options)

    @property
    def estimator(self) -> dict:
        """The estimator's options that differ from :func:`~torchmisspec.correction_samples`' defaults, as its
        keywords (``derivative`` apart)."""
        defaults = Samples()
        names = ("noise_std", "order", "window", "degree", "generator", "in_noise_space")
        return {n: getattr(self, n) for n in names if getattr(self, n) != getattr(defaults, n)}
