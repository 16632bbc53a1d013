"""Sparse Bayesian learning of the feature kernel's weights (automatic relevance with a price per term).

:func:`fit_relevance` maximises the evidence of the samples over one prior variance (weight) per term of the
library and the noise floor, by fixed-point updates in feature space (O(N p^2)), removing a term whose weight
falls to :data:`~torchmisspec.gp._features.PRUNE` and, with a price ``min_gain`` per term, keeping a term only
while the log evidence it adds exceeds the price (re-admitting removed terms whose gain comes back). The kept
terms' slab (:func:`unit_information_weights`) and each term's posterior chance of being present
(:func:`term_inclusion`) are computed from the same quantities. The maths is in :mod:`torchmisspec.gp._features`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from .._errors import FittingError
from .._linalg import cholesky
from ._features import PRUNE, _posterior

__all__ = ["fit_relevance", "noise_groups", "term_gain", "term_inclusion", "term_price", "unit_information_weights"]

#: Relative change of the log weights (and noise) below which the fixed-point iteration has converged.
_TOLERANCE = 1e-9
#: Removed terms are tested for re-entry only above this noise (a fraction of the targets' second moment): below it
#: the test's residual correlations are round-off, and nearly noiseless fits keep every term they need anyway.
_READD_NOISE = 1e-8
#: Relative changes below this count as converged beside known noise with a learned floor: the golden-section search
#: (:func:`_golden_floor`, 40 steps over a bracket of about 30 in log space) resolves the floor to about 1e-7.
_GOLDEN_RESOLUTION = 1e-6
#: Beside known noise with a learned floor, the iteration has also converged when the last
#: :data:`_PLATEAU_ITERATIONS` iterations did not raise the log evidence above its best before them by
#: :data:`_PLATEAU_NATS`: on nearly exact samples (known noise 1e-12 of the targets' second moment, the floor at its
#: minimum) the weights went round a cycle of about 300 iterations whose log evidence varied by 8e-4 nats, each
#: iteration with a golden-section search of the floor, until the cap of 2,000 (a one-trajectory command-line fit of
#: 21 exact states took 53 s, 48 of them here). The best converged state is kept either way.
_PLATEAU_NATS = 1e-6
_PLATEAU_ITERATIONS = 100
#: A removed term is added back only when its gain exceeds the price by this many nats (no move back and forth on a
#: tie).
_MARGIN = 1e-6
#: The learned noise floor is kept above this fraction of the targets' second moment (noiseless data stay solvable).
_MIN_NOISE = 1e-12


def _evidence(Phi, Y, D, w) -> float:
    """Log evidence summed over the outputs ``Y (N, m)`` sharing weights ``w``, noise ``D (N, m)``."""
    total = 0.0
    act = w > 0
    P = Phi[:, act]
    for o in range(Y.shape[1]):
        y, d = Y[:, o], D[:, o]
        quad = float((y * y / d).sum())
        logdet = float(d.log().sum())
        if bool(act.any()):
            _, mu, logdet_A = _posterior(P.T @ (P / d.unsqueeze(-1)), P.T @ (y / d), w[act])
            quad -= float(mu @ (P.T @ (y / d)))
            logdet += float(logdet_A) + float(w[act].log().sum())
        total += -0.5 * quad - 0.5 * logdet - 0.5 * y.numel() * math.log(2 * math.pi)
    return total


@dataclass(frozen=True)
class _Data:
    """What every iteration of :func:`fit_relevance` reads: the features ``Phi (N, p)``, targets ``Y (N, m)`` and
    known noise (or ``None``), each term's mean square feature ``scale_phi (p,)``, the targets' second moment, the
    floor's lower bound and whether the floor is learned; without known noise the sufficient statistics
    ``Phi^T Phi``, ``Phi^T Y`` and the targets' sums of squares, which make every iteration O(p^3)."""

    Phi: torch.Tensor
    Y: torch.Tensor
    known: torch.Tensor | None
    scale_phi: torch.Tensor
    second: float
    s_min: float
    learn_floor: bool
    G0: torch.Tensor | None = None
    B0: torch.Tensor | None = None
    yy: torch.Tensor | None = None

    @classmethod
    def of(cls, Phi: torch.Tensor, Y: torch.Tensor, known, floor) -> _Data:
        """The fit's data, after refusing targets that are all zero (every weight would be 0)."""
        second = float(Y.pow(2).mean())
        if not second > 0:
            raise FittingError(
                "targets: expected some non-zero samples to learn the feature weights from, got all zeros (every "
                "weight would be 0)"
            )
        scale_phi = Phi.pow(2).mean(0).clamp_min(torch.finfo(Phi.dtype).tiny)  # (p,)
        data = cls(Phi, Y, known, scale_phi, second, _MIN_NOISE * second, floor is None)
        if known is not None:
            return data
        return replace(data, G0=Phi.T @ Phi, B0=Phi.T @ Y, yy=Y.pow(2).sum(0))  # B0 (p, m), yy (m,)

    @property
    def homoscedastic(self) -> bool:
        """No known noise: one noise variance for every sample (the floor)."""
        return self.known is None


