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
from dataclasses import dataclass

import gpytorch
import torch

from .._errors import InputError, ShapeError
from .._linalg import cholesky

#: Most samples for which a feature-space posterior builds its dense factor on request (3.2 GB in float64).
DENSE_LIMIT = 20_000


def check_dense(N: int) -> None:
    """Refuse an N x N training covariance above :data:`DENSE_LIMIT` samples (a model fitted in feature space on
    many samples), with what it would take."""
    if N > DENSE_LIMIT:
        raise InputError(
            f"this operation needs the dense N x N training covariance, expected at most {DENSE_LIMIT} samples for it, "
            f"got {N} ({8 * N * N / 2**30:.1f} GiB); fit on fewer samples for it"
        )


__all__ = [
    "check_dense",
    "FeatureKernel",
    "PRUNE",
    "Term",
    "monomial_names",
    "monomial_powers",
    "monomials",
    "FeatureFactorization",
    "coefficient_posterior",
]

#: Highest degree of the monomials of the feature-kernel candidate of :func:`~torchmisspec.fit_correction` (and
#: of the first model of partly measured data, :mod:`torchmisspec.learning.refinement.partial`).
FEATURE_DEGREE = 3

#: A term is removed when ``w_j mean(phi_j^2)`` (its share of the prior variance) falls below this fraction of the
#: targets' second moment.
PRUNE = 1e-12


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


def monomials(x: torch.Tensor, powers: torch.Tensor, tops=None) -> torch.Tensor:
    """``phi(x)``: ``(..., p)`` monomials of inputs ``(..., d_in)`` (differentiable in ``x``); ``tops``: each input's
    highest power, ``powers.max(0)`` as a list (given by kernels that call this at every solver step)."""
    tops = (powers.amax(0).tolist() if powers.numel() else [0] * powers.shape[1]) if tops is None else tops
    out = None
    for i, top in enumerate(tops):
        if top == 0:
            continue
        xi = x[..., i : i + 1]
        pw = [torch.ones_like(xi), xi]
        for _ in range(top - 1):
            pw.append(pw[-1] * xi)
        table = torch.cat(pw, dim=-1)[..., powers[:, i]]  # x_i to each term's power
        out = table if out is None else out * table
    return torch.ones((*x.shape[:-1], powers.shape[0]), dtype=x.dtype, device=x.device) if out is None else out


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
        self._tops = powers.amax(0).tolist() if powers.numel() else [0] * d_in  # monomials' highest powers
        self.register_parameter("weights", torch.nn.Parameter(torch.ones(*batch_shape, powers.shape[0])))
        #: each term's posterior probability of being present (:func:`term_inclusion`; 1 until a fit sets it)
        self.register_buffer("inclusion", torch.ones(*batch_shape, powers.shape[0]))
        #: the removed terms' coefficient variance averaged over their presence, ``p v`` (module docstring; 0 for
        #: kept terms and until a fit sets it), per output with ``per_output``: the draws' and bands' extra spread
        self.register_buffer("spread", torch.zeros(*batch_shape, powers.shape[0]))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        if self.library is None:
            return monomials(x, self.powers, self._tops)
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
    L = cholesky(A, what="diag(1 / w) + Phi^T D^-1 Phi (coefficient posterior)")
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


