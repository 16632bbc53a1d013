"""The readings' domain criterion: how much readings z = H y lower the posterior variance of F averaged over D.

:class:`~torchmisspec.design.ReadoutCriterion` scores, by default, the readings' information about F anywhere
(:mod:`._readings`). That prefers the candidates whose paths sweep far and fast (a predator-prey orbit started far
from its equilibrium), which a scientist who wants F over a box D of its inputs may not need:
``ReadoutCriterion(readout, domain=DomainCriterion(...))`` scores instead the mean posterior variance of F over D
that the readings remove, the quantity the error-over-D studies measure (:mod:`._domain` for correction samples).

The readings are linear in F to first order (:mod:`._readings`): the whitened readings of candidate c are
z_c = sum_o A_c^(o) f_o(X_c) + eps, with A_c^(o) ``(R, S)`` (quadrature weights and the noise included) and X_c its
S quadrature nodes. :mod:`._domain`'s feature model writes each output f_o(x) = phi(x)^T w_o + f_r(x), w_o ~ N(0, I)
over the r pivot nodes of D, the residual f_r of variance rho(x) = k(x, x) - |phi(x)|^2 (zero on the pivots, tiny
inside D) taken with its full covariance along each candidate's path and independent between candidates (PITC,
Snelson and Ghahramani 2007: the nodes of one path are close together, and treating their residuals as independent,
as FITC does, would understate a reading's residual variance). So

    z_c = F_c w + e_c,    F_c = [A_c^(1) phi(X_c), ..., A_c^(d_out) phi(X_c)]   (R, d_out r),
    Cov(e_c) = N_c = I + sum_o A_c^(o) R_c A_c^(o)T,    R_c = k(X_c, X_c) - phi(X_c) phi(X_c)^T,

and with L_c L_c^T = N_c the candidate's whitened features are Psi_c = L_c^-1 F_c: exactly the form the domain engine
takes (:class:`._domain.DomainTerms`), with the outputs' features stacked (A_0 = I (x) A_D, W = I (x) W_D, A_D the
data's precision and W_D the quadrature over D of one output). The residual's share makes a reading of nodes outside
D worth less, as it does for correction samples there.

V is monotone but not submodular in general (:mod:`._domain`): greedy's picks carry no (1 - 1/e) guarantee.
"""

from __future__ import annotations

import torch

from .._linalg import cholesky
from ._domain import DomainModel, DomainTerms

__all__ = ["readings_terms"]


def readings_terms(model: DomainModel, A: torch.Tensor, nodes: torch.Tensor, Bt: torch.Tensor | None = None):
    """The domain engine's :class:`~._domain.DomainTerms` for the readings of N candidates: ``A (N, R, d_out, S)``
    their whitened sensitivities to F at their quadrature nodes ``nodes (N, S, d_in)``, and with G's uncertain
    parameters ``Bt (N, R, p)`` their whitened sensitivity to theta times its covariance's factor (see the module
    docstring)."""
    N, R, d_out, S = A.shape
    phi, _ = model.features(nodes)  # (N, S, r)
    r = phi.shape[-1]
    F = torch.einsum("nros,nsk->nrok", A, phi).reshape(N, R, d_out * r)
    dd = {"dtype": A.dtype, "device": A.device}
    outputs = torch.eye(d_out, **dd)
    A0, W = torch.kron(outputs, model.A), torch.kron(outputs, model.W)
    if Bt is not None:  # theta's features: in the precision's prior, not in the quadrature
        p = Bt.shape[-1]
        F = torch.cat([F, Bt], dim=-1)
        A0 = torch.block_diag(A0, torch.eye(p, **dd))
        W = torch.block_diag(W, torch.zeros(p, p, **dd))
    with torch.no_grad():  # F's residual off the features along each path, its covariance in full (PITC)
        residual = model.prior.module.forward(nodes, nodes) - phi @ phi.transpose(1, 2)  # (N, S, S)
    noise = torch.eye(R, **dd) + torch.einsum("nros,nst,nqot->nrq", A, residual, A)
    L = cholesky(noise, what="the readings' noise and F's residual off the domain's features")
    psi = torch.linalg.solve_triangular(L, F, upper=False)
    return DomainTerms(psi=psi, A=A0, W=W, multiplier=1)