@dataclass(frozen=True)
class _Sums:
    """One fixed-point iteration's sums over the outputs, per active term: the squared posterior means ``num``, the
    well-determinedness factors ``gam_sum``, whether every output's best weight is 0 (``dead``); without known
    noise, the residual sum of squares, its degrees of freedom and the coefficients' posterior variances ``var``."""

    num: torch.Tensor
    gam_sum: torch.Tensor
    dead: torch.Tensor
    resid: float
    dof: float
    var: torch.Tensor | None


class _PriceSearch:
    """The moves of the price ``min_gain`` per term from each converged state: the best converged state so far by
    log evidence less the price (``best``: ``(value, w, floor)``), and the moves made (at most 4 per term)."""

    def __init__(self, data: _Data, min_gain: float):
        self.data, self.min_gain = data, min_gain
        self.best, self.moves = None, 0

    def step(self, w: torch.Tensor, s: float) -> bool:
        """At a converged state (w, s): keep it if it is the best so far, then one move of the price (``w`` changed
        in place); whether a move was made."""
        d = self.data
        self.best = _better(self.best, d.Phi, d.Y, d.known, w, s, self.min_gain)
        p = d.Phi.shape[1]
        if self.moves < 4 * p and _price_move(d.Phi, d.Y, d.known, w, s, self.min_gain, d.scale_phi, d.second):
            self.moves += 1
            return True
        return False


