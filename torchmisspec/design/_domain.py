"""The domain criterion: how much the samples lower the posterior variance of F averaged over the domain D.

The paper's criterion, the information about F anywhere, prefers samples far apart: the corners of a grid, whose
trajectories may leave D. A scientist who wants F on D needs the *integrated posterior variance* over D lowered:

    V(S) = d_out * sum_q w_q [ var(F(q) | data) - var(F(q) | data, y_S) ],     sum_q w_q = 1,

with q the nodes of a ``domain_size``-per-axis grid over D and w_q its trapezoid weights (so V is the mean over D of
the variance removed, summed over the d_out outputs; units of F squared). It is the expected decrease of the mean
squared error of the posterior mean over D when F is drawn from the GP, the quantity the error-vs-K studies measure.

The model. F on D is represented exactly by its values at pivot nodes Z (a pivoted Cholesky of K_QQ stops once F at
Z determines F at every node to 1e-8 of the prior variance): phi(x) = L_Z^-1 k(Z, x), F(x) = phi(x)^T w + f_r(x),
w ~ N(0, I). The residual f_r, zero on the nodes and tiny inside D, is treated as independent noise of variance
r(x) = k(x, x) - |phi(x)|^2 at each sample (the FITC approximation, Snelson & Ghahramani 2006); it matters only for
samples outside D, which it correctly discounts. Then, with Psi_c = phi(P_c) / sqrt(sigma^2 + r) the whitened
features of candidate c's T samples, A = I + sum over the data and the picks of Psi^T Psi (r x r), and
W = sum_q w_q phi(q) phi(q)^T,

    V(S) = d_out * [tr(W A_data^-1) - tr(W A_S^-1)],
    gain(c | S) = d_out * tr((I + B_c Psi_c^T)^-1 B_c W B_c^T),     B_c = Psi_c A_S^-1     (Woodbury).

Guarantee, honestly: V is monotone but **not submodular** in general (variance reduction is submodular only without
"suppressor" variables, Das & Kempe 2008), so greedy has no (1 - 1/e) guarantee for it; Das & Kempe (2011) bound
greedy by 1 - exp(-gamma) with gamma the submodularity ratio, which is not computed here. For the same reason lazy
greedy's stale bounds are not valid: ``method="lazy"`` runs the exact vectorised engine (every remaining gain at
every pick), so lazy = plain by construction, and ``"naive"`` recomputes V(S + c) from scratch as the reference.
The cost per pick is O(N T^2 r) with rank-T updates of B (r: the number of pivot nodes, reported as
``diagnostics["domain_rank"]``), memory 16 N T r bytes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .._errors import InputError, ShapeError
from .._linalg import cholesky, pivots
from .._validation import as_tensor, check_domain, check_finite, check_ndim, check_positive_int, progress_bar
from ..metrics import box_grid
from ._common import GPKernel, check_system

CRITERIA = ("information", "domain")  # the paper's criterion, or the variance of F over the domain D
DOMAIN_NODES = 1024  # default most quadrature nodes
PIVOT_TOL = 1e-8  # pivot nodes until F at them fixes F at every node to this fraction of the prior variance
MEMORY = 2 * 2**30  # bytes the engine may hold (B and B W for every candidate)


@dataclass(frozen=True)
class DomainCriterion:
    """The criterion that aims the design at a box D of F's inputs: the mean posterior variance of F over D that
    the samples remove (:func:`~torchmisspec.design.variance_reduction`; gains in units of F squared, not nats).

    Not submodular in general: no (1 - 1/e) guarantee, and lazy greedy evaluates every remaining gain. The string
    ``criterion="domain"`` is this criterion with its defaults. See :mod:`torchmisspec.design._domain`.

    Attributes:
        domain: the box D, one ``(lo, hi)`` per correction input (default ``system.domain``).
        size: quadrature nodes per axis (default: at most 1024 nodes in all, at least 2 per axis).
    """

    domain: Any = None
    size: int | None = None

    def __post_init__(self) -> None:
        if self.size is not None:
            check_positive_int(self.size, "DomainCriterion.size")


class DomainModel:
    """Features of F on the domain D, the data's precision in feature space, and the quadrature matrix W."""

    def __init__(self, kern: GPKernel, system, domain=None, domain_size: int | None = None) -> None:
        d_in = system.input_dim
        if kern.expanded and kern.gp.output_dim == 1:
            raise InputError(
                "gp: criterion='domain' is not built for a GP kept per output, as a fit through the ODE (partly "
                "measured states, readings) returns one, even with one output; use criterion='information' (for "
                "readings: design.ReadoutCriterion(readout) without domain=)"
            )
        if kern.expanded:
            raise InputError(
                "gp: criterion='domain' weighs the variance of F over D in F's units and needs one kernel and one "
                "noise for all outputs; this GP has per-output kernels or per-output noise. Use "
                "criterion='information' (it conditions each output on its own data), or fit a shared GP "
                "(CorrectionGP(per_output=False)) on samples with the same noise for every output "
                "(samples.with_shared_noise())"
            )
        if domain is None:
            domain = system.domain
            if domain is None:
                raise InputError(
                    f"domain: criterion='domain' needs the domain D; system '{system.name}' has none, pass "
                    f"domain=((lo, hi), ...) with one (lo, hi) per correction input ({d_in})"
                )
        self.box = check_domain(domain, "domain (one (lo, hi) per correction input)", dim=d_in)
        if domain_size is None:  # at most DOMAIN_NODES in all up to 10 inputs (2 per axis beyond)
            domain_size = max(2, min(33, int(math.floor(DOMAIN_NODES ** (1.0 / d_in) + 1e-9))))
        self.size = check_positive_int(domain_size, "domain_size", minimum=2)
        self.noise = kern.noise
        dd = {"dtype": kern.dtype, "device": kern.device}
        nodes, weights = box_grid(self.box, self.size, **dd)
        self.nodes, self.weights = nodes, weights / weights.sum()
        self.prior = GPKernel(kern.gp, condition=False)
        k0 = float(self.prior.diag(nodes).max())
        piv, _ = pivots(self.prior, nodes, nodes.shape[0], PIVOT_TOL * k0)
        self.pivots = nodes[piv]
        with torch.no_grad():
            self.LZ = cholesky(self.prior(self.pivots), what="K(pivot nodes)")
            phi_q, _ = self.features(nodes)
            self.W = (phi_q * self.weights.unsqueeze(-1)).T @ phi_q  # (r, r)
            self.A = torch.eye(self.rank, **dd)  # I + Psi_data^T Psi_data
            self.num_conditioned = 0
            if kern.data is not None:  # the GP's data, with their own noise (floor + known, the same for all outputs)
                X = kern.data
                phi, r = self.features(X)
                noise = kern.gp._noise_diag(kern.gp.train_noise_)[0].detach().expand(X.shape[0])
                psi = phi / torch.sqrt(noise + r).unsqueeze(-1)
                self.A = self.A + psi.T @ psi
                self.num_conditioned = X.shape[0]

    @property
    def rank(self) -> int:
        """Number of features (pivot nodes)."""
        return self.pivots.shape[0]

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``phi(x) (..., M, r)`` and the residual variance ``r(x) (..., M)`` for ``x (..., M, d_in)``."""
        with torch.no_grad():
            K = self.prior.module.forward(self.pivots, x)  # (..., r, M)
            phi = torch.linalg.solve_triangular(self.LZ, K, upper=False).transpose(-1, -2)
            resid = (self.prior.module.forward(x, x, diag=True) - phi.pow(2).sum(-1)).clamp_min(0.0)
        return phi, resid

    def whitened(self, x: torch.Tensor) -> torch.Tensor:
        """``Psi = phi(x) / sqrt(sigma^2 + r(x))``: the features of new samples, noise and residual included."""
        phi, r = self.features(x)
        return phi / torch.sqrt(self.noise + r).unsqueeze(-1)

    def mean_variance(self, A: torch.Tensor) -> torch.Tensor:
        """``tr(W A^-1)`` (batched over leading dimensions of ``A``): the mean variance of one output over D."""
        return _trace_solve(A, self.W)

    def terms(self, points: torch.Tensor, d_out: int) -> DomainTerms:
        """The engine's terms for noisy correction samples at ``points (N, T, d_in)``, every output alike."""
        return DomainTerms(psi=self.whitened(points), A=self.A, W=self.W, multiplier=d_out)


