"""Feature kernels with automatic relevance: the Bayesian counterpart of sparse polynomial regression (SINDy).

``k(x, x') = sum_j w_j phi_j(x) phi_j(x')`` over a library of monomials ``phi_j(x) = x^a`` (``|a| <= degree``,
the constant included), one weight ``w_j >= 0`` per monomial (per output with ``per_output=True``). It is the
prior of ``F(x) = sum_j beta_j phi_j(x)`` with independent ``beta_j ~ N(0, w_j)``: a weight of 0 removes the term.

**Fitting by evidence in feature space** (sparse Bayesian learning: MacKay 1992, Tipping 2001). With the noise
covariance ``D`` (the learned floor plus any known per-sample noise), the posterior of the coefficients of one
output ``y`` is ``N(mu, Sigma)`` with

    Sigma = (W^-1 + Phi^T D^-1 Phi)^-1,    mu = Sigma Phi^T D^-1 y,

and the log evidence ``log N(y; 0, Phi W Phi^T + D)`` is, by the matrix determinant lemma and Woodbury,

    -1/2 (y^T D^-1 y - mu^T Phi^T D^-1 y) - 1/2 (log|W^-1 + Phi^T D^-1 Phi| + sum log w + sum log D) - N/2 log 2 pi.

MacKay's fixed-point update ``w_j <- sum_o mu_oj^2 / sum_o gamma_oj`` with ``gamma_oj = 1 - Sigma_o,jj / w_j`` (the
sum over the outputs sharing the weights) is a stationary point of the evidence in ``w_j``; the homoscedastic
noise is updated the same way, ``s <- sum_o ||y_o - Phi mu_o||^2 / sum_o (N - sum_j gamma_oj)``, and a floor
beside known noise by a golden-section search of the evidence. Weights of terms the data do not support shrink
to 0 geometrically and are removed (set to exactly 0) once their contribution falls below :data:`PRUNE` of the
targets' second moment. Every step works with ``p x p`` matrices: O(N p^2 + p^3) per iteration, never O(N^3).

**A price per term.** Plain automatic relevance keeps every term whose evidence-optimal weight is positive, however
little evidence it adds; with noisy samples that leaves weak spurious terms. With ``min_gain`` > 0 a term stays only
while the log evidence it adds at its best weight, :func:`term_gain` (closed form from Tipping & Faul's sparsity and
quality factors), exceeds ``min_gain``. The price acts only at converged states, starting from plain relevance's
final one (so the result is never worse than it by evidence less price), one move at a time (Tipping & Faul's one
action per step): the kept term of least gain leaves if its gain is at most the price, or the removed term of
most gain comes back if its gain exceeds it, whichever raises the evidence less the price more; then the weights
converge again. Removing several terms at once would be wrong: collinear terms each look redundant given the others.
Every move raises the evidence less the price, so the search ends, and the best converged state is kept. This is a
spike-and-slab prior with inclusion odds ``exp(-min_gain)``; :class:`~torchmisspec.CorrectionGP` uses BIC's
``log(N) / 2`` per learned weight by default.

**The slab of a kept term.** MacKay's evidence-optimal weight of a kept term is about its coefficient squared,
``w_j ~ mu_j^2 / gamma_j``: a prior as narrow as the coefficient, which shrinks the posterior mean toward 0 by a
factor ``1 / (1 + 1/SNR_j)`` (``SNR_j = mu_j^2 / v_j``, ``v_j`` the coefficient's least-squares variance). On a term
the data measure only moderately that bias is the whole error: on paper_linear with 20 random experiments, the
coefficient 0.01 of y2^2 measured at SNR 19 came out 0.00949 where least squares (and SINDy) gave 0.01009, twice
SINDy's integrated error (issue 27). Once the price has decided *which* terms are present, the slab of each kept
term is therefore widened to the unit-information prior (Kass & Wasserman 1995), the prior carrying one
observation's worth of information, ``w_j = N / sum_n phi_nj^2 / D_n`` (the prior under which BIC's ``log(N) / 2``
is the log Bayes factor of the term): the kept terms' posterior is least squares' within ``N / (N + 1)``, and a
weight already wider is left as it is (:func:`unit_information_weights`).

**Which terms are present is uncertain too** (:func:`term_inclusion`). The price chooses one subset of terms, the
most probable one; a term it removed may still be present. Under the spike-and-slab prior with the
unit-information slab (whose Occam factor is BIC's price, so prior odds 1:1), each term's posterior probability of
being present given the others is ``sigmoid(log BF_j)``, with the Bayes factor in closed form from its sparsity and
quality factors ``s_oj, q_oj`` (Tipping & Faul 2003; for a kept term those of the model without it),

    log BF_j = sum_o [ q_oj^2 u_j / (1 + u_j s_oj) - log(1 + u_j s_oj) ] / 2,   u_j its unit-information weight.

It is reported per term (``Term.inclusion``, :attr:`FeatureKernel.inclusion`), and it widens the bands: averaged
over the two cases, a removed term's coefficient (given the kept ones) has variance ``p_j v_oj`` within the case
where it is present (``v = u / (1 + u s)``, its posterior variance then). The posterior draws of F add
``sum_j e_j phi_j(x)`` with independent ``e_oj ~ N(0, p_j v_oj)`` over the removed terms, and the posterior variance
``sum_j p_j v_oj phi_j(x)^2`` (:attr:`FeatureKernel.spread`); the mean stays the chosen subset's. This leaves out the
shift of the mean by ``p_j m_oj`` and the between-case variance ``p_j (1 - p_j) m_oj^2``, both small where ``p_j``
is (a term the price removed), and the correlation with the kept terms. Measured (issue 27) before settling on it:
putting the removed terms back into the kernel with the Gaussian weights that give each, alone, the averaged mean
``p m`` and variance ``p v`` raised the uncalibrated feature bands' coverage on paper_linear from 0.36 to 0.78
(K = 5), but all removed terms at once pull the correlated kept ones, and the mean's error against SINDy's rose at
K = 20 from 0.94 to 1.17 (one realization 3.2x). The design criteria use the chosen subset's covariance.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import gpytorch
import torch

from .._errors import FittingError, InputError, ShapeError
from .._linalg import cholesky

__all__ = [
    "FeatureKernel",
    "PRUNE",
    "Term",
    "monomial_names",
    "monomial_powers",
    "monomials",
    "term_inclusion",
    "unit_information_weights",
]

#: A term is removed when ``w_j mean(phi_j^2)`` (its share of the prior variance) falls below this fraction of the
#: targets' second moment.
PRUNE = 1e-12
#: Relative change of the log weights (and noise) below which the fixed-point iteration has converged.
_TOLERANCE = 1e-9
#: Removed terms are tested for re-entry only above this noise (a fraction of the targets' second moment): below it
#: the test's residual correlations are round-off, and nearly noiseless fits keep every term they need anyway.
_READD_NOISE = 1e-8
#: Relative changes below this count as converged beside known noise with a learned floor: the golden-section search
#: (:func:`_golden_floor`, 40 steps over a bracket of about 30 in log space) resolves the floor to about 1e-7.
_GOLDEN_RESOLUTION = 1e-6
#: A removed term is added back only when its gain exceeds the price by this many nats (no move back and forth on a
#: tie).
_MARGIN = 1e-6
#: The learned noise floor is kept above this fraction of the targets' second moment (noiseless data stay solvable).
_MIN_NOISE = 1e-12


def monomial_powers(d_in: int, degree: int, *, device=None) -> torch.Tensor:
    """``(p, d_in)`` exponents of the monomials of total degree ``0 .. degree``, by degree, then lexicographically
    (``1, x1, x2, x1^2, x1 x2, x2^2, ...``)."""
    rows = []
    for k in range(degree + 1):
        for combo in itertools.combinations_with_replacement(range(d_in), k):
            a = [0] * d_in
            for i in combo:
                a[i] += 1
            rows.append(a)
    return torch.tensor(rows, dtype=torch.long, device=device)


def monomials(x: torch.Tensor, powers: torch.Tensor) -> torch.Tensor:
    """``phi(x)``: ``(..., p)`` monomials of inputs ``(..., d_in)`` (differentiable in ``x``)."""
    out = torch.ones((*x.shape[:-1], powers.shape[0]), dtype=x.dtype, device=x.device)
    for i in range(powers.shape[1]):
        top = int(powers[:, i].max()) if powers.numel() else 0
        if top == 0:
            continue
        xi = x[..., i : i + 1]
        pw = [torch.ones_like(xi)]
        for _ in range(top):
            pw.append(pw[-1] * xi)
        table = torch.cat(pw, dim=-1)  # (..., top + 1): x_i^0 .. x_i^top
        out = out * table[..., powers[:, i]]
    return out


def monomial_names(powers: torch.Tensor, names=None) -> list[str]:
    """Readable names of the monomials, e.g. ``"1"``, ``"y1"``, ``"y1^2 y2"``; ``names``: one per input."""
    d_in = powers.shape[1]
    names = [f"x{i + 1}" for i in range(d_in)] if names is None else list(names)
    out = []
    for a in powers.tolist():
        parts = [n if e == 1 else f"{n}^{e}" for n, e in zip(names, a, strict=True) if e > 0]
        out.append(" ".join(parts) if parts else "1")
    return out


def check_library(library, library_names=None) -> tuple[tuple, tuple[str, ...]]:
    """A user feature library: a non-empty sequence of callables (and as many distinct names, default f1, f2, ...)."""
    if isinstance(library, (str, bytes)) or not hasattr(library, "__iter__"):
        kind = type(library).__name__
        raise InputError(f"library: expected a sequence of callables x (..., d_in) -> (...,), got {kind}")
    library = tuple(library)
    if not library:
        raise InputError("library: expected at least one feature, got an empty sequence")
    bad = [i for i, f in enumerate(library) if not callable(f)]
    if bad:
        raise InputError(
            f"library: expected callables x (..., d_in) -> (...,), got {type(library[bad[0]]).__name__} at {bad}"
        )
    names = tuple(f"f{i + 1}" for i in range(len(library))) if library_names is None else tuple(library_names)
    if len(names) != len(library) or len(set(names)) != len(names) or not all(isinstance(n, str) for n in names):
        raise InputError(
            f"library_names: expected {len(library)} distinct strings (one per feature), got {library_names!r}"
        )
    return library, names


def library_features(library, x: torch.Tensor, names) -> torch.Tensor:
    """``(..., p)``: the library's features at ``x (..., d_in)``, each checked for its shape and finiteness."""
    out = []
    for f, name in zip(library, names, strict=True):
        v = f(x)
        if not isinstance(v, torch.Tensor) or v.shape != x.shape[:-1]:
            shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
            raise ShapeError(
                f"library: feature {name!r} must map inputs {tuple(x.shape)} to {tuple(x.shape[:-1])}, got {shape}"
            )
        if not bool(torch.isfinite(v).all()):
            count = x.shape[:-1].numel()
            raise InputError(f"library: feature {name!r} returned NaN or inf at some of the {count} inputs")
        out.append(v.to(x.dtype))
    return torch.stack(out, -1)


