"""Uncertain parameters of the known model G, learned with the correction F.

The declaration (:class:`Priors`, from ``parameters=`` of :class:`~torchmisspec.MisspecifiedSystem`), G's
Jacobian in theta (:func:`parameter_basis`), and the posterior object (:class:`ParameterPosterior`). How theta is
learned: :mod:`torchmisspec.learning.theta`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from ._errors import InputError, TorchMisspecWarning, warn
from ._validation import (
    DEFAULT_DTYPE,
    as_tensor,
    check_callable,
    check_finite,
    check_generator,
    check_positive_int,
    check_real,
)

__all__ = [
    "Priors",
    "ParameterPosterior",
    "check_priors",
    "parameter_basis",
    "jacobian",
    "IDENTIFIED_RATIO",
    "CORRELATION_LIMIT",
    "LINEARITY_TOLERANCE",
    "LARGER_CORRECTION",
]

#: theta_k counts as identified from the data when its posterior standard deviation is at most this fraction of its
#: prior's (the data removed at least 3/4 of the prior variance)
IDENTIFIED_RATIO = 0.5
#: parameters whose posterior correlation exceeds this in absolute value are reported as only jointly determined
CORRELATION_LIMIT = 0.95
#: how much larger (in variance) a correction is allowed to be in the check of whether F can stand in for a
#: parameter: the data must still determine theta_k when F's prior variance is this many times the fitted one (and
#: at least what a change of 2 prior standard deviations in a parameter makes to G)
LARGER_CORRECTION = 100.0
#: relative tolerance of the numerical check that G is linear in its uncertain parameters
LINEARITY_TOLERANCE = 1e-6
#: the central differences of a nonlinear G's Jacobian in theta, in prior scales
JACOBIAN_STEP = 1e-4


@dataclass(frozen=True)
class Priors:
    """Independent Gaussian priors of G's uncertain parameters: ``names`` ``(k,)``, ``mean`` and ``scale`` (standard
    deviations), float64 tensors ``(k,)``."""

    names: tuple[str, ...]
    mean: torch.Tensor
    scale: torch.Tensor

    def __len__(self) -> int:
        return len(self.names)


def check_priors(parameters) -> Priors | None:
    """``parameters`` as :class:`Priors`: a mapping ``name -> (value, scale)`` (the prior mean and standard deviation,
    finite, the scale positive), or ``None`` (no uncertain parameter)."""
    if parameters is None or isinstance(parameters, Priors):
        return parameters
    if not isinstance(parameters, Mapping) or not parameters:
        raise InputError(
            "parameters: expected a non-empty mapping of names to (value, scale) priors, e.g. "
            f"{{'c': (0.4, 0.2)}}, got {type(parameters).__name__} {parameters!r:.80}"
        )
    means, scales = [], []
    for name, prior in parameters.items():
        if not isinstance(name, str) or not name:
            raise InputError(f"parameters: expected non-empty string names, got {name!r}")
        if not (isinstance(prior, (tuple, list)) and len(prior) == 2):
            raise InputError(
                f"parameters[{name!r}]: expected (value, scale), two real numbers (the prior mean and standard "
                f"deviation), got {prior!r:.80}"
            )
        value = check_real(prior[0], f"parameters[{name!r}] value (the prior mean)")
        scale = check_real(prior[1], f"parameters[{name!r}] scale (the prior standard deviation)", positive=True)
        means.append(value)
        scales.append(scale)
    return Priors(
        tuple(parameters), torch.tensor(means, dtype=DEFAULT_DTYPE), torch.tensor(scales, dtype=DEFAULT_DTYPE)
    )


def _theta_and_scale(rhs, theta, scale) -> tuple[torch.Tensor, torch.Tensor]:
    """``theta (k,)`` finite and ``scale (k,)`` positive, for the differences of a callable ``rhs``."""
    check_callable(rhs, "rhs", "rhs(theta) giving G at the data with the parameters theta (k,)")
    theta = check_finite(as_tensor(theta, "theta"), "theta")
    scale = check_finite(as_tensor(scale, "scale", dtype=theta.dtype, device=theta.device), "scale")
    if theta.dim() != 1 or scale.shape != theta.shape or not bool((scale > 0).all()):
        raise InputError(
            f"theta, scale: expected (k,) parameters and (k,) positive scales, got shapes {tuple(theta.shape)} and "
            f"{tuple(scale.shape)}" + ("" if scale.shape != theta.shape else " with a scale <= 0")
        )
    return theta, scale


def parameter_basis(rhs, theta: torch.Tensor, scale: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """``(basis, linear)``: G's basis g_k = dG/dtheta_k ``(..., d, k)`` at ``theta`` from ``rhs(theta) -> (..., d)``
    (G at the data with the parameters ``theta``), and whether G is linear in theta there.

    Linearity is checked numerically (a step of one prior scale ``scale`` back, and the steps of each pair at once,
    must agree with the differences of one step forward to :data:`LINEARITY_TOLERANCE`). A linear G's basis is those
    differences (exact); a nonlinear G's is its Jacobian at ``theta`` by central differences of
    :data:`JACOBIAN_STEP` prior scales, the linearisation the Gauss-Newton / Laplace fit uses
    (:mod:`torchmisspec.learning.theta.closed_form`)."""
    theta, scale = _theta_and_scale(rhs, theta, scale)
    base = rhs(theta)
    k = theta.shape[0]
    steps = torch.eye(k, dtype=theta.dtype, device=theta.device) * scale.to(theta)
    ups = [rhs(theta + steps[j]) for j in range(k)]
    size = base.abs().amax() + sum(float((u - base).abs().amax()) for u in ups) + 1e-300
    checks = [(rhs(theta - steps[j]), base - (ups[j] - base)) for j in range(k)]
    checks += [(rhs(theta + steps[i] + steps[j]), ups[i] + ups[j] - base) for i in range(k) for j in range(i + 1, k)]
    linear = all(float((got - want).abs().amax()) <= LINEARITY_TOLERANCE * float(size) for got, want in checks)
    if linear:
        return torch.stack([(ups[j] - base) / scale[j].item() for j in range(k)], dim=-1), True
    return jacobian(rhs, theta, scale), False


def jacobian(rhs, theta: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """dG/dtheta ``(..., d, k)`` at ``theta`` by central differences of :data:`JACOBIAN_STEP` prior scales ``scale``
    (``rhs(theta) -> (..., d)``): the basis of a G known to be nonlinear in theta."""
    theta, scale = _theta_and_scale(rhs, theta, scale)
    h = torch.eye(theta.shape[0], dtype=theta.dtype, device=theta.device) * scale.to(theta) * JACOBIAN_STEP
    cols = [(rhs(theta + h[j]) - rhs(theta - h[j])) / (2 * h[j, j].item()) for j in range(theta.shape[0])]
    return torch.stack(cols, dim=-1)


@dataclass(frozen=True)
class ParameterPosterior:
    """The posterior of G's uncertain parameters given the data, F integrated out
    (:mod:`torchmisspec.learning.theta.closed_form`).

    Attributes:
        names: the parameters' names ``(k,)``.
        prior_mean, prior_scale: their priors ``(k,)``.
        mean: the posterior mean ``(k,)``.
        covariance: the posterior covariance ``(k, k)``.
        sd_without_correction: the posterior standard deviation the same samples would give with no correction F
            (noise only), ``(k,)``: far below :attr:`stddev` when F can absorb the parameter's effect.
        log_evidence: log p(r) of the residual samples with theta integrated out (nats).
        basis_targets: the basis g_k at the GP's training inputs on the corrected components ``(N, d_out, k)``
            (F's absorption of each, :meth:`draw_terms`).
        linear: whether G is linear in theta (else the posterior is the Laplace approximation at the MAP, and
            :attr:`log_evidence` the linearised model's).
        sd_larger_correction: per parameter, the posterior standard deviation the same samples would give with F's
            prior variance :data:`LARGER_CORRECTION` times the fitted one, and at least what a change of 2 prior
            standard deviations in a parameter makes to G ``(k,)``: near the prior's where F could
            stand in for the parameter had it been allowed to be larger (its fitted size, not the data, then decides
            the parameter); ``None`` where the fit did not compute it.
    """

    names: tuple[str, ...]
    prior_mean: torch.Tensor
    prior_scale: torch.Tensor
    mean: torch.Tensor
    covariance: torch.Tensor
    sd_without_correction: torch.Tensor
    log_evidence: float
    basis_targets: torch.Tensor
    linear: bool = True
    sd_larger_correction: torch.Tensor | None = None

    @property
    def stddev(self) -> torch.Tensor:
        """Posterior standard deviations ``(k,)``."""
        return self.covariance.diagonal().clamp_min(0).sqrt()

    @property
    def correlation(self) -> torch.Tensor:
        """Posterior correlation matrix ``(k, k)``."""
        sd = self.stddev.clamp_min(1e-300)
        return self.covariance / (sd[:, None] * sd[None, :])

    @property
    def moved(self) -> torch.Tensor:
        """How far each estimate went from its prior mean, in prior standard deviations ``(k,)``."""
        return (self.mean - self.prior_mean.to(self.mean)).abs() / self.prior_scale.to(self.mean)

    @property
    def absorbable(self) -> tuple[bool, ...]:
        """Per parameter: whether F could stand in for it: with F allowed to be larger, the data would leave it
        undetermined (:attr:`sd_larger_correction` above :data:`IDENTIFIED_RATIO` of the prior's), and F is the
        reason (at least twice :attr:`sd_without_correction`: a parameter the samples inform weakly with or without
        F is not one F absorbs)."""
        if self.sd_larger_correction is None:
            return (False,) * len(self.names)
        larger = self.sd_larger_correction
        wide = larger > IDENTIFIED_RATIO * self.prior_scale.to(larger)
        by_f = larger >= 2 * self.sd_without_correction.to(larger)
        return tuple(bool(v) for v in (wide & by_f))

    @property
    def identified(self) -> tuple[bool, ...]:
        """Per parameter: whether the data determined it: posterior sd at most :data:`IDENTIFIED_RATIO` of the
        prior's, and not a parameter F can stand in for (:attr:`absorbable`). Where F can, the data cannot tell the
        parameter's error from a missing term whatever the width says: the width then measures F's prior (a small F
        is preferred, so the parameter takes up what is missing) or the curvature of G in it (the Laplace width of a
        parameter entering G as 1 / theta shrinks as its estimate drifts low), not where the parameter is."""
        narrow = self.stddev <= IDENTIFIED_RATIO * self.prior_scale.to(self.stddev)
        return tuple(bool(n) and not a for n, a in zip(narrow, self.absorbable, strict=True))

    def as_dict(self) -> dict[str, tuple[float, float]]:
        """``{name: (posterior mean, posterior sd)}``."""
        return {n: (float(m), float(s)) for n, m, s in zip(self.names, self.mean, self.stddev, strict=True)}

    def summary(self) -> str:
        """One line per parameter: prior, posterior, and whether the data determined it."""
        lines = []
        for j, name in enumerate(self.names):
            tag = "" if self.identified[j] else "  NOT identified from these data"
            lines.append(
                f"{name} = {float(self.mean[j]):.4g} +- {float(self.stddev[j]):.2g} (prior "
                f"{float(self.prior_mean[j]):.4g} +- {float(self.prior_scale[j]):.2g}; without a correction "
                f"+- {float(self.sd_without_correction[j]):.2g}){tag}"
            )
        return "\n".join(lines)

    def problems(self) -> list[str]:
        """What the data leave undetermined, in words (empty when every parameter is identified)."""
        out = []
        s0 = self.prior_scale.to(self.stddev)
        for j, name in enumerate(self.names):
            if not self.identified[j]:
                out.append(self._problem(j, name, s0))
        corr = self.correlation
        k = len(self.names)
        for i in range(k):
            for j in range(i + 1, k):
                if abs(float(corr[i, j])) > CORRELATION_LIMIT:
                    out.append(
                        f"{self.names[i]} and {self.names[j]}: posterior correlation {float(corr[i, j]):+.3f}, only a "
                        "combination of the two is determined"
                    )
        return out

    def absorbing(self, other: ParameterPosterior | None) -> ParameterPosterior:
        """This posterior with :attr:`sd_larger_correction` at least ``other``'s (per parameter): what a correction
        could stand in for stays on record when the model returned has another F, or none (the known model alone,
        F = 0, whose parameters then take up what is missing)."""
        if other is None or other.sd_larger_correction is None:
            return self
        theirs = other.sd_larger_correction.to(self.mean)
        mine = theirs if self.sd_larger_correction is None else torch.maximum(self.sd_larger_correction, theirs)
        return dataclasses.replace(self, sd_larger_correction=mine)

    def _problem(self, j: int, name: str, s0: torch.Tensor) -> str:
        """Why parameter ``j`` is not identified, and where its estimate went."""
        ratio = float(self.stddev[j] / s0[j])
        where = (
            f"estimate {float(self.mean[j]):.4g} +- {float(self.stddev[j]):.2g}, {float(self.moved[j]):.1f} prior sd "
            f"from its prior {float(self.prior_mean[j]):.4g} +- {float(s0[j]):.2g}"
        )
        if self.absorbable[j] and ratio <= IDENTIFIED_RATIO:
            larger = float(self.sd_larger_correction[j] / s0[j])
            return (
                f"{name}: {where}; a correction F allowed to be larger would leave it at {larger:.2f} of the prior's "
                "sd, so F could stand in for its effect on G: the data cannot tell this parameter's error from a "
                "missing term, and its narrow posterior (set by F's fitted size) is not evidence of where it is: do "
                "not read the estimate as measured"
            )
        without = float(self.sd_without_correction[j] / s0[j])
        reason = (
            f"the correction F can absorb its effect on G (without F the same data would determine it to "
            f"{without:.2f} of the prior's sd): a parameter error and a missing term look alike here"
            if without <= IDENTIFIED_RATIO or self.absorbable[j]
            else "these data hardly depend on it"
        )
        return f"{name}: posterior sd {ratio:.2f} of the prior's ({where}); {reason}"

    def warn_if_unidentified(self, where: str) -> None:
        problems = self.problems()
        if problems:
            warn(
                f"{where}: uncertain parameters not determined by the data ({'; '.join(problems)}). The bands include "
                "their posterior widths, so where a width is set by F's fitted size (said above) the bands do not show "
                "the trade-off; to tell them apart, measure where G's dependence on them differs from what F may "
                "depend on (other states, inputs or times), or tighten their priors",
                TorchMisspecWarning,
            )

    def sample(self, num_samples: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``num_samples`` draws of theta ``(S, k)`` from the posterior."""
        num_samples = check_positive_int(num_samples, "num_samples", minimum=0)
        generator = check_generator(generator, self.covariance.device)
        L = torch.linalg.cholesky(
            self.covariance + 1e-12 * self.covariance.diagonal().max() * torch.eye(len(self.names)).to(self.covariance)
        )
        eps = torch.randn(num_samples, len(self.names), generator=generator, dtype=L.dtype, device=L.device)
        return self.mean + eps @ L.T

    def draw_terms(self, gp, *, with_mean: bool = False):
        """The functions m_k of the module's notes: ``x (M, d_in) -> (M, d_out, k)``, F's posterior mean given the
        targets g_k (what F absorbs of each parameter's effect), from ``gp``'s current factor; ``with_mean``: F's
        posterior mean first, ``(M, d_out, 1 + k)``, from the same kernel block."""
        post = gp.posterior()
        parts = [post.with_targets(self.basis_targets[:, :, j].to(post.weights)) for j in range(len(self.names))]
        parts = [post, *parts] if with_mean else parts
        return post.means_function(parts)  # one kernel block for every parameter's term

    def draw_field(self, system, gp, deltas: torch.Tensor, batch: int, *, with_mean: bool = False):
        """G under each posterior draw (:mod:`torchmisspec.learning.theta.closed_form`): for draws ``deltas`` ``(S, k)``
        of theta - :attr:`mean`, a function ``(y, t, u, x) -> (S * batch, d)`` of the states, times, controls and
        correction inputs of the rows (draw s drives rows s * batch ... s * batch + batch - 1): G at the row's theta
        (one call of G for every row, :meth:`~torchmisspec.MisspecifiedSystem.rows_rhs`) less what F absorbs of the
        move from :attr:`mean`; ``with_mean``: plus F's posterior mean, from the same kernel block as the absorbed
        terms (a fit's right-hand side)."""
        at_mean = system.at(self.mean)
        rows = deltas.repeat_interleave(batch, dim=0)
        thetas = self.mean + rows  # every row's theta, once (not at every step)
        moved = bool(deltas.any())  # else every draw at the mean: G and F's mean unmoved
        if not moved and not with_mean:
            return lambda y, t, u, x: at_mean.known_rhs(y, t, u)
        terms = self.draw_terms(gp, with_mean=with_mean)
        weights = -rows if not with_mean else torch.cat([torch.ones_like(rows[:, :1]), -rows], -1)

        def field(y: torch.Tensor, t, u, x: torch.Tensor) -> torch.Tensor:
            m = terms(x.to(gp.device, gp.dtype)).to(y)  # (rows, d_out, k) or (rows, d_out, 1 + k)
            g = system.rows_rhs(y, t, u, thetas.to(y)) if moved else at_mean.known_rhs(y, t, u)
            return g + system.embed((m * weights.to(y).unsqueeze(1)).sum(-1))

        return field

    @classmethod
    def prior(cls, priors: Priors, num_samples: int, output_dim: int, like: torch.Tensor) -> ParameterPosterior:
        """The prior as a posterior (a model whose fit did not learn theta): F absorbs nothing of it."""
        mean, scale = priors.mean.to(like), priors.scale.to(like)
        return cls(
            names=priors.names,
            prior_mean=mean,
            prior_scale=scale,
            mean=mean,
            covariance=torch.diag(scale**2),
            sd_without_correction=scale,
            log_evidence=math.nan,
            basis_targets=like.new_zeros(num_samples, output_dim, len(priors)),
        )

    def to_dict(self) -> dict:
        """Plain values and CPU tensors for a model file."""
        return {
            "names": list(self.names),
            "prior_mean": self.prior_mean.detach().cpu(),
            "prior_scale": self.prior_scale.detach().cpu(),
            "mean": self.mean.detach().cpu(),
            "covariance": self.covariance.detach().cpu(),
            "sd_without_correction": self.sd_without_correction.detach().cpu(),
            "log_evidence": float(self.log_evidence),
            "basis_targets": self.basis_targets.detach().cpu(),
            "linear": bool(self.linear),
            **({} if self.sd_larger_correction is None else {"sd_larger_correction": self.sd_larger_correction.cpu()}),
        }

    @classmethod
    def from_dict(cls, values, path, *, num_samples: int, output_dim: int, like: torch.Tensor) -> ParameterPosterior:
        """The record of :meth:`to_dict`, checked (``path`` names the file in errors)."""
        fields = ("names", "prior_mean", "prior_scale", "mean", "covariance", "sd_without_correction")
        if not isinstance(values, dict) or not all(f in values for f in (*fields, "basis_targets", "log_evidence")):
            raise InputError(
                f"{path}: expected an uncertain-parameter record with fields {list(fields)}, got {values!r:.80}"
            )
        names = values["names"]
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise InputError(f"{path}: expected the parameters' names as a list of strings, got {names!r:.80}")
        k = len(names)
        shapes = {
            "prior_mean": (k,),
            "prior_scale": (k,),
            "mean": (k,),
            "covariance": (k, k),
            "sd_without_correction": (k,),
            "basis_targets": (num_samples, output_dim, k),
        }
        for key, shape in shapes.items():
            t = values[key]
            if not (isinstance(t, torch.Tensor) and t.is_floating_point() and tuple(t.shape) == shape):
                raise InputError(f"{path}: expected {key!r} a float tensor of shape {shape}, got {t!r:.60}")
            if not bool(torch.isfinite(t).all()):
                raise InputError(f"{path}: {key!r} holds non-finite values (the file is damaged)")
        try:
            evidence = float(values["log_evidence"])
        except (TypeError, ValueError) as exc:
            raise InputError(f"{path}: expected 'log_evidence' a number ({exc})") from exc
        linear = values.get("linear", True)  # files written before nonlinear parameters: linear
        if not isinstance(linear, bool):
            raise InputError(f"{path}: expected 'linear' True or False, got {linear!r:.40}")
        larger = values.get("sd_larger_correction")  # files written before issue 42: not computed
        shaped = isinstance(larger, torch.Tensor) and tuple(larger.shape) == (k,)
        if larger is not None and not (shaped and bool(torch.isfinite(larger).all())):
            raise InputError(
                f"{path}: expected 'sd_larger_correction' a finite float tensor of shape ({k},), got {larger!r:.60}"
            )
        return cls(
            tuple(names),
            **{key: values[key].to(like) for key in shapes},
            log_evidence=evidence,
            linear=linear,
            sd_larger_correction=None if larger is None else larger.to(like),
        )