def fit_relevance(
    Phi: torch.Tensor,
    Y: torch.Tensor,
    known: torch.Tensor | None,
    *,
    floor: float | None,
    max_iter: int,
    min_gain: float = 0.0,
) -> tuple[torch.Tensor, float, int]:
    """Sparse Bayesian learning of the weights (and the noise floor) for outputs ``Y (N, m)`` sharing them.

    Args:
        Phi: ``(N, p)`` features of the training inputs.
        Y: ``(N, m)`` targets.
        known: ``(N, m)`` known noise variances or ``None``.
        floor: the noise floor if fixed, ``None`` to learn it.
        max_iter: most fixed-point iterations.
        min_gain: the price of a term in nats (the prior log-odds against it, see :func:`term_gain`): from each
            converged state, one move at a time (:func:`_price_move`) until no term's gain crosses the price; the
            best converged state by log evidence less the price is returned. 0 is plain automatic relevance.

    Returns:
        ``(w (p,), floor, iterations)``.
    """
    data = _Data.of(Phi, Y, known, floor)
    w = data.second / (Phi.shape[1] * data.scale_phi)
    s = 0.1 * data.second if data.learn_floor else float(floor)
    iterations = 0
    readmitted = torch.zeros_like(w, dtype=torch.bool)  # each term re-enters at most once: no remove/re-admit cycle
    price = _PriceSearch(data, min_gain)  # with a price: the best converged state by evidence less price
    plain_done = False  # plain relevance has converged (its re-admissions done)
    history: list[float] = []  # the log evidence after each iteration (known noise, learned floor)
    for iterations in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        if not bool((w > 0).any()):  # no term left: F = 0, and the noise is all of the targets' variance
            s = _empty_floor(data, w, s)
            if min_gain > 0 and price.step(w, s):  # a converged state too: a term may still be worth its price
                continue
            break
        new, new_s, change, pruned = _fixed_point(data, w, s)
        w, s = new, new_s
        if not (_converged(data, change, history, w, s) and not pruned):
            continue
        if not plain_done:  # plain relevance first: its converged state is where the price starts from
            if _readmits(data, w, s, readmitted):
                continue  # a removed term is relevant given the final others: back in, iterate again
            plain_done = True
        if min_gain > 0 and price.step(w, s):
            history.clear()  # a new state to converge from: its plateau is measured from here
            continue
        break
    if price.best is not None and price.best[0] > _penalised(Phi, Y, known, w, s, min_gain):
        w, s = price.best[1], price.best[2]
    return w, s, iterations


def _empty_floor(data: _Data, w: torch.Tensor, s: float) -> float:
    """The floor with no term left (F = 0): all of the targets' variance, or beside known noise the golden-section
    search's; ``s`` itself when the floor is fixed."""
    if not data.learn_floor:
        return s
    if data.homoscedastic:
        return max(data.second, data.s_min)
    return max(_golden_floor(data.Phi, data.Y, data.known, w, data.s_min, 10.0 * data.second), data.s_min)


def _output_sums(data: _Data, w: torch.Tensor, s: float, act: torch.Tensor) -> _Sums:
    """The sums over the outputs of one fixed-point iteration (:class:`_Sums`) at the weights ``w`` and floor ``s``,
    from each output's coefficient posterior over the active terms ``act``."""
    wa = w[act]
    num = torch.zeros_like(wa)
    gam_sum = torch.zeros_like(wa)
    dead = torch.ones_like(wa, dtype=torch.bool)
    resid, dof, var = 0.0, 0.0, None
    N = data.Phi.shape[0]
    for o in range(data.Y.shape[1]):
        if data.homoscedastic:
            G = data.G0[act][:, act] / s
            b = data.B0[act, o] / s
        else:
            d = data.known[:, o] + s
            P = data.Phi[:, act]
            G = P.T @ (P / d.unsqueeze(-1))
            b = P.T @ (data.Y[:, o] / d)
        try:
            Sigma, mu, _ = _posterior(G, b, wa)
        except torch.linalg.LinAlgError as exc:
            raise FittingError(f"the feature-kernel fit failed: the coefficient posterior is singular ({exc})") from exc
        gam = (1.0 - Sigma.diagonal() / wa).clamp(0.0, 1.0)
        num += mu.pow(2)
        gam_sum += gam
        dead &= mu.pow(2) <= gam * Sigma.diagonal()  # this output's best weight for the term is 0
        if data.homoscedastic:
            Ga = data.G0[act][:, act]
            r2 = float(data.yy[o] - 2.0 * mu @ data.B0[act, o] + mu @ Ga @ mu)
            resid += max(r2, 0.0)
            dof += N - float(gam.sum())
            var = Sigma.diagonal()
    return _Sums(num, gam_sum, dead, resid, dof, var)


