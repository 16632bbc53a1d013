"""The price of a term through the ODE: a sparse rival for the feature kernel's terms refined on the trajectories.

Fitted to derivative samples, the feature kernel keeps a term only while the log evidence it adds exceeds a price
(:mod:`torchmisspec.gp._features`: BIC's ``log(N) / 2`` per term by default). Refined through the ODE
(:func:`~torchmisspec.fit_trajectories`), its terms' weights are re-learned by automatic relevance (MacKay's
updates), which keeps every term whose evidence-optimal weight is positive, however little it adds, and settles
slowly: on the UDE paper's Lotka-Volterra protocol (one trajectory of 31 noisy times on [0, 3]) 13-17 of the 20
terms were still active after the rounds, F's error over the data's box was 0.4-2.0 of its size in 6 of 10
realizations, and yet the two true terms (x y in both outputs) had the best Laplace evidence less BIC's price of
the sets compared in those realizations.

:func:`forward_selection` proposes a sparse set where the rounds end: the misfit linearised in the coefficients
(the initial-state offsets with their unit prior marginalised) is a linear model, in which terms are added one at a
time while BIC (half the residual sum of squares plus the price per term) falls, and removed when that lowers it.
:func:`~torchmisspec.fit_trajectories` refits the proposal through the ODE and keeps whichever of the two has the
lower BIC through the ODE (:func:`bic`), so the rival is judged on the trajectories, not on the linearisation
(which, at a wrong set of terms, misleads moves made round by round: tried and measured, issue 41's closing note).
"""

from __future__ import annotations

import torch

from ..._linalg import cholesky
from ...gp._relevance import term_price as _price

__all__ = ["bic", "forward_selection", "term_price"]

#: BIC must fall by more than this (nats) for a move of the forward selection to be made (no move on a tie).
_MARGIN = 1e-9


def term_price(gp, n_obs: int) -> float:
    """The price of a term through the ODE: the samples' rule (:func:`~torchmisspec.gp._relevance.term_price`:
    ``gp.min_gain`` when set, else ``log(n_obs) / 2``) with ``n_obs`` the scalar measurements of the trajectories."""
    return _price(getattr(gp, "min_gain", None), n_obs)


def bic(misfit: float, terms: int, price: float) -> float:
    """Half the scaled misfit (the sum of squared residuals over their noise variances) plus ``price`` per term."""
    return 0.5 * misfit + price * terms


def _whitened(J: torch.Tensor, r: torch.Tensor, beta: torch.Tensor, J_f, f):
    """``(A, z)``: the linearised misfit ``||A beta - z||^2``, the unknowns ``J_f f`` with their unit normal prior
    marginalised (their covariance ``J_f J_f^T`` added to the residuals' identity, then whitened)."""
    y = J @ beta - r
    C = torch.eye(r.shape[0], dtype=r.dtype, device=r.device)
    if J_f is not None and J_f.shape[1]:
        y = y + J_f @ f
        C = C + J_f @ J_f.T
    L = cholesky(C, what="the residuals' covariance with the initial states marginalised")
    A = torch.linalg.solve_triangular(L, J, upper=False)
    z = torch.linalg.solve_triangular(L, y.unsqueeze(-1), upper=False).squeeze(-1)
    return A, z


def _score(A: torch.Tensor, z: torch.Tensor, kept: frozenset, price: float) -> float:
    """BIC of the least-squares fit of ``z`` on the columns ``kept`` of ``A``."""
    if not kept:
        return bic(float(z @ z), 0, price)
    P = A[:, sorted(kept)]
    coef = torch.linalg.lstsq(P, z.unsqueeze(-1)).solution.squeeze(-1)
    e = z - P @ coef
    return bic(float(e @ e), len(kept), price)


def forward_selection(J: torch.Tensor, r: torch.Tensor, beta: torch.Tensor, price: float, J_f=None, f=None):
    """The proposed terms, ``(q,)`` booleans: from none, the best addition or removal of one term at a time while
    BIC of the linearised model falls.

    ``J (n, q)``: d (scaled residual) / d coefficient for every coefficient at ``beta (q,)``; ``r (n,)``: the scaled
    residuals there; ``J_f (n, s)``, ``f (s,)``: the columns and values of the other unknowns (each with a unit
    normal prior: the initial-state offsets), or ``None``."""
    A, z = _whitened(J, r, beta, J_f, f)
    q = A.shape[1]
    kept: frozenset = frozenset()
    best = _score(A, z, kept, price)
    for _ in range(2 * q):  # each move lowers BIC; the cap guards round-off
        trials = [kept | {j} for j in range(q) if j not in kept] + [kept - {j} for j in kept]
        value, chosen = min((_score(A, z, t, price), sorted(t)) for t in trials)
        if not value < best - _MARGIN:
            break
        best, kept = value, frozenset(chosen)
    return torch.tensor([j in kept for j in range(q)], dtype=torch.bool, device=J.device)
