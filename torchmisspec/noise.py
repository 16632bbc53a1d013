"""How the states were measured: the observation noise model that fits compare predictions with measurements by.

A measured population of 30 and one of 3,000 are not off by the same amount when each is 10 % off: counts, cell
densities and concentrations carry errors proportional to their size (multiplicative, log-normal), and a fit that
adds up squared differences lets the largest values decide everything. A noise model says in which space the errors
are alike:

* :class:`Additive` - ``observed - predicted``: errors of one size whatever the state (the default for states
  that may be negative or 0);
* :class:`Relative` - ``log observed - log predicted``: log-normal errors of positive states (a 10 % error is the
  same anywhere);
* :class:`Counts` - ``log(1 + observed) - log(1 + predicted)``: counts, whose errors grow with their size and which
  may be 0 (the log of one plus the count stabilises a negative-binomial variance, up to proportional to the
  square of the count: animals trapped, cases of a large outbreak);
* :class:`Poisson` - ``2 sqrt(observed + 3/8) - 2 sqrt(predicted + 3/8)``: counts of independent events (variance
  proportional to the count: cells counted in a chamber, decays, colonies), their dispersion fitted, and the bands of
  new measurements drawn as counts (Poisson or negative binomial).

:func:`fit_correction <torchmisspec.fit_correction>` compares the held-out predictions of its candidates (and of the
known model alone) and fits G's uncertain parameters through the ODE with these residuals, and estimates dy/dt in the
model's space (:meth:`NoiseModel.transform`, then the chain rule: a derivative sample's noise follows its state's
size under relative errors; :mod:`~torchmisspec.learning.samples._noise_space`). ``noise="auto"`` (the
default) picks :class:`Counts` when the measured values are whole numbers, 0 or more, with a 0 after each
experiment's first row (where every prediction starts, so it is never compared); :class:`Relative` when every measured
value after the first rows is positive and some component spans a factor of at least :data:`RELATIVE_SPAN` (growth,
decay, epidemics, concentrations after a dose given at a concentration of 0); :class:`Additive` otherwise; and says
which in a one-line message.
"""

from __future__ import annotations

import math

import torch

from ._errors import InputError, TorchMisspecWarning, warn
from .data import Trajectories

__all__ = [
    "RELATIVE_SPAN",
    "Additive",
    "CountNoise",
    "Counts",
    "NoiseModel",
    "Poisson",
    "Relative",
    "as_noise_model",
    "NOISE_MODELS",
]

#: ``noise="auto"`` chooses :class:`Relative` when every measured value after the first rows is positive and a
#: component's largest measurement is at least this many times its smallest.
RELATIVE_SPAN = 5.0
#: the largest share of a component's values at 0 or below that the automatic choice names as ruling out relative noise
FEW_LOW = 0.05


