"""Bands from sampled paths: which order statistics of S draws make a band that covers ``level`` of new draws.

The central ``level`` band of S draws taken at the plain quantiles ``(1 -/+ level) / 2`` is too narrow: a new draw
from the same distribution falls between the i-th and j-th smallest of S exchangeable draws with probability
``(j - i) / (S + 1)`` (whatever the distribution), so the plain 5 % and 95 % quantiles of 64 draws (ranks 4.15 and
60.85 under linear interpolation) cover a new draw with probability 0.87, not 0.9. :func:`band_quantiles` places
the ranks at ``(S + 1)(1 -/+ level) / 2`` instead, which makes the expected coverage ``level`` exactly wherever the
ranks are whole numbers (and to within the interpolation between two neighbouring draws elsewhere).

:class:`TrajectoryPosterior` holds the sampled paths of :meth:`CorrectedODE.posterior
<torchmisspec.CorrectedODE.posterior>` and gives their bands this way (and the bands of what a readout reads). A
draw that left the posterior's region (NaN from there) is left out of its bands: each entry's band is that of the
draws that remain there (:class:`TrajectoryPosterior`); :func:`path_quantiles`, which counts such a draw as
unbounded, is what the calibration's held-out bands use.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from .._errors import InputError, ShapeError, TorchMisspecWarning, warn
from .._validation import as_tensor, check_real
from ..data import Readout


def band_quantiles(
    level: float, num_draws: int, *, dtype=torch.float64, device=None, what: str = "band"
) -> torch.Tensor:
    """``(2,)`` quantile positions (for :func:`torch.quantile`'s linear interpolation) of the central band of
    ``num_draws`` exchangeable draws that covers a new draw with probability ``level``.

    When ``level`` exceeds ``(S - 1) / (S + 1)`` no band within the draws reaches it: the band is the draws' whole
    range, and a warning says how many draws the level needs.
    """
    S = int(num_draws)
    lo_rank = (S + 1) * (1.0 - level) / 2.0  # 1-based rank of the lower end
    if lo_rank < 1.0 - 1e-9 and level > 0.0:
        need = math.ceil(2.0 / (1.0 - level) - 1.0 - 1e-9) if level < 1.0 else None
        warn(
            f"{what}: the central {level:g} band of {S} draws is wider than the draws: their range covers a new draw "
            f"with probability {(S - 1) / (S + 1):.3f} only; "
            + (f"draw at least {need} (num_samples={need})" if need else "no finite number of draws covers all")
            + " for this level",
            TorchMisspecWarning,
        )
    if S < 2:
        return torch.tensor([0.0, 1.0], dtype=dtype, device=device)
    lo = min(max((lo_rank - 1.0) / (S - 1), 0.0), 0.5)
    return torch.tensor([lo, 1.0 - lo], dtype=dtype, device=device)


def path_quantiles(samples: torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
    """Quantiles ``qs (Q,)`` over the draws ``samples (S, ...)`` -> ``(Q, ...)``, where a NaN (a path that diverged
    before that time) counts as unbounded on the side of the quantile: as -inf for q < 1/2, +inf for q > 1/2 (and the
    mean of both for the median), so a band that such paths reach is infinite, never silently narrowed."""
    if not bool(torch.isnan(samples).any()):
        return torch.quantile(samples, qs, dim=0)
    # interpolating between two infinite values gives NaN: there the quantile is that infinity
    low = torch.quantile(samples.nan_to_num(nan=-math.inf), qs, dim=0).nan_to_num(nan=-math.inf)
    high = torch.quantile(samples.nan_to_num(nan=math.inf), qs, dim=0).nan_to_num(nan=math.inf)
    side = qs.reshape(-1, *([1] * (samples.dim() - 1)))
    return torch.where(side < 0.5, low, torch.where(side > 0.5, high, 0.5 * (low + high)))


def widened(samples: torch.Tensor, mean: torch.Tensor, scale: float, noise) -> torch.Tensor:
    """``samples (S, ..., d)`` with their deviation from ``mean (..., d)`` times ``scale`` in ``noise``'s space
    (``T(mean) + c (T(y) - T(mean))``, mapped back): a relative band widens by a factor and stays positive. An
    entry the model cannot hold (``noise.holds``: a draw at or below 0 under relative noise) is widened in the
    states' own units. A draw at the mean stays exactly there: mapped through log and back it moved by a rounding
    error, and a band of paths that all start at a subject's fitted state (nlme's Remifentanil, 79.3 ng/mL) then
    no longer held its own mean path there."""
    z, zm = noise.transform(samples), noise.transform(mean)
    inside = noise.holds(samples) & noise.holds(mean)
    spaced = noise.inverse(zm + scale * (z - zm))
    plain = mean + scale * (samples - mean)
    return torch.where(samples == mean, samples, torch.where(inside, spaced, plain))


@dataclass(frozen=True)
class TrajectoryPosterior:
    """Predicted trajectories under S posterior draws of the correction (:meth:`CorrectedODE.posterior`).

    Attributes:
        times: ``(B, T)`` output times of every initial condition.
        samples: ``(S, B, T, d)`` the sampled paths.
        mean_path: ``(B, T, d)`` the trajectory of the posterior mean of F (what :meth:`CorrectedODE.predict`
            returns; not the same as :attr:`mean`, the mean over the sampled paths, when the dynamics are nonlinear).
        support: ``(B, T)`` posterior / prior standard deviation of F along the mean paths (near 0: well inside the
            data; near 1: the prior alone).
        extrapolating: ``(B,)`` paths whose support ratio exceeds ``threshold`` somewhere.
        threshold: the extrapolation threshold used.
        update_error: the certified bound on the compression of the draws' update (0: exact).
        state_names: the system's names of the state components (``None`` when it names none): what plots label
            the panels with.
        fraction_remaining: ``(B,)`` the fraction of each initial condition's draws that remained in the region
            to the last output time (1 where none left; computed from the NaN of ``samples`` when not given).
        region: ``(lo, hi)`` ``(d,)`` the region of the states the draws were stopped at (``None``: not bounded;
            kept as it is by :meth:`read`).
        escaped: ``(S, B, T, d)`` int8, where a draw left the region: +1 / -1 for each component that was above /
            below it where the draw crossed its edge, from there on (0 elsewhere; ``None``: not recorded, and after
            :meth:`read`).

    Draws that leave the region: a draw that left it (its path diverges under that draw of F) or stalled in it is
    NaN in ``samples`` from its first output time outside it (or not reached). :attr:`mean`, :attr:`stddev`,
    :meth:`quantile` and :meth:`interval` come from the draws that remain at each entry: with n of the S draws left
    there, the band is that of n draws (its ranks ``(n + 1)(1 -/+ level) / 2``), and where n is too few for the
    level (``level > (n - 1) / (n + 1)``, fewer than S remaining) that entry of the band is NaN, with a warning
    that says how many entries and why; with all S draws, the band is as always. :meth:`interval` counts a draw that
    left the region across an edge in a component (:attr:`escaped`) as lying beyond that edge (censored there, not
    dropped: dropping the draws that diverge upwards would pull the band's upper end down), so where more than
    the band's tail of the draws left on one side, that end of the band is the region's edge, with a warning: the
    band says how far it can tell, and stays finite (where too few draws remain for a component that did not cross,
    the band is the whole region). :attr:`fraction_remaining` says how much of the posterior remained.
    """

    times: torch.Tensor
    samples: torch.Tensor
    mean_path: torch.Tensor
    support: torch.Tensor
    extrapolating: torch.Tensor
    threshold: float
    update_error: float = 0.0
    state_names: tuple[str, ...] | None = None
    fraction_remaining: torch.Tensor | None = None
    region: tuple[torch.Tensor, torch.Tensor] | None = None
    escaped: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.fraction_remaining is None and isinstance(self.samples, torch.Tensor) and self.samples.dim() == 4:
            left = torch.isnan(self.samples).any(-1).any(-1).to(self.samples.dtype)  # (S, B)
            object.__setattr__(self, "fraction_remaining", 1.0 - left.mean(0))

    @property
    def num_samples(self) -> int:
        return self.samples.shape[0]

    @property
    def mean(self) -> torch.Tensor:
        """``(B, T, d)``: the mean over the sampled paths (those that remain in the region; NaN where none does)."""
        if not bool(torch.isnan(self.samples).any()):
            return self.samples.mean(0)
        return torch.nanmean(self.samples, 0)

    @property
    def stddev(self) -> torch.Tensor:
        """``(B, T, d)``: the standard deviation over the sampled paths (those that remain in the region; 0 with one
        draw, NaN where fewer than two of several remain)."""
        if self.num_samples < 2:
            return torch.zeros_like(self.samples[0])
        if not bool(torch.isnan(self.samples).any()):
            return self.samples.std(0)
        n = (~torch.isnan(self.samples)).sum(0)
        squares = (self.samples - torch.nanmean(self.samples, 0)).pow(2).nansum(0)
        return torch.where(n > 1, squares / (n - 1).clamp_min(1), math.nan).sqrt()

    def quantile(self, q) -> torch.Tensor:
        """Empirical quantile(s) over the sampled paths (those that remain in the region; NaN where none does):
        ``(B, T, d)`` for a number, ``(Q, B, T, d)`` for Q of them."""
        qs = as_tensor(q, "q", dtype=self.samples.dtype, device=self.samples.device)
        if qs.dim() > 1 or not bool(((qs >= 0) & (qs <= 1)).all()):
            raise InputError(f"q: expected a quantile or a 1-D list of quantiles in [0, 1], got {q!r:.80}")
        if not bool(torch.isnan(self.samples).any()):
            return path_quantiles(self.samples, qs)
        return torch.nanquantile(self.samples, qs, dim=0)

    def interval(self, level: float = 0.9) -> tuple[torch.Tensor, torch.Tensor]:
        """``(lower, upper)``, each ``(B, T, d)``: the central band of the sampled paths that a new draw falls in with
        probability ``level``: the order statistics at ranks ``(S + 1)(1 -/+ level) / 2`` of the S draws, not the
        plain quantiles, whose band of 64 draws covers 0.87 for ``level=0.9`` (:mod:`torchmisspec.prediction._bands`). A
        level beyond ``(S - 1) / (S + 1)`` gives the draws' range, with a warning naming the draws it needs. Where draws
        left the region, the band of the n that remain at each entry, NaN (with a warning) where n is too few for
        the level (the class's docstring)."""
        level = check_real(level, "level", minimum=0.0)
        if level > 1.0:
            raise InputError(f"level: expected a probability in [0, 1], got {level!r}")
        S, kw = self.num_samples, dict(dtype=self.samples.dtype, device=self.samples.device)
        if not bool(torch.isnan(self.samples).any()):
            lo_hi = path_quantiles(self.samples, band_quantiles(level, S, what="interval", **kw))
            return lo_hi[0], lo_hi[1]
        if self.escaped is None or self.region is None or self.escaped.shape != self.samples.shape:
            return _remaining_band(self.samples, level)
        return _censored_band(self.samples, self.escaped, self.region, level)

    def covers(self, states, level: float = 0.9) -> torch.Tensor:
        """``(B, T, d)`` booleans: whether ``states (B, T, d)`` (e.g. the true trajectories) lie in the band."""
        lower, upper = self.interval(level)
        states = as_tensor(states, "states", dtype=lower.dtype, device=lower.device)
        if states.shape != lower.shape:
            raise ShapeError(f"states: expected shape {tuple(lower.shape)} (B, T, d), got {tuple(states.shape)}")
        return (states >= lower) & (states <= upper)

    def measured(self, noise, scale, *, generator: torch.Generator | None = None) -> TrajectoryPosterior:
        """The posterior of new *measurements* of these states: each sampled path with the measurement noise of
        ``noise`` (a :class:`~torchmisspec.noise.NoiseModel`) at standard deviation ``scale`` ``(d,)`` in its space
        added independently at every time (:meth:`NoiseModel.measure <torchmisspec.noise.NoiseModel.measure>`); a
        fit gives both: ``posterior.measured(gp.noise_, gp.noise_scale_)`` (a component it never measured, scale NaN,
        gets none). Its :meth:`interval` is the band that new measurements fall in (the bands of the states alone
        cover the true states, not noisy readings of them)."""
        from ..noise import NoiseModel

        if not isinstance(noise, NoiseModel):
            raise InputError(f"noise: expected a torchmisspec.noise.NoiseModel (a fit's gp.noise_), got {noise!r:.60}")
        d = self.samples.shape[-1]
        scale = as_tensor(scale, "scale", dtype=self.samples.dtype, device=self.samples.device)
        if scale.shape != (d,) or not bool((torch.isnan(scale) | (torch.isfinite(scale) & (scale >= 0))).all()):
            raise InputError(
                f"scale: expected ({d},) standard deviations >= 0 (a fit's gp.noise_scale_; NaN for a component never "
                f"measured), got {scale.tolist() if scale.numel() <= 8 else tuple(scale.shape)}"
            )
        samples = noise.measure(self.samples, scale.nan_to_num(nan=0.0), generator)  # never measured: no noise
        return dataclasses.replace(self, samples=torch.where(torch.isnan(self.samples), math.nan, samples))

    def read(self, readout: Readout) -> TrajectoryPosterior:
        """The posterior of what ``readout`` reads (a :class:`~torchmisspec.data.Readout`, z = H y): every sampled
        path and the mean path read out, ``(.., m)``; :meth:`interval` then gives the readings' band (e.g. the
        total a tracer counts, when the states themselves are not measured)."""
        if not isinstance(readout, Readout):
            raise InputError(f"readout: expected a torchmisspec.data.Readout, got {type(readout).__name__}")
        d = self.samples.shape[-1]
        if readout.state_dim != d:
            raise ShapeError(f"readout: expected weights over the {d} states, got {readout.state_dim} columns")
        readout = readout.for_states(self.state_names, "the posterior's system")  # by name, when both name them
        return dataclasses.replace(  # a reading of draws that left the region: dropped from its band, not censored
            self,
            samples=readout(self.samples),
            mean_path=readout(self.mean_path),
            state_names=readout.names,
            escaped=None,
        )


def _censored_band(samples: torch.Tensor, escaped: torch.Tensor, region, level: float):
    """:meth:`TrajectoryPosterior.interval` with the draws that left the region across an edge in a component
    (``escaped`` +1 / -1) counted at that edge (censored: beyond it, how far unknown); the other components of such
    a draw, and the draws that stalled, as :func:`_remaining_band` (left out), except where too few remain for the
    level: there the band is the whole region (they may be anywhere in it). The band is finite, and where more than
    its tail of the draws left on one side, that end is the region's edge (one warning says at how many entries)."""
    lo, hi = (b.to(samples) for b in region)
    gone = torch.isnan(samples)
    values = torch.where(gone & (escaped > 0), hi, samples)
    values = torch.where(gone & (escaped < 0), lo, values)
    lower, upper = _remaining_band(values, level, quiet=True)  # entries too few remain for: the region, below
    left = gone & (escaped != 0).any(-1, keepdim=True)  # (S, ...): components of draws that left the region
    unknown = torch.isnan(lower) & left.any(0)
    lower = torch.where(unknown, lo.expand_as(lower), lower)
    upper = torch.where(unknown, hi.expand_as(upper), upper)
    at_edge = (lower <= lo) | (upper >= hi)
    if bool(at_edge.any()):
        warn(
            f"interval: at {int(at_edge.sum())} of {at_edge.numel()} entries so many draws left the region "
            f"(posterior.region) that the central {level:g} band reaches its edge there: the states may lie anywhere "
            "beyond it (posterior.fraction_remaining says how many draws remained). Shorten the time span, or collect "
            "data where the paths go",
            TorchMisspecWarning,
        )
    if bool(torch.isnan(lower).any()):  # draws that stalled inside the region, too many: as before
        _warn_short(int(torch.isnan(lower).sum()), lower.numel(), samples.shape[0], level)
    return lower, upper


def _remaining_band(samples: torch.Tensor, level: float, quiet: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """:meth:`TrajectoryPosterior.interval` where some draws of ``samples (S, ...)`` are NaN (they left the region):
    at each entry the band of the n draws that remain, NaN where fewer than S remain and they are too few for
    ``level``, with one warning naming how many such entries there are (none when ``quiet``)."""
    S = samples.shape[0]
    n = (~torch.isnan(samples)).sum(0)
    lower = torch.full(n.shape, math.nan, dtype=samples.dtype, device=samples.device)
    upper = lower.clone()
    need = math.ceil(2.0 / (1.0 - level) - 1.0 - 1e-9) if level < 1.0 else math.inf  # draws the level needs
    short = 0
    for k in torch.unique(n).tolist():
        at = n == k
        if k < S and (k == 0 or (k < need and level > 0.0)):
            short += int(at.sum())
            continue
        qs = band_quantiles(level, k, dtype=samples.dtype, device=samples.device, what="interval")
        lo_hi = torch.nanquantile(samples[:, at], qs, dim=0)
        lower[at], upper[at] = lo_hi[0], lo_hi[1]
    if short and not quiet:
        _warn_short(short, n.numel(), S, level)
    return lower, upper


def _warn_short(short: int, total: int, S: int, level: float) -> None:
    """The warning of :func:`_remaining_band`: at ``short`` of ``total`` entries too few of the ``S`` draws remain."""
    need = math.ceil(2.0 / (1.0 - level) - 1.0 - 1e-9) if level < 1.0 else math.inf
    fewer = f"fewer than {need} draws" if need < math.inf else "fewer than all the draws (for a level of 1)"
    more = f"Draw more (num_samples={max(need, S) * 2}), ask" if need < math.inf else "Ask"
    warn(
        f"interval: at {short} of {total} entries {fewer} remain in the region (of the {S} drawn; the "
        f"others diverged out of it: posterior.fraction_remaining), too few for the central {level:g} band: "
        f"those entries are NaN. {more} a lower level, or shorten the time span",
        TorchMisspecWarning,
    )