class FeatureKernel(gpytorch.kernels.Kernel):
    """``k(x, x') = sum_j w_j x^a_j x'^a_j`` over the monomials up to ``degree`` of ``d_in`` inputs.

    ``weights``: ``(*batch_shape, p)`` non-negative prior variances of the terms' coefficients (a plain parameter,
    not constrained: a weight of exactly 0 removes its term; it is fitted by :func:`fit_relevance`, not by
    gradients). ``powers``: ``(p, d_in)`` exponents (a buffer).
    """

    is_stationary = False

    def __init__(
        self,
        d_in: int,
        degree: int,
        batch_shape: torch.Size | None = None,
        library: tuple | None = None,
        library_names: tuple[str, ...] | None = None,
        **kwargs,
    ) -> None:
        batch_shape = torch.Size([]) if batch_shape is None else batch_shape
        super().__init__(batch_shape=batch_shape, **kwargs)
        #: user features (callables ``x (..., d_in) -> (...,)``) replacing the monomials, or None
        self.library = library
        self.library_names = library_names
        powers = monomial_powers(d_in, degree) if library is None else torch.zeros(len(library), d_in, dtype=torch.long)
        self.register_buffer("powers", powers)
        self.register_parameter("weights", torch.nn.Parameter(torch.ones(*batch_shape, powers.shape[0])))
        #: each term's posterior probability of being present (:func:`term_inclusion`; 1 until a fit sets it)
        self.register_buffer("inclusion", torch.ones(*batch_shape, powers.shape[0]))
        #: the removed terms' coefficient variance averaged over their presence, ``p v`` (module docstring; 0 for
        #: kept terms and until a fit sets it), per output with ``per_output``: the draws' and bands' extra spread
        self.register_buffer("spread", torch.zeros(*batch_shape, powers.shape[0]))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        if self.library is None:
            return monomials(x, self.powers)
        return library_features(self.library, x, self.library_names)

    def names(self, input_names=None) -> list[str]:
        """Readable names of the features: the monomials', or the library's."""
        if self.library is None:
            return monomial_names(self.powers, input_names)
        return list(self.library_names)

    def forward(self, x1, x2, diag: bool = False, last_dim_is_batch: bool = False, **params):
        if last_dim_is_batch:
            raise NotImplementedError("FeatureKernel: last_dim_is_batch is not supported")
        p1 = self.features(x1)
        w = self.weights.unsqueeze(-2)  # (*batch, 1, p)
        if diag:
            p2 = self.features(x2)
            return (p1 * w * p2).sum(-1)
        p2 = p1 if x2 is x1 else self.features(x2)
        return (p1 * w) @ p2.transpose(-1, -2)