#: rows per block of the feature-space Gram matrix (its temporaries)
_ROWS = 16384


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
        # per batch, once: the active terms, sqrt(W_a) and chol(M) (P = Phi_a sqrt(W_a) enters only in products)
        self._factors = []
        means, covs, logdet = [], [], D.log().sum()
        for b in range(B):
            act = W[b] > 0
            mean, cov = Phi.new_zeros(p, m), Phi.new_zeros(p, p)
            factor = None
            if bool(act.any()):
                sw = W[b, act].sqrt()
                Pa = self._active(act)
                G = sum(  # Phi_a^T D^-1 Phi_a in blocks of rows: no N x q temporary beside Phi
                    Pa[r : r + _ROWS].T @ (Pa[r : r + _ROWS] / D[b, r : r + _ROWS].unsqueeze(-1))
                    for r in range(0, N, _ROWS)
                )
                M = torch.eye(sw.shape[0], dtype=Phi.dtype, device=Phi.device) + sw.unsqueeze(-1) * G * sw
                L = cholesky(M, what="I + P^T D^-1 P (feature-space posterior)")
                factor = (act, sw, L)  # P = Phi_a diag(sw) is never formed
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

    def _active(self, act: torch.Tensor) -> torch.Tensor:
        """``Phi_a``, the active terms' features (``Phi`` itself, not a copy, when every term is active)."""
        return self._Phi if bool(act.all()) else self._Phi[:, act]

    def _solve(self, V: torch.Tensor) -> tuple[torch.Tensor, list]:
        """``C^-1 V`` for ``V (B, N, k)`` and, per batch, ``g = M^-1 P^T D^-1 V`` (None without active terms)."""
        out, gs = [], []
        for b, factor in enumerate(self._factors):
            d = self._D[b].unsqueeze(-1)
            v, g = V[b] / d, None
            if factor is not None:
                act, sw, L = factor
                Pa = self._active(act)
                g = torch.cholesky_solve(sw.unsqueeze(-1) * (Pa.T @ v), L)
                v = _consistent(v - (Pa @ (sw.unsqueeze(-1) * g)) / d, Pa, g / sw.unsqueeze(-1))
            out.append(v)
            gs.append(g)
        return torch.stack(out), gs

    def sample_coefficients(self, S: int, scale: float, generator) -> torch.Tensor:
        """``(S, p, m)`` draws of the first batch's coefficients, ``mean + scale sqrt(W) L_M^-T e`` (covariance
        ``scale^2 cov``), e standard normal: posterior draws of F in feature space, without a solve with C."""
        mean = self.mean[0]
        beta = mean.unsqueeze(0).expand(S, -1, -1).clone()
        if self._factors[0] is not None:
            act, sw, L = self._factors[0]
            e = torch.randn((S, L.shape[0], mean.shape[-1]), generator=generator, dtype=mean.dtype, device=mean.device)
            beta[:, act] += scale * sw.unsqueeze(-1) * torch.linalg.solve_triangular(L.T.unsqueeze(0), e, upper=True)
        return beta

    def mean_error(self, Y: torch.Tensor) -> float:
        """The largest error of the posterior mean at the training inputs that the coefficients' solve leaves, to
        first order: ``max |P M^-1 r|`` with ``r = M g - P^T D^-1 y`` its residual. (:attr:`alpha` cannot show it:
        with tiny noise its Woodbury form cancels although the mean, computed from g, is accurate.)"""
        worst = 0.0
        for b, factor in enumerate(self._factors):
            if factor is None:
                continue
            act, sw, L = factor
            Pa = self._active(act)
            g = self.mean[b][act] / sw.unsqueeze(-1)
            r = L @ (L.T @ g) - sw.unsqueeze(-1) * (Pa.T @ (Y[b] / self._D[b].unsqueeze(-1)))
            worst = max(worst, float((Pa @ (sw.unsqueeze(-1) * torch.cholesky_solve(r, L))).abs().max()))
        return worst

    def solve(self, V: torch.Tensor) -> torch.Tensor:
        """``C^-1 V`` for ``V (B, N, k)`` (Woodbury, from the factors kept at construction)."""
        return self._solve(V)[0]

    def times(self, V: torch.Tensor) -> torch.Tensor:
        """``C V = Phi (W (Phi^T V)) + D V`` for ``V (B, N, k)``, without forming C (O(N p k))."""
        return self._Phi @ (self._W.unsqueeze(-1) * (self._Phi.T @ V)) + self._D.unsqueeze(-1) * V

    @property
    def chol(self) -> torch.Tensor:
        """The dense ``(B, N, N)`` Cholesky factor of C, built on first access (O(N^3)); refused above
        :data:`DENSE_LIMIT` samples (the paths that need it are for models of modest size)."""
        if self._chol is None:
            check_dense(self._Phi.shape[0])
            K = (self._Phi.unsqueeze(0) * self._W.unsqueeze(1)) @ self._Phi.T
            self._chol = cholesky(K + torch.diag_embed(self._D), what="K + noise (dense, on request)")
        return self._chol