def _fixed_point(data: _Data, w: torch.Tensor, s: float) -> tuple[torch.Tensor, float, float, bool]:
    """``(new weights, new floor, largest relative change, whether a term was removed)``: one fixed-point iteration
    (MacKay's update of the weights, the irrelevant terms removed at once, the floor's update where it is learned)."""
    act = w > 0
    sums = _output_sums(data, w, s, act)
    new = torch.zeros_like(w)
    new[act] = sums.num / sums.gam_sum.clamp_min(torch.finfo(w.dtype).tiny)
    if data.homoscedastic:
        # Tipping & Faul (2003): with the term left out of C, its sparsity and quality factors are
        # s_j = 1 / Sigma_jj - 1 / w_j and q_oj = mu_oj / Sigma_jj, and its evidence-optimal weight given the
        # others is exactly 0 iff sum_o q_oj^2 <= m s_j, i.e. sum_o mu_oj^2 <= m Sigma_jj gamma_j (no
        # cancellation, whatever the noise): such a term is removed at once instead of shrinking geometrically
        # over hundreds of fixed-point iterations
        irrelevant = torch.zeros_like(w, dtype=torch.bool)
        irrelevant[act] = sums.num <= sums.gam_sum * sums.var
        new[irrelevant] = 0.0
    else:
        # with known noise each output has its own factors: a term whose best weight is 0 for every output has
        # a shared best weight of 0 (each output's evidence falls as the weight grows), exactly so for one
        new[act.nonzero().flatten()[sums.dead]] = 0.0
    new[new * data.scale_phi < PRUNE * data.second] = 0.0
    new_s = s
    if data.learn_floor:
        if data.homoscedastic:
            new_s = max(sums.resid / max(sums.dof, 1.0), data.s_min)
        else:
            new_s = _golden_floor(data.Phi, data.Y, data.known, new, data.s_min, 10.0 * data.second)
    both = (new > 0) & (w > 0)
    change = float((new[both].log() - w[both].log()).abs().max()) if bool(both.any()) else 0.0
    change = max(change, abs(math.log(new_s / s)))
    return new, new_s, change, bool(((new == 0) & (w > 0)).any())


def _converged(data: _Data, change: float, history: list[float], w: torch.Tensor, s: float) -> bool:
    """Whether the iteration that moved the weights and floor by ``change`` (to ``w``, ``s``) has converged: the
    change below the tolerance (beside known noise with a learned floor, the golden-section search's resolution:
    the floor moves by it from one iteration to the next, and the weights with it), or there, the log evidence
    (appended to ``history``) on a plateau (module constants above)."""
    plateau = False
    if data.learn_floor and not data.homoscedastic:
        history.append(_evidence(data.Phi, data.Y, _noise(data.Phi, data.Y.shape[1], data.known, s), w))
        before, recent = history[:-_PLATEAU_ITERATIONS], history[-_PLATEAU_ITERATIONS:]
        plateau = bool(before) and max(recent) < max(before) + _PLATEAU_NATS
    tolerance = _TOLERANCE if data.homoscedastic or not data.learn_floor else _GOLDEN_RESOLUTION
    return change < tolerance or plateau


def _readmits(data: _Data, w: torch.Tensor, s: float, readmitted: torch.Tensor) -> bool:
    """Whether a removed term re-enters at plain relevance's converged state (:func:`_readd`, ``w`` changed in
    place): only without known noise and above :data:`_READD_NOISE` of the targets' second moment."""
    if not (data.homoscedastic and s >= _READD_NOISE * data.second):
        return False
    return _readd(w, s, data.G0, data.B0, data.Y.shape[1], data.scale_phi, data.second, readmitted)


def _noise(Phi: torch.Tensor, m: int, known: torch.Tensor | None, floor: float) -> torch.Tensor:
    """``(N, m)``: the samples' noise variances ``D = known + floor`` of ``m`` outputs (kept positive)."""
    D = torch.full((Phi.shape[0], m), floor, dtype=Phi.dtype, device=Phi.device) if known is None else known + floor
    return D.clamp_min(torch.finfo(Phi.dtype).tiny)