@dataclass(frozen=True)
class Term:
    """One learned term of a feature kernel: ``mean +- std * name`` on output ``output``.

    Attributes:
        output: index of the output (0-based).
        name: the monomial, e.g. ``"y1^2"``.
        mean: posterior mean of its coefficient.
        std: posterior standard deviation of its coefficient.
        weight: its learned prior variance ``w_j`` (0: removed).
        inclusion: its posterior probability of being present given the other terms (module docstring; 1 where no
            fit with a price estimated it).
    """

    output: int
    name: str
    mean: float
    std: float
    weight: float
    inclusion: float = 1.0

    def __str__(self) -> str:
        return f"{self.mean:+.4g} +- {self.std:.2g} * {self.name}"


def _posterior(G: torch.Tensor, b: torch.Tensor, w: torch.Tensor):
    """Coefficient posterior over the active terms: ``Sigma (q, q)``, ``mu (q,)``, ``logdet A`` for
    ``A = diag(1 / w) + G`` (``G = Phi^T D^-1 Phi``, ``b = Phi^T D^-1 y``)."""
    A = G + torch.diag(1.0 / w)
    L = torch.linalg.cholesky(A)
    Sigma = torch.cholesky_inverse(L)
    mu = torch.cholesky_solve(b.unsqueeze(-1), L).squeeze(-1)
    return Sigma, mu, 2.0 * L.diagonal().log().sum()


