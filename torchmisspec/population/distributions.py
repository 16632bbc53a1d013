"""How a parameter varies between experiments: :class:`Normal` or :class:`LogNormal` around the population's value.

Each experiment i has its own value theta_i of a varying parameter. Its distribution over the population is Gaussian
in a transformed coordinate ``eta = to_eta(theta)``: ``eta_i ~ N(mu + beta^T c_i, omega^2)`` (``c_i`` the
experiment's covariates, centred). :class:`Normal` is the identity (a spread in the parameter's own units);
:class:`LogNormal` is ``log`` (a spread in relative terms, for positive parameters: clearances, rates, volumes, the
usual choice of pharmacometrics, where omega = 0.3 is about a 30 % coefficient of variation).
"""

from __future__ import annotations

import math

import torch

from .._errors import InputError

__all__ = ["Distribution", "LogNormal", "Normal"]


class Distribution:
    """A population distribution: Gaussian in ``eta = to_eta(theta)`` (subclass it: ``name``, :meth:`to_eta`,
    :meth:`from_eta`, :meth:`spread_of`)."""

    name = ""

    def to_eta(self, theta: torch.Tensor) -> torch.Tensor:
        """The parameter's values in the coordinate where the population is Gaussian."""
        raise NotImplementedError

    def from_eta(self, eta: torch.Tensor) -> torch.Tensor:
        """The parameter's values from that coordinate."""
        raise NotImplementedError

    def spread_of(self, value: float, scale: float) -> float:
        """A starting spread omega in eta's units from a prior ``(value, scale)`` of the parameter."""
        raise NotImplementedError

    def check(self, name: str, value: float) -> None:
        """Refuse a prior value this distribution cannot hold (a log-normal parameter that is not positive)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    def __eq__(self, other) -> bool:
        return type(self) is type(other)

    def __hash__(self) -> int:
        return hash(type(self))


class Normal(Distribution):
    """theta_i ~ N(mu, omega^2) in the parameter's own units."""

    name = "normal"

    def to_eta(self, theta):
        return theta

    def from_eta(self, eta):
        return eta

    def spread_of(self, value, scale):
        return float(scale)


class LogNormal(Distribution):
    """log theta_i ~ N(mu, omega^2): a positive parameter whose spread is relative (omega ~ its coefficient of
    variation when small)."""

    name = "lognormal"

    def to_eta(self, theta):
        return torch.log(theta)

    def from_eta(self, eta):
        return torch.exp(eta)

    def spread_of(self, value, scale):
        return math.sqrt(math.log1p((float(scale) / float(value)) ** 2))

    def check(self, name, value):
        if not value > 0:
            raise InputError(
                f"population: expected a positive prior value of the log-normal parameter {name!r}, got {value:g}; "
                "declare it Normal() or give a positive value"
            )


#: the distributions by name (the CLI's words)
DISTRIBUTIONS = {"normal": Normal, "lognormal": LogNormal}