def _unit_information(Phi: torch.Tensor, D: torch.Tensor) -> torch.Tensor:
    """``(p,)``: each term's unit-information prior variance ``N m / sum_{n,o} phi_nj^2 / D_no`` over the ``N``
    samples and ``m`` outputs ``D (N, m)`` sharing it (module docstring: the slab of a kept term)."""
    information = (Phi.pow(2).unsqueeze(-1) / D.unsqueeze(1)).sum((0, 2))  # (p,)
    return D.numel() / information.clamp_min(torch.finfo(Phi.dtype).tiny)


def unit_information_weights(Phi: torch.Tensor, w: torch.Tensor, known: torch.Tensor | None, floor: float):
    """``(p,)``: the weights ``w`` with every kept term's (``w_j > 0``) raised to at least its unit-information prior
    (:func:`_unit_information`, ``D = known + floor``; module docstring: the slab of a kept term). Removed terms
    (``w_j = 0``) stay removed."""
    unit = _unit_information(Phi, _noise(Phi, 1 if known is None else known.shape[1], known, floor))
    return torch.where(w > 0, torch.maximum(w, unit), w)


def term_inclusion(Phi: torch.Tensor, Y: torch.Tensor, known: torch.Tensor | None, w: torch.Tensor, floor: float):
    """``(inclusion (p,), spread (m, p))``: every term's posterior probability of being present given the others,
    and each removed term's coefficient variance averaged over its presence (0 for kept terms), for outputs
    ``Y (N, m)`` sharing the weights ``w`` of the chosen subset (``w_j > 0``, with their unit-information slab;
    module docstring: which terms are present is uncertain too). Everything in ``p x p``: O(N p^2 + p^3) per
    output."""
    p, m = Phi.shape[1], Y.shape[1]
    kept = w > 0
    D = _noise(Phi, m, known, floor)
    u = _unit_information(Phi, D)  # (p,): the slab
    log_bf = torch.zeros(p, dtype=Phi.dtype, device=Phi.device)
    sparsity = []
    for o in range(m):
        P = Phi / D[:, o : o + 1]
        G = Phi.T @ P  # Phi^T D^-1 Phi
        b = P.T @ Y[:, o]
        S, Q = G.diagonal().clone(), b.clone()
        if bool(kept.any()):  # C^-1 = D^-1 - D^-1 Phi_k A^-1 Phi_k^T D^-1, A = W_k^-1 + Phi_k^T D^-1 Phi_k
            A = G[kept][:, kept] + torch.diag(1.0 / w[kept])
            L = cholesky(A, what="feature kernel: the coefficients' posterior precision")
            V = torch.linalg.solve_triangular(L, G[kept], upper=False)  # L^-1 Phi_k^T D^-1 Phi
            r = torch.linalg.solve_triangular(L, b[kept].unsqueeze(-1), upper=False).squeeze(-1)
            S = S - V.pow(2).sum(0)
            Q = Q - V.T @ r
        # a kept term's factors are those of the model without it (Tipping & Faul): s = S / a, q = Q / a with
        # a = 1 - w S (1 for a removed term), written so that a -> 0 (a term the data fix exactly) stays finite:
        # q^2 u / (1 + u s) = Q^2 u / (a (a + u S)), log(1 + u s) = log(a + u S) - log a
        a = torch.where(kept, 1.0 - w * S, torch.ones_like(S)).clamp_min(torch.finfo(Phi.dtype).tiny)
        S = S.clamp_min(0.0)
        log_bf += 0.5 * (Q.pow(2) * u / (a * (a + u * S)) - torch.log(a + u * S) + torch.log(a))
        sparsity.append(S)  # a removed term's s (a = 1)
    inclusion = torch.sigmoid(log_bf)
    spread = inclusion * u / (1.0 + u * torch.stack(sparsity))  # (m, p): p v, v the variance given presence
    return inclusion, torch.where(kept, torch.zeros_like(spread), spread)