class NoiseModel:
    """The space in which measurement errors are alike (subclass it: a ``name`` and :meth:`transform`)."""

    name = ""

    def transform(self, y: torch.Tensor) -> torch.Tensor:
        """The states in the space where their errors are alike (elementwise)."""
        raise NotImplementedError

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        """The states whose :meth:`transform` is ``z``."""
        raise NotImplementedError

    def measure(self, y: torch.Tensor, scale: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """New measurements of the states ``y (..., d)``: ``inverse(transform(y) + scale * eps)``, eps standard
        normal, ``scale (d,)`` the noise's standard deviation in the model's space (a fit's ``noise_scale_``)."""
        eps = torch.randn(y.shape, generator=generator, dtype=y.dtype, device=y.device)
        return self.inverse(self.transform(y) + scale.to(y) * eps)

    def holds(self, y: torch.Tensor) -> torch.Tensor:
        """Elementwise, whether a measured value ``y`` lies where :meth:`transform` is one to one (the default: every
        finite value); a derivative estimated in this model's space leaves the others out."""
        return torch.isfinite(y)

    def residuals(self, observed: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
        """``transform(observed) - transform(predicted)`` (a non-finite prediction gives a non-finite residual)."""
        return self.transform(observed) - self.transform(predicted)

    def check(self, observed: torch.Tensor, what: str) -> None:
        """Refuse measurements this model cannot hold (the default: any finite value)."""

    def resolution(self, trajectories: Trajectories) -> torch.Tensor | None:
        """``(d,)`` the smallest magnitude of each state that a solve must resolve for this model's residuals on
        ``trajectories`` (NaN for a state without one; ``None``, the default: the solver's own scales suffice, as
        for errors of one size at every magnitude). Passed as :func:`~torchmisspec._ode.solve`'s ``floor``."""
        return None

    def in_units(self, scale: torch.Tensor) -> NoiseModel:
        """The same model for states divided by ``scale`` ``(d,)`` (a fit in the data's units,
        :mod:`torchmisspec.learning._units`): itself, unless its residuals depend on the unit."""
        return self

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    def __eq__(self, other) -> bool:
        return type(other) is type(self)

    def __hash__(self) -> int:
        return hash(type(self))


class Additive(NoiseModel):
    """Errors of one size whatever the state: ``observed - predicted``."""

    name = "additive"

    def transform(self, y):
        return y

    def inverse(self, z):
        return z

    def residuals(self, observed, predicted):
        return observed - predicted


class Relative(NoiseModel):
    """Log-normal errors of positive states: ``log observed - log predicted`` (a prediction at or below 0 is
    infinitely wrong: its residual is taken at the smallest positive number of its dtype)."""

    name = "relative"

    def transform(self, y):
        return torch.log(y.clamp_min(torch.finfo(y.dtype).tiny))

    def inverse(self, z):
        return torch.exp(z)

    def holds(self, y):
        return y > 0

    def resolution(self, trajectories):
        """Each state's smallest positive measured value: a logarithm is compared there, so the solve must resolve it
        to a few digits (states read only through a readout: none)."""
        _, states, mask = trajectories.padded()
        seen = torch.isfinite(states) & mask.unsqueeze(-1) & (states > 0)
        low = torch.where(seen, states, torch.full_like(states, math.inf)).flatten(0, -2).amin(0)
        return torch.where(torch.isfinite(low), low, torch.full_like(low, math.nan))

    def check(self, observed, what):
        seen = observed[~torch.isnan(observed)]
        if bool((seen <= 0).any()):
            raise InputError(
                f"noise: expected positive measurements for relative (log-normal) noise, got {int((seen <= 0).sum())} "
                f"at or below 0 in {what} (smallest {float(seen.min()):.3g}); use noise='counts' for counts that may "
                "be 0, or noise='additive'"
            )


class CountNoise(NoiseModel):
    """A noise model of counts (0 allowed; subclass it: a ``name``, :meth:`transform` and :meth:`inverse`);
    ``unit`` (``(d,)`` or a number, default 1) is one count in the states' units (a fit in the data's units divides
    the states by a power of ten)."""

    def __init__(self, unit=1.0) -> None:
        self.unit = unit

    def _unit(self, like: torch.Tensor) -> torch.Tensor:
        """The unit for ``like (..., e)``: per component, and 1 for columns beyond the states' (readings)."""
        unit = torch.as_tensor(self.unit, dtype=like.dtype, device=like.device)
        if unit.dim() == 1 and like.dim() and like.shape[-1] > unit.numel() > 1:
            unit = torch.cat([unit, unit.new_ones(like.shape[-1] - unit.numel())])
        return unit

    def in_units(self, scale):
        return type(self)(torch.as_tensor(self.unit, dtype=scale.dtype) * scale)

    def holds(self, y):
        return y >= 0

    def __repr__(self) -> str:
        name = type(self).__name__
        return f"{name}()" if isinstance(self.unit, float) and self.unit == 1.0 else f"{name}(unit={self.unit})"

    def check(self, observed, what):
        seen = observed[~torch.isnan(observed)]
        if bool((seen < 0).any()):
            raise InputError(
                f"noise: expected counts (0 or more) for noise='{self.name}', got {int((seen < 0).sum())} negative "
                f"value(s) in {what} (smallest {float(seen.min()):.3g}); use noise='additive'"
            )


class Counts(CountNoise):
    """Counts whose spread grows with their size (negative-binomial-like, a variance up to proportional to the
    square of the count): ``log(1 + observed) - log(1 + predicted)``."""

    name = "counts"

    def transform(self, y):
        return torch.log1p(y.clamp_min(0.0) * self._unit(y))

    def inverse(self, z):
        return torch.expm1(z).clamp_min(0.0) / self._unit(z)


class Poisson(CountNoise):
    """Counts of independent events, Poisson with a dispersion (quasi-Poisson: variance ``phi`` times the mean):
    ``2 sqrt(observed + 3/8) - 2 sqrt(predicted + 3/8)`` (Anscombe's transform: unit variance for Poisson counts,
    so a fit's residual scale per component, ``noise_scale_``, is ``sqrt(phi)``: about 1 for Poisson counts, above
    for overdispersed ones). :meth:`measure` draws counts: Poisson where ``phi <= 1``, negative binomial of mean
    ``mu`` and variance ``phi mu`` (a gamma-Poisson mixture) above."""

    name = "poisson"

    def transform(self, y):
        return 2.0 * torch.sqrt(y.clamp_min(0.0) * self._unit(y) + 0.375)

    def inverse(self, z):
        return ((z / 2.0).pow(2) - 0.375).clamp_min(0.0) / self._unit(z)

    def measure(self, y, scale, generator=None):
        """New counts at the states ``y (..., d)`` (their means), in the states' units: ``phi = scale^2`` per
        component (a scale of 0: ``y`` itself, no noise, as for the other models); NaN where ``y`` is NaN (a draw
        that left its region)."""
        mu = (y.clamp_min(0.0) * self._unit(y)).nan_to_num(0.0)
        phi = scale.to(y).pow(2).nan_to_num(1.0).expand_as(mu)
        extra = (phi - 1.0).clamp_min(0.0)
        over = extra > 0
        rate = mu
        if bool(over.any()):  # gamma-Poisson: rate ~ Gamma(mu / (phi - 1), scale phi - 1): mean mu, var mu (phi - 1)
            shape = torch.where(over & (mu > 0), mu / extra.clamp_min(1e-300), torch.ones_like(mu))
            seed = int(torch.randint(2**62, (1,), generator=generator))  # the gamma sampler takes no generator
            with torch.random.fork_rng(devices=[] if y.device.type == "cpu" else [y.device]):
                torch.manual_seed(seed)
                gamma = torch.distributions.Gamma(shape, torch.ones_like(shape)).sample()
            rate = torch.where(over & (mu > 0), gamma * extra, mu)
        counts = torch.poisson(rate, generator=generator) / self._unit(y)
        none = (scale.to(y) == 0).expand_as(y)  # a component with no noise (never measured: the bands' NaN -> 0)
        return torch.where(torch.isnan(y) | none, y, counts)


#: the models ``noise=`` names
NOISE_MODELS = {m.name: m for m in (Additive, Relative, Counts, Poisson)}


def _measured(trajectories: Trajectories) -> torch.Tensor:
    """``(N, m)``: the values of the components some experiment measures (a starting value given for a state that is
    not measured, e.g. 0 recovered on day 0, is not a measurement), NaN where not observed, and NaN for a 0 in an
    experiment's first row: every prediction starts from that row, so it is never compared in any noise model's
    space (a concentration of 0 before the dose does not rule out relative errors for the concentrations after it)."""
    flat = trajectories.flat_states()[:, trajectories.measured.any(0)]
    first = torch.tensor([0, *trajectories.lengths[:-1]], device=flat.device).cumsum(0)
    rows = flat[first]
    flat = flat.clone()
    flat[first] = torch.where(rows == 0, torch.full_like(rows, float("nan")), rows)
    return flat


def _auto(trajectories: Trajectories) -> NoiseModel:
    flat = _measured(trajectories)
    seen = ~torch.isnan(flat)
    values = flat[seen]
    if bool(values.numel()) and bool((values >= 0).all()) and bool((values == values.round()).all()):
        if bool((values == 0).any()):  # whole numbers with zeros: counts (logs cannot hold the zeros)
            return Counts()
    if not bool(seen.any()) or bool((values <= 0).any()):
        return Additive()
    for j in range(flat.shape[1]):
        col = flat[seen[:, j], j]
        if col.numel() and float(col.max()) >= RELATIVE_SPAN * float(col.min()):
            return Relative()
    return Additive()


def _say_what_ruled_out_relative(flat: torch.Tensor, announce: str) -> None:
    """Warn where a few small values of 0 or below are all that kept the automatic choice from relative noise: in some
    component, at most :data:`FEW_LOW` of the measured values, each within a tenth of the positive values' median,
    while the positive ones span a factor of :data:`RELATIVE_SPAN` (a concentration decaying over decades). A
    blank-corrected assay's -0.02 or a 0 below the detection limit turned the fit additive, which weighs the small
    values' errors as the large ones' (a user's trial on nlme's Remifentanil: no word of it). A signal that crosses
    zero (many values below it, or large ones) is additive without a word."""
    for j in range(flat.shape[1]):
        col = flat[~torch.isnan(flat[:, j]), j]
        low, positive = col[col <= 0], col[col > 0]
        if not low.numel() or not positive.numel() or low.numel() > FEW_LOW * col.numel():
            continue
        if float(low.abs().max()) > 0.1 * float(positive.median()):
            continue
        if float(positive.max()) >= RELATIVE_SPAN * float(positive.min()):
            warn(
                f"{announce}: noise 'additive': {low.numel()} measured value(s) after the first row are 0 or below "
                f"(the lowest {float(low.min()):.3g}), so errors proportional to the size (compared as logs) cannot "
                f"hold them, although the positive values span a factor of at least {RELATIVE_SPAN:g}. If those are "
                "below a detection limit, leave their cells empty and pass noise='relative'; else pass "
                "noise='additive' to keep errors of one size and silence this",
                TorchMisspecWarning,
            )
            return


def as_noise_model(noise, trajectories: Trajectories, *, announce: str | None = None) -> NoiseModel:
    """The :class:`NoiseModel` ``noise`` names (``"auto"``, ``"additive"``, ``"relative"``, ``"counts"``, or an
    instance, used as it is), a name checked against ``trajectories``' measurements (the components some experiment
    measures). With ``"auto"`` and ``announce`` (the caller's name), a one-line
    :class:`~torchmisspec.TorchMisspecWarning` says which was chosen when it is not additive."""
    if isinstance(noise, NoiseModel):
        return noise
    if isinstance(noise, str) and noise == "auto":
        model = _auto(trajectories)
        if announce and isinstance(model, Counts):
            warn(
                f"{announce}: noise 'counts' (the measured values are whole numbers, 0 or more, with zeros: their "
                "errors are taken to grow with the count, compared as log(1 + count)); pass noise='poisson' for "
                "counts of independent events (variance proportional to the count), or noise='additive' for errors of "
                "one size",
                TorchMisspecWarning,
            )
        elif announce and not isinstance(model, Additive):
            warn(
                f"{announce}: noise '{model.name}' (every measured value after the first row is positive and spans a "
                f"factor of at least {RELATIVE_SPAN:g}: its errors are taken as proportional to its size, compared as "
                "logs); pass noise='additive' for errors of one size",
                TorchMisspecWarning,
            )
        elif announce:
            _say_what_ruled_out_relative(_measured(trajectories), announce)
    elif isinstance(noise, str) and noise in NOISE_MODELS:
        model = NOISE_MODELS[noise]()
    else:
        raise InputError(
            f"noise: expected 'auto', one of {list(NOISE_MODELS)} or a torchmisspec.noise.NoiseModel, got {noise!r:.60}"
        )
    model.check(_measured(trajectories), "the measured states")
    return model
