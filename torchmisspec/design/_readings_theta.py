"""The readings' information about F with G's uncertain parameters integrated out.

When G has uncertain parameters theta (``MisspecifiedSystem(parameters=...)``), a reading moves with theta as well as
with F. Linearised about the centre theta_0 (the fit's posterior mean, ``gp.parameters_``, else the prior mean) and
along the same proxy paths as F's sensitivity (:mod:`._readings`), a perturbation theta = theta_0 + eta moves the path
by the variational equation forced by G's derivative in theta:

    d(delta y)/dt = J(t) delta y + G_theta(y*(t)) eta,    so    delta z(t_j) ~ B_j eta,
    B_j = sum_{i : s_i <= t_j} w_{j,i} H Phi(t_j, s_i) G_theta(y*(s_i))

(the same transitions and trapezoid weights; G_theta by central differences of G). With eta ~ N(0, Sigma_theta)
(the fit's Laplace covariance, else the prior's) and Sigma_theta = L L^T, the whitened readings of a set S of
experiments are z_S = A_S f + B_S L nu + eps, nu ~ N(0, I), theta shared by every experiment.

**The criterion: the information about F with theta integrated out**,

    I_F(S) = (1/2) logdet(I + A_S K_S A_S^T + B_S Sigma_theta B_S^T) - (1/2) logdet(I + B_S Sigma_theta B_S^T),

the mutual information between F and the readings when theta is unknown (its uncertainty acts as noise that is
correlated across the experiments and shaped like G's response to theta). Why this and not the information about
theta and F jointly (the first term alone): the package designs experiments to learn the *missing term*; theta is a
nuisance, and a parameter that F could absorb is exactly one whose readings the joint criterion would reward twice
(once for theta, once for F) though they cannot tell the two apart. I_F discounts what theta can explain: an
experiment whose readings mostly pin theta is worth little for F, and one that separates F from theta's effect is
worth more. It reduces to the plug-in criterion as Sigma_theta -> 0.

An approximation, stated: after a fit, theta and F are correlated in their joint posterior (F can stand in for part of
theta's effect); the criterion takes theta's marginal posterior and F's GP conditioned on its own samples, each as the
fit reports them, not that coupling.

I_F is not submodular in general (the experiments' readings are coupled through theta, not only through F), so the
greedy picks carry no (1 - 1/e) guarantee. Over a box D (``ReadoutCriterion(domain=...)``), theta enters as extra
features of F's feature model with no weight in the quadrature: the variance of F over D with theta integrated out
(:func:`._readings_domain.readings_terms`).

The second term is cheap: with M_c = L^T B_c^T B_c L ``(p, p)``, logdet(I + B_S Sigma_theta B_S^T) =
logdet(I_p + sum_{c in S} M_c) (Sylvester).
"""

from __future__ import annotations

import torch

from .._errors import InputError
from .._linalg import cholesky
from ..systems import MisspecifiedSystem

__all__ = ["ThetaUncertainty", "theta_uncertainty"]

#: central-difference step of G_theta, in units of each parameter's standard deviation
STEP = 1e-3


class ThetaUncertainty:
    """G's uncertain parameters as the readings' criterion sees them: the centre ``theta (p,)``, the factor ``L`` of
    their covariance (``L L^T = Sigma_theta``) and where they came from (``"fitted"`` or ``"prior"``)."""

    def __init__(self, system: MisspecifiedSystem, theta: torch.Tensor, covariance: torch.Tensor, source: str):
        self.system, self.theta, self.source = system, theta, source
        self.L = cholesky(covariance, what="the uncertain parameters' covariance")

    @property
    def centred(self) -> MisspecifiedSystem:
        """The system with theta fixed at the centre (the proxies' dynamics)."""
        return self.system.at(self.theta)

    def forcing(self, paths: torch.Tensor, t=None, u=None) -> torch.Tensor:
        """``G_theta (N, S, d, p)`` along ``paths (N, S, d)`` (at times ``t (N, S)`` with inputs ``u (N, S, m)`` for a
        system that has them): central differences, steps of :data:`STEP` standard deviations."""
        sd = self.L.pow(2).sum(-1).sqrt()
        columns = []
        for k in range(self.theta.numel()):
            h = STEP * float(sd[k])
            up, down = self.theta.clone(), self.theta.clone()
            up[k] += h
            down[k] -= h
            diff = self.system.at(up).known_rhs(paths, t, u) - self.system.at(down).known_rhs(paths, t, u)
            columns.append(diff / (2 * h))
        return torch.stack(columns, dim=-1)

    def whitened_factor(self, B: torch.Tensor) -> torch.Tensor:
        """``B L`` for sensitivities ``B (..., p)``."""
        return B @ self.L.to(B)


def theta_uncertainty(system: MisspecifiedSystem, gp) -> ThetaUncertainty | None:
    """The parameters' centre and covariance: the fit's posterior (``gp.parameters_``) where it has one for these
    parameters, else the system's priors at its current theta; ``None`` for a system without uncertain parameters."""
    priors = system.parameters
    if priors is None:
        return None
    fitted = getattr(gp, "parameters_", None)
    if fitted is not None:
        if tuple(fitted.names) != tuple(priors.names):
            raise InputError(
                f"gp: expected a fit of system '{system.name}' whose parameters are {list(priors.names)}, got one "
                f"with {list(fitted.names)}; design with the GP fitted on this system"
            )
        return ThetaUncertainty(system, fitted.mean.detach().double(), fitted.covariance.detach().double(), "fitted")
    return ThetaUncertainty(system, system.theta.double(), torch.diag(priors.scale.double().pow(2)), "prior")