def _penalised(Phi, Y, known, w, s: float, min_gain: float) -> float:
    """The log evidence less ``min_gain`` per kept term."""
    D = torch.full_like(Y, s) if known is None else known + s
    return _evidence(Phi, Y, D, w) - min_gain * int((w > 0).sum())


def _better(best, Phi, Y, known, w, s: float, min_gain: float):
    """``(score, w, s)`` of the better of ``best`` (or None) and this state, by :func:`_penalised`."""
    score = _penalised(Phi, Y, known, w, s, min_gain)
    return (score, w.clone(), s) if best is None or score > best[0] else best


def _factors(G: torch.Tensor, B: torch.Tensor, w: torch.Tensor):
    """Tipping & Faul's sparsity and quality factors of every term with that term left out of the covariance
    ``C = Phi W Phi^T + D`` of outputs sharing the noise ``D``, from ``G = Phi^T D^-1 Phi (p, p)`` and
    ``B = Phi^T D^-1 Y (p, m)``: ``S (p,)``, ``Q (p, m)``. With ``s_j = phi_j^T C^-1 phi_j = G_jj - G_ja Sigma G_aj``
    and ``q_j = B_j - G_ja Sigma B_a`` (``Sigma = (W_a^-1 + G_aa)^-1`` over the kept terms a), a kept term's are
    ``S_j = s_j / (1 - w_j s_j)``, ``Q_j = q_j / (1 - w_j s_j)`` (Sherman-Morrison), a removed one's ``s_j``,
    ``q_j``. O(p^3), never N."""
    act = w > 0
    S, Q = G.diagonal().clone(), B.clone()
    if bool(act.any()):
        Sigma, _, _ = _posterior(G[act][:, act], B[act, 0], w[act])
        Ga = G[:, act]
        S = S - ((Ga @ Sigma) * Ga).sum(-1)
        Q = Q - Ga @ (Sigma @ B[act])
        shrink = (1.0 - w * S).clamp_min(torch.finfo(w.dtype).tiny)
        S = torch.where(act, S / shrink, S)
        Q = torch.where(act.unsqueeze(-1), Q / shrink.unsqueeze(-1), Q)
    return S, Q


def noise_groups(D: torch.Tensor) -> list[list[int]]:
    """The output columns of noise variances ``D (N, m)`` that share one noise vector: all together when every
    column is the same (homoscedastic, or the same known noise), else one each."""
    return [list(range(D.shape[1]))] if bool((D == D[:, :1]).all()) else [[o] for o in range(D.shape[1])]


def _price_move(Phi, Y, known, w: torch.Tensor, s: float, min_gain: float, scale_phi, second: float) -> bool:
    """One move of sparse Bayesian learning with a price per term, at a converged state (in place on ``w``): of
    removing the kept term of least gain when that gain is at most ``min_gain`` and adding the removed term of most
    gain when it exceeds ``min_gain`` (at its best weight ``(theta - 1) / S``), the one that raises the log evidence
    less the price the most (Tipping & Faul 2003, one action at a time). Every move raises it, so the search ends.
    When the outputs' noise differs, a term's gain is bounded by the sum of each output's own best gain: removals
    use that bound (a term is never removed for a gain it could have), and no term is added; nor below
    :data:`_READD_NOISE` (nearly noiseless fits, whose residual correlations are round-off). Returns whether a move
    was made."""
    tiny = torch.finfo(w.dtype).tiny
    D = torch.full_like(Y, s) if known is None else known + s
    groups = noise_groups(D)
    gain = torch.zeros_like(w)
    for cols in groups:
        P = Phi / D[:, cols[0]].unsqueeze(-1)
        S, Q = _factors(Phi.T @ P, P.T @ Y[:, cols], w)
        theta = Q.pow(2).sum(-1) / (len(cols) * S).clamp_min(tiny)
        gain += term_gain(theta, len(cols))
    act = w > 0
    moves = []  # (rise of the penalised evidence, term, new weight)
    if bool(act.any()):
        j = int(torch.where(act, gain, torch.full_like(gain, math.inf)).argmin())
        if gain[j] <= min_gain:
            moves.append((min_gain - float(gain[j]), j, 0.0))
    # re-admission only with one noise group (theta and S are then that group's), judged by the noise with the
    # known part, not the floor alone
    if len(groups) == 1 and float(D.mean()) >= _READD_NOISE * second:
        weight = (theta - 1.0) / S.clamp_min(tiny)
        add = ~act & (S > 0) & (gain > min_gain + _MARGIN) & (weight * scale_phi >= PRUNE * second)
        if bool(add.any()):
            j = int(torch.where(add, gain, torch.full_like(gain, -math.inf)).argmax())
            moves.append((float(gain[j]) - min_gain, j, float(weight[j])))
    if not moves:
        return False
    _, j, value = max(moves)
    w[j] = value
    return True


