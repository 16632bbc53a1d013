"""The screening of lazy greedy: rigorous upper bounds on the marginal gains from a low-rank (Nystrom) feature
model of the kernel on every proxy point (see :class:`LowRank`); :mod:`torchmisspec.design._greedy` uses them to
evaluate exactly only the candidates that can still win, so the picks stay plain greedy's."""

from __future__ import annotations

import torch

from .._linalg import cholesky, pivots
from ._common import logdet_identity_plus

__all__ = ["LowRank", "SLACK_NATS", "SLACK_USELESS", "CHUNK_BYTES"]

SLACK_NATS = 1e-4  # target slack of the feature bounds at the last pick (sets the pivot tolerance)
SLACK_USELESS = 1e-2  # features whose predicted slack exceeds this many nats are not built
CHUNK_BYTES = 8 * 2**20  # size of the batched temporaries (small enough for the allocator to reuse them)


class LowRank:
    """Nystrom features of the kernel on all proxy points: cheap, rigorous upper bounds on the marginal gains.

    With pivots Z, phi(x) = L_Z^-1 k(Z, x) and the residual E = K - Phi Phi^T is positive semi-definite; e_max is its
    largest diagonal over all proxy points. The feature model's gain g~(c | S) (the same formula with Phi Phi^T in
    place of K) bounds the exact gain: det(I + X + Y) <= det(I + X) det(I + Y) for X, Y >= 0 and logdet(I + E / s2)
    <= tr(E) / s2 give logdet(I + K_A / s2) <= logdet(I + Phi_A Phi_A^T / s2) + |A| e_max / s2 for any point set A,
    and Phi Phi^T <= K gives the reverse without slack, so

        g(c | S) <= g~(c | S) + (d_out / 2) (|S| T + T) e_max / sigma^2.

    In feature space, Sigma~_{c|S} = Phi_c Lambda_S^-1 Phi_c^T with Lambda_S = I + Phi_S^T Phi_S / sigma^2 (r x r), so a
    bound costs one (T x r) triangular solve against chol(Lambda_S): about (KT / r)^2 times less than an exact gain.
    """

    def __init__(self, prob, max_rank: int, sample: int = 8192, chunk: int = 32768) -> None:
        """``prob``: the greedy's validated problem (its kernel, proxy points, budget, T and d_out)."""
        self.prob = prob
        kern, P = prob.kern, prob.points
        N, T, d_in = P.shape
        flat = P.reshape(N * T, d_in)
        gen = torch.Generator().manual_seed(0)  # a fixed subsample: the picks never depend on it, only the speed
        sub = flat if N * T <= sample else flat[torch.randperm(N * T, generator=gen)[:sample].to(P.device)]
        k0 = float(kern.diag(sub).max())
        # pivot tolerance: the bound slack stays around SLACK_NATS up to the last pick
        tol = max(SLACK_NATS * kern.noise / (0.5 * prob.d_out * (prob.budget + 1) * T), 1e-13 * k0)
        piv, e_sub = pivots(kern, sub, max_rank, tol)
        self.rank = r = piv.shape[0]
        # a rough kernel needs more features than max_rank allows: bounds that loose would only cost time
        self.useful = 0.5 * prob.d_out * prob.budget * T * e_sub / kern.noise <= SLACK_USELESS
        if not self.useful:
            return
        Z = sub[piv]
        LZ = cholesky(kern(Z), what="K(pivots)")
        phi = P.new_empty(N * T, r)
        e_max = 0.0
        for s in range(0, N * T, chunk):
            x = flat[s : s + chunk]
            Kzx, dx = kern.cross_and_diag(Z, x)
            f = torch.linalg.solve_triangular(LZ, Kzx, upper=False).T
            phi[s : s + chunk] = f
            e_max = max(e_max, float((dx - f.pow(2).sum(-1)).max()))
        # floating-point slack on the residual (its computed value can be off by a few ulps of k0)
        self.e_max = max(e_max, 0.0) + 64 * torch.finfo(P.dtype).eps * k0
        self.phi = phi.reshape(N, T, r)
        self.Lam = torch.eye(r, dtype=P.dtype, device=P.device)  # I + Phi_S^T Phi_S / sigma^2
        self.LLam = self.Lam.clone()

    def bounds(self, idx: torch.Tensor, m: int) -> torch.Tensor:
        """Upper bounds on the exact gains of candidates ``idx (b,)`` given the m selected proxy points."""
        prob = self.prob
        T, r = prob.T, self.rank
        chunk = max(1, CHUNK_BYTES // (8 * T * r))
        out = []
        for s in range(0, idx.shape[0], chunk):
            c = idx[s : s + chunk]
            X = torch.linalg.solve_triangular(self.LLam.T, self.phi[c].reshape(-1, r), upper=True, left=False).reshape(
                -1, T, r
            )  # Phi_c L^-T
            ld, _ = logdet_identity_plus(X @ X.transpose(1, 2), prob.kern.noise, "I + Sigma~_{c|S} / noise_variance")
            out.append(ld)
        g = 0.5 * prob.d_out * torch.cat(out)
        return g + self.slack(m) + 1e-10 * g.abs().clamp_min(1.0)  # + round-off allowance on g~

    def slack(self, m: int) -> float:
        """The bound's slack (nats) given m selected proxy points: (d_out / 2) (m + T) e_max / sigma^2."""
        return 0.5 * self.prob.d_out * (m + self.prob.T) * self.e_max / self.prob.kern.noise

    def add(self, n: int) -> None:
        f = self.phi[n]  # (T, r)
        self.Lam += f.T @ f / self.prob.kern.noise
        self.LLam = cholesky(self.Lam, what="I + Phi_S^T Phi_S / noise_variance")