def _trace_solve(A: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """``tr(W A^-1)``, batched over the leading dimensions of ``A``."""
    L = cholesky(A, what="I + Psi^T Psi")
    X = torch.linalg.solve_triangular(L, W.expand(*A.shape[:-2], -1, -1), upper=False)
    Y = torch.linalg.solve_triangular(L, X.transpose(-1, -2), upper=False)
    return Y.diagonal(dim1=-2, dim2=-1).sum(-1)


@dataclass(frozen=True)
class DomainTerms:
    """What the domain engine needs: V(S) = multiplier * [tr(W A^-1) - tr(W (A + sum_{c in S} Psi_c^T Psi_c)^-1)].

    Attributes:
        psi: ``(N, T, r)`` each candidate's observations, whitened, in the features' space.
        A: ``(r, r)`` the features' precision before the picks (the prior's identity and the data).
        W: ``(r, r)`` the quadrature of the features over D.
        multiplier: outputs sharing these terms (d_out for correction samples of every output alike; 1 where the
            features stack the outputs, as for readings).
    """

    psi: torch.Tensor
    A: torch.Tensor
    W: torch.Tensor
    multiplier: int

    def mean_variance(self, A: torch.Tensor) -> torch.Tensor:
        return _trace_solve(A, self.W)


def variance_reduction(
    points, gp, *, system, domain=None, domain_size: int | None = None, condition: bool | None = None
) -> float:
    """The domain criterion V of noisy correction samples at ``points``: mean variance of F over D removed.

    ``V = d_out * mean over D of [var(F | data) - var(F | data, samples)]`` (see the module docstring for the model),
    the quantity ``greedy(..., criterion="domain")`` maximises, in units of F squared.

    Args:
        points: ``(M, d_in)`` sample locations, already restricted to the correction inputs.
        gp: a :class:`~torchmisspec.CorrectionGP` with a shared kernel whose hyperparameters are set.
        system: the system (its correction inputs, outputs and domain).
        domain: the box D, one ``(lo, hi)`` per correction input (default ``system.domain``).
        domain_size: quadrature nodes per axis (default: at most 1024 nodes in all for up to 10 inputs, at most 33
            per axis, at least 2).
        condition: condition on the GP's training samples (default: when it is fitted).
    """
    system = check_system(system)
    kern = GPKernel(gp, input_dim=system.input_dim, condition=condition, system=system)
    x = as_tensor(points, "points", dtype=kern.dtype, device=kern.device)
    check_ndim(x, 2, "points", f"(M, {system.input_dim})")
    if x.shape[1] != system.input_dim:
        raise ShapeError(f"points: expected {system.input_dim} columns (the correction inputs), got {tuple(x.shape)}")
    check_finite(x, "points")
    model = DomainModel(kern, system, domain, domain_size)
    psi = model.whitened(x)
    with torch.no_grad():
        base = model.mean_variance(model.A)
        after = model.mean_variance(model.A + psi.T @ psi)
    return system.output_dim * float(base - after)


def domain_greedy(prob, method: str, progress: bool, feasible, terms: DomainTerms | None = None):
    """Greedy maximisation of V: ``(picks, gains, evaluations, diagnostics)``. ``prob``: the validated problem (its
    ``domain`` model and candidates' points, unless ``terms`` are given); ``feasible``: picks left."""
    model: DomainModel = prob.domain
    if terms is None:
        terms = model.terms(prob.points, prob.d_out)
    psi, d_out = terms.psi, terms.multiplier
    N, T, r = psi.shape
    K = prob.budget
    need = 2 * 8 * N * T * r
    if method != "naive" and need > MEMORY:
        raise InputError(
            f"criterion='domain': the engine needs {need / 2**30:.1f} GiB for {N} candidates x {T} times x {r} "
            f"domain features (at most {MEMORY / 2**30:.0f} GiB); pass fewer quadrature nodes "
            "(design.DomainCriterion(size=...) for greedy, domain_size= here) or fewer candidates"
        )
    base = float(terms.mean_variance(terms.A))
    scale = max(d_out * base, 1e-300)  # ties are judged relative to the prior's mean variance over D

    def first_best(g: torch.Tensor, ok: torch.Tensor) -> int:
        best = float(torch.where(ok, g, torch.tensor(-math.inf, dtype=g.dtype, device=g.device)).max())
        thr = best - prob.tie_tol * max(abs(best), scale)
        return int(torch.nonzero(ok & (g >= thr))[0, 0])

    picks, gains, evaluations = [], [], 0
    feas = feasible(prob)
    bar = progress_bar(progress, K, f"domain greedy (N={N})", "pick")
    dd = {"dtype": psi.dtype, "device": psi.device}
    eye = torch.eye(T, **dd)
    if method == "naive":
        A = terms.A.clone()
        current = base
        for _ in range(K):
            ok = feas.mask()
            idx = torch.nonzero(ok).flatten()
            values = torch.full((N,), -math.inf, **dd)
            for s in range(0, idx.numel(), 256):
                c = idx[s : s + 256]
                values[c] = d_out * (current - terms.mean_variance(A + psi[c].transpose(1, 2) @ psi[c]))
            evaluations += idx.numel()
            n = first_best(values, ok)
            picks.append(n)
            gains.append(float(values[n]))
            A = A + psi[n].T @ psi[n]
            current = float(terms.mean_variance(A))
            feas.add(n)
            if bar is not None:
                bar.update(1)
    else:  # exact vectorised greedy with rank-T (Woodbury) updates of B_c = Psi_c A^-1 and Y_c = B_c W
        LA = cholesky(terms.A, what="I + Psi_data^T Psi_data")
        Ainv = torch.cholesky_inverse(LA)
        B = psi @ Ainv  # (N, T, r)
        Y = B @ terms.W  # (N, T, r)
        H = B @ psi.transpose(1, 2)  # (N, T, T): Psi_c A^-1 Psi_c^T
        for k in range(K):
            ok = feas.mask()
            E = Y @ B.transpose(1, 2)  # B_c W B_c^T
            Lc = cholesky(eye + H, what="I + Psi A^-1 Psi^T (domain criterion)")
            g = d_out * torch.cholesky_solve(E, Lc).diagonal(dim1=1, dim2=2).sum(-1)
            evaluations += int(ok.sum())
            n = first_best(g, ok)
            picks.append(n)
            gains.append(float(g[n]))
            feas.add(n)
            if k + 1 < K:
                C = B @ psi[n].T  # (N, T, T): Psi_c A^-1 Psi_n^T
                Mn = Lc[n]  # chol(I + Psi_n A^-1 Psi_n^T)
                G = torch.cholesky_solve(C.transpose(1, 2), Mn).transpose(1, 2)  # C M_n^-1
                Bn, Yn = B[n].clone(), Y[n].clone()
                B -= G @ Bn
                Y -= G @ Yn
                H -= G @ C.transpose(1, 2)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    info = {
        "engine": "naive" if method == "naive" else "exact (not submodular: no lazy bounds)",
        "domain_nodes": model.nodes.shape[0],
        "domain_rank": model.rank,
        "mean_variance": d_out * base,  # the mean variance over D before the picks (data included)
    }
    return picks, gains, evaluations, info