def coefficient_posterior(Phi: torch.Tensor, y: torch.Tensor, D: torch.Tensor, w: torch.Tensor):
    """Posterior mean ``(p,)`` and standard deviation ``(p,)`` of the coefficients of one output (0 for removed
    terms), given features ``Phi (N, p)``, targets ``y (N,)``, noise variances ``D (N,)`` and weights ``w (p,)``."""
    mean = torch.zeros_like(w)
    std = torch.zeros_like(w)
    act = w > 0
    if bool(act.any()):
        P = Phi[:, act]
        Sigma, mu, _ = _posterior(P.T @ (P / D.unsqueeze(-1)), P.T @ (y / D), w[act])
        mean[act] = mu
        std[act] = Sigma.diagonal().clamp_min(0).sqrt()
    return mean, std


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
    N, p = Phi.shape
    m = Y.shape[1]
    second = float(Y.pow(2).mean())
    if not second > 0:
        raise FittingError(
            "targets: expected some non-zero samples to learn the feature weights from, got all zeros (every "
            "weight would be 0)"
        )
    scale_phi = Phi.pow(2).mean(0).clamp_min(torch.finfo(Phi.dtype).tiny)  # (p,)
    w = second / (p * scale_phi)
    learn_floor = floor is None
    s = 0.1 * second if learn_floor else float(floor)
    s_min = _MIN_NOISE * second
    homoscedastic = known is None
    if homoscedastic:  # sufficient statistics: every iteration is O(p^3)
        G0 = Phi.T @ Phi
        B0 = Phi.T @ Y  # (p, m)
        yy = Y.pow(2).sum(0)  # (m,)
    iterations = 0
    readmitted = torch.zeros_like(w, dtype=torch.bool)  # each term re-enters at most once: no remove/re-admit cycle
    best, moves = None, 0  # with a price: the best converged state by evidence less price, and the moves made
    plain_done = False  # plain relevance has converged (its re-admissions done)

    def price_step() -> bool:
        """At a converged state (w, s): keep it if it is the best so far, then one move of the price."""
        nonlocal best, moves
        best = _better(best, Phi, Y, known, w, s, min_gain)
        if moves < 4 * p and _price_move(Phi, Y, known, w, s, min_gain, scale_phi, second):
            moves += 1
            return True
        return False

    for iterations in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        act = w > 0
        if not bool(act.any()):  # no term left: F = 0, and the noise is all of the targets' variance
            if learn_floor:
                s = max(second if homoscedastic else _golden_floor(Phi, Y, known, w, s_min, 10.0 * second), s_min)
            if min_gain > 0 and price_step():  # a converged state too: a term may still be worth its price
                continue
            break
        wa = w[act]
        num = torch.zeros_like(wa)
        gam_sum = torch.zeros_like(wa)
        dead = torch.ones_like(wa, dtype=torch.bool)
        resid, dof = 0.0, 0.0
        for o in range(m):
            if homoscedastic:
                G = G0[act][:, act] / s
                b = B0[act, o] / s
            else:
                d = known[:, o] + s
                P = Phi[:, act]
                G = P.T @ (P / d.unsqueeze(-1))
                b = P.T @ (Y[:, o] / d)
            try:
                Sigma, mu, _ = _posterior(G, b, wa)
            except torch.linalg.LinAlgError as exc:
                raise FittingError(
                    f"the feature-kernel fit failed: the coefficient posterior is singular ({exc})"
                ) from exc
            gam = (1.0 - Sigma.diagonal() / wa).clamp(0.0, 1.0)
            num += mu.pow(2)
            gam_sum += gam
            dead &= mu.pow(2) <= gam * Sigma.diagonal()  # this output's best weight for the term is 0
            if homoscedastic:
                Ga = G0[act][:, act]
                r2 = float(yy[o] - 2.0 * mu @ B0[act, o] + mu @ Ga @ mu)
                resid += max(r2, 0.0)
                dof += N - float(gam.sum())
                var = Sigma.diagonal()
        new = torch.zeros_like(w)
        new[act] = num / gam_sum.clamp_min(torch.finfo(w.dtype).tiny)
        if homoscedastic:
            # Tipping & Faul (2003): with the term left out of C, its sparsity and quality factors are
            # s_j = 1 / Sigma_jj - 1 / w_j and q_oj = mu_oj / Sigma_jj, and its evidence-optimal weight given the
            # others is exactly 0 iff sum_o q_oj^2 <= m s_j, i.e. sum_o mu_oj^2 <= m Sigma_jj gamma_j (no
            # cancellation, whatever the noise): such a term is removed at once instead of shrinking geometrically
            # over hundreds of fixed-point iterations
            irrelevant = torch.zeros_like(w, dtype=torch.bool)
            irrelevant[act] = num <= gam_sum * var
            new[irrelevant] = 0.0
        else:
            # with known noise each output has its own factors: a term whose best weight is 0 for every output has
            # a shared best weight of 0 (each output's evidence falls as the weight grows), exactly so for one
            new[act.nonzero().flatten()[dead]] = 0.0
        new[new * scale_phi < PRUNE * second] = 0.0
        new_s = s
        if learn_floor:
            if homoscedastic:
                new_s = max(resid / max(dof, 1.0), s_min)
            else:
                new_s = _golden_floor(Phi, Y, known, new, s_min, 10.0 * second)
        both = (new > 0) & (w > 0)
        change = float((new[both].log() - w[both].log()).abs().max()) if bool(both.any()) else 0.0
        change = max(change, abs(math.log(new_s / s)))
        pruned = bool(((new == 0) & (w > 0)).any())
        w, s = new, new_s
        # beside known noise the golden-section floor moves by its resolution from one iteration to the next, and
        # the weights with it: converged at that resolution
        if change < (_TOLERANCE if homoscedastic or not learn_floor else _GOLDEN_RESOLUTION) and not pruned:
            if not plain_done:  # plain relevance first: its converged state is where the price starts from
                if (
                    homoscedastic
                    and s >= _READD_NOISE * second
                    and _readd(w, s, G0, B0, m, scale_phi, second, readmitted)
                ):
                    continue  # a removed term is relevant given the final others: back in, iterate again
                plain_done = True
            if min_gain > 0 and price_step():
                continue
            break
    if best is not None and best[0] > _penalised(Phi, Y, known, w, s, min_gain):
        w, s = best[1], best[2]
    return w, s, iterations


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


