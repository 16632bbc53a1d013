"""The covariance of candidates' whitened readings under F's GP (and G's uncertain parameters): what the readings'
criterion's engines (:mod:`._readings`) condition and take log-determinants of; the maths in :mod:`._readings` and
:mod:`._readings_theta`."""

from __future__ import annotations

import torch

from .._linalg import logdet_identity_plus
from ._common import GPKernel

__all__ = ["ReadingsCovariance"]


class ReadingsCovariance:
    """Covariances of the whitened readings of candidates, Sigma_ab = sum_o A_a^(o) k_o(X_a, X_b) A_b^(o)T, plus
    ``Bt_a Bt_b^T`` with G's uncertain parameters (``Bt (N, R, p)``: the readings' sensitivity to theta times the
    factor of its covariance, :mod:`._readings_theta`)."""

    def __init__(self, kern: GPKernel, A: torch.Tensor, nodes: torch.Tensor, d_out: int, Bt=None) -> None:
        self.kern, self.A, self.nodes, self.d_out, self.Bt = kern, A, nodes, d_out, Bt

    def theta_logdet(self, idx: list[int]) -> float:
        """``logdet(I + B_S Sigma_theta B_S^T)`` for the candidates ``idx`` (0 without uncertain parameters)."""
        if self.Bt is None or not idx:
            return 0.0
        Bt = self.Bt[torch.tensor(idx, dtype=torch.long, device=self.Bt.device)].reshape(-1, self.Bt.shape[-1])
        eye = torch.eye(Bt.shape[-1], dtype=Bt.dtype, device=Bt.device)
        return float(torch.logdet(eye + Bt.T @ Bt))

    def theta_gains(self, idx: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
        """``(b,)`` logdet(I + M + M_c) - logdet(I + M) for candidates ``idx``, ``M (p, p)`` the picks' sum of
        ``M_c = Bt_c^T Bt_c`` (zeros without uncertain parameters)."""
        if self.Bt is None:
            return torch.zeros(idx.shape[0], dtype=self.A.dtype, device=self.A.device)
        Bt = self.Bt[idx]
        eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
        return torch.logdet(eye + M + Bt.transpose(1, 2) @ Bt) - torch.logdet(eye + M)

    def _k(self, xa: torch.Tensor, xb: torch.Tensor) -> torch.Tensor:
        """``(d_out, ..., Sa, Sb)``: output o's (conditioned) covariance of F between the nodes ``xa`` and ``xb``. In
        the per-output layout the kernel's blocks are divided by each output's sample noise (GPKernel): undone."""
        kern = self.kern
        if not kern.expanded:
            return kern(xa, xb).unsqueeze(0).expand(self.d_out, *([-1] * (xa.dim() - 1)), xb.shape[-2])
        out = []
        for o in range(self.d_out):
            pa, pb = (torch.cat([x, torch.full_like(x[..., :1], float(o))], dim=-1) for x in (xa, xb))
            out.append(kern(pa, pb) * kern.scales[o])
        return torch.stack(out)

    def blocks(self, idx: torch.Tensor) -> torch.Tensor:
        """``(b, R, R)``: Sigma_cc of candidates ``idx``."""
        A = self.A[idx]
        K = self._k(self.nodes[idx], self.nodes[idx])  # (d_out, b, S, S)
        out = torch.einsum("croi,ocij,csoj->crs", A, K, A)
        return out if self.Bt is None else out + self.Bt[idx] @ self.Bt[idx].transpose(1, 2)

    def cross(self, n: int, idx: torch.Tensor) -> torch.Tensor:
        """``(R, b, R)``: Sigma_{n c} for candidates ``idx``."""
        b, S, d_in = idx.shape[0], self.nodes.shape[1], self.nodes.shape[2]
        K = self._k(self.nodes[n], self.nodes[idx].reshape(b * S, d_in)).reshape(self.d_out, S, b, S)
        out = torch.einsum("roi,oicj,csoj->rcs", self.A[n], K, self.A[idx])
        return out if self.Bt is None else out + torch.einsum("rp,csp->rcs", self.Bt[n], self.Bt[idx])

    def joint(self, idx: list[int]) -> torch.Tensor:
        """The covariance of the stacked readings of ``idx`` (the reference: one dense matrix)."""
        i = torch.tensor(idx, dtype=torch.long, device=self.A.device)
        S, d_in = self.nodes.shape[1], self.nodes.shape[2]
        A = self.A[i]  # (k, R, d_out, S)
        K = self._k(self.nodes[i].reshape(-1, d_in), self.nodes[i].reshape(-1, d_in))  # (d_out, k S, k S)
        K = K.reshape(self.d_out, len(idx), S, len(idx), S)
        out = torch.einsum("aroi,oaibj,bsoj->arbs", A, K, A).reshape(len(idx) * A.shape[1], -1)
        if self.Bt is None:
            return out
        Bt = self.Bt[i].reshape(-1, self.Bt.shape[-1])
        return out + Bt @ Bt.T

    def information(self, idx: list[int]) -> float:
        """The readings' information about F of the candidates ``idx`` (theta integrated out)."""
        if not idx:
            return 0.0
        ld, _ = logdet_identity_plus(self.joint(idx), 1.0, "I + Sigma_S (readings)")
        return 0.5 * (float(ld) - self.theta_logdet(idx))