def term_price(min_gain: float | None, n: int) -> float:
    """The price of a term in nats: ``min_gain`` when the user set one, else BIC's ``log(n) / 2`` for ``n``
    measurements (the Occam factor of the unit-information slab)."""
    return float(min_gain) if min_gain is not None else 0.5 * math.log(max(n, 2))


def term_gain(theta: torch.Tensor, m: int) -> torch.Tensor:
    """The log evidence a term adds at its evidence-optimal weight, ``m/2 (theta - 1 - log theta)`` for ``theta > 1``
    (0 otherwise), where ``theta = sum_o q_oj^2 / (m s_j)`` from its sparsity and quality factors (Tipping & Faul
    2003) over the ``m`` outputs sharing it: with ``1 + w s_j = theta`` at the optimum ``w = (theta - 1) / s_j``,
    ``sum_o [q_oj^2 w / (1 + w s_j) - log(1 + w s_j)] / 2`` is that value. A spike-and-slab prior that includes each
    term with probability pi keeps a term when this exceeds ``log((1 - pi) / pi)``."""
    t = theta.clamp_min(1.0)
    return 0.5 * m * (t - 1.0 - t.log())


def _readd(w: torch.Tensor, s: float, G0, B0, m: int, scale_phi, second: float, readmitted) -> bool:
    """Put back (in place) the removed terms whose evidence-optimal weight given the kept ones is positive:
    ``sum_o Q_oj^2 > m S_j`` (:func:`_factors` with the homoscedastic noise ``s``), at the weight
    ``w_j = (sum_o Q_oj^2 - m S_j) / (m S_j^2)`` (Tipping & Faul 2003), each term at most once per fit
    (``readmitted``, updated): with shared weights the removal test and this one can disagree near the boundary, and a
    term could otherwise cycle until the iteration cap. Returns whether any came back."""
    off = w == 0
    if not bool(off.any()):
        return False
    S, Q = _factors(G0 / s, B0 / s, w)
    S, Q = S[off], Q[off]
    q2 = Q.pow(2).sum(-1)
    back = (q2 > m * S) & (S > 0)
    weight = (q2 - m * S) / (m * S.pow(2)).clamp_min(torch.finfo(w.dtype).tiny)
    back &= (weight * scale_phi[off] >= PRUNE * second) & ~readmitted[off]
    if not bool(back.any()):
        return False
    idx = off.nonzero().flatten()[back]
    w[idx] = weight[back]
    readmitted[idx] = True
    return True


def _golden_floor(Phi, Y, known, w, lo: float, hi: float, steps: int = 40) -> float:
    """The noise floor in ``[lo, hi]`` maximising the evidence (golden-section search in log space)."""
    a, b = math.log(lo), math.log(hi)
    g = (math.sqrt(5) - 1) / 2

    def f(t):
        return _evidence(Phi, Y, known + math.exp(t), w)

    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(steps):
        if fc > fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return math.exp((a + b) / 2)