def _consistent(alpha: torch.Tensor, Phi: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``alpha`` moved least in norm so that ``Phi^T alpha = target`` holds (``Phi (N, q)``, ``target (q, k)``).

    Woodbury's ``C^-1 y = D^-1 (y - P g)`` subtracts two terms of size |y| / D: with nearly noiseless samples the
    rounding, amplified by 1 / D, ruins ``alpha``, while every use of it goes through ``k(x, X) alpha =
    phi(x)^T W Phi^T alpha`` and the exact solution satisfies ``Phi_a^T alpha = M^-1 P^T D^-1 y / sqrt(W_a)``, which
    the small q x q system gives accurately. Enforcing that identity keeps those products as accurate as the
    coefficients' posterior mean."""
    G = Phi.T @ Phi
    try:
        return alpha + Phi @ torch.linalg.solve(G, target - Phi.T @ alpha)
    except torch.linalg.LinAlgError:  # linearly dependent active features: keep the plain Woodbury value
        return alpha


class FeatureFactorization:
    """The posterior of a feature kernel in feature space: ``C = Phi W Phi^T + diag(D)`` is never formed.

    With the active terms' scaled features ``P = Phi_a sqrt(W_a)`` (``q`` of them) and ``M = I + P^T D^-1 P`` (q x q),
    Woodbury gives ``C^-1 v = D^-1 v - D^-1 P M^-1 P^T D^-1 v`` and ``logdet C = sum log D + logdet M``, and the
    posterior of the coefficients is ``N(mean, cov)`` with ``cov = sqrt(W) M^-1 sqrt(W)`` and
    ``mean = sqrt(W) M^-1 P^T D^-1 y``: the posterior mean at x is ``phi(x)^T mean = k(x, X) alpha`` and the posterior
    variance ``phi(x)^T cov phi(x)``. Cost O(N q^2 + q^3) per batch instead of O(N^3), memory O(N q).

    The attributes of :class:`~torchmisspec.gp._mll.Factorization` are provided (``alpha``, ``logdet``, ``quad``),
    and ``chol`` (the ``(B, N, N)`` Cholesky factor of C) is built on first access only, for the few paths that need
    the dense factor.

    Args:
        Phi: ``(N, p)`` features of the training inputs.
        W: ``(B or 1, p)`` effective weights (the output scale included; 0 removes a term).
        D: ``(B or 1, N)`` or ``(B or 1, 1)`` noise variances.
        Y: ``(B, N, m)`` targets, batched as for the dense factorization.
    """

    def __init__(self, Phi: torch.Tensor, W: torch.Tensor, D: torch.Tensor, Y: torch.Tensor) -> None:
        B, N, m = Y.shape
        p = Phi.shape[1]
        W = W.expand(B, p)
        D = D.expand(B, N)
        self._Phi, self._W, self._D = Phi, W, D
        # per batch, once: the active terms, sqrt(W_a), P = Phi_a sqrt(W_a) and chol(M); every solve reuses them
        self._factors = []
        means, covs, logdet = [], [], D.log().sum()
        for b in range(B):
            act = W[b] > 0
            mean, cov = Phi.new_zeros(p, m), Phi.new_zeros(p, p)
            factor = None
            if bool(act.any()):
                sw = W[b, act].sqrt()
                P = Phi[:, act] * sw
                M = torch.eye(P.shape[1], dtype=P.dtype, device=P.device) + P.T @ (P / D[b].unsqueeze(-1))
                L = cholesky(M, what="I + P^T D^-1 P (feature-space posterior)")
                factor = (act, sw, P, L)
                logdet = logdet + 2.0 * L.diagonal().log().sum()
                idx = act.nonzero().flatten()
                cov[idx.unsqueeze(-1), idx] = sw.unsqueeze(-1) * torch.cholesky_inverse(L) * sw
            self._factors.append(factor)
            covs.append(cov)
            means.append(mean)
        self.alpha, g = self._solve(Y)  # (B, N, m)
        for b, factor in enumerate(self._factors):
            if factor is not None:
                means[b][factor[0]] = factor[1].unsqueeze(-1) * g[b]
        self.logdet = logdet
        self.quad = (Y * self.alpha).sum()
        #: ``(B, p, m)`` posterior means and ``(B, p, p)`` covariances of the coefficients
        self.mean = torch.stack(means)
        self.cov = torch.stack(covs)
        self._chol = None

    def _solve(self, V: torch.Tensor) -> tuple[torch.Tensor, list]:
        """``C^-1 V`` for ``V (B, N, k)`` and, per batch, ``g = M^-1 P^T D^-1 V`` (None without active terms)."""
        out, gs = [], []
        for b, factor in enumerate(self._factors):
            d = self._D[b].unsqueeze(-1)
            v, g = V[b] / d, None
            if factor is not None:
                act, sw, P, L = factor
                g = torch.cholesky_solve(P.T @ v, L)
                v = _consistent(v - (P / d) @ g, self._Phi[:, act], g / sw.unsqueeze(-1))
            out.append(v)
            gs.append(g)
        return torch.stack(out), gs

    def solve(self, V: torch.Tensor) -> torch.Tensor:
        """``C^-1 V`` for ``V (B, N, k)`` (Woodbury, from the factors kept at construction)."""
        return self._solve(V)[0]

    @property
    def chol(self) -> torch.Tensor:
        """The dense ``(B, N, N)`` Cholesky factor of C, built on first access (O(N^3))."""
        if self._chol is None:
            K = (self._Phi.unsqueeze(0) * self._W.unsqueeze(1)) @ self._Phi.T
            self._chol = cholesky(K + torch.diag_embed(self._D), what="K + noise (dense, on request)")
        return self._chol
