"""Private helpers of the design subpackage: the GP kernel view, input checks, the result type."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

from .._errors import BudgetError, InputError, ShapeError
from .._linalg import logdet_identity_plus, pivots
from .._validation import as_tensor, check_finite, check_input_names, check_ndim
from .._validation import check_times as _check_times
from ..gp import CorrectionGP
from ..gp._features import FeatureFactorization
from ..systems import MisspecifiedSystem

__all__ = ["DesignResult", "logdet_identity_plus"]


@dataclass(frozen=True)
class DesignResult:
    """A chosen set of experiments (initial conditions) and what the criterion says about it.

    All information quantities are in nats of a *real* Gaussian: the information gain of a set S is
    ``(d_out / 2) * logdet(I + K(P_S, P_S) / sigma^2)`` with ``P_S`` the proxy points of S restricted to the
    correction inputs (the paper's complex-Gaussian convention gives twice these numbers; the picks are the same).

    Attributes:
        indices: ``(K,)`` long, the chosen candidates in pick order.
        gains: ``(K,)`` marginal gain of each pick given the earlier ones: information (nats), or with
            ``criterion="domain"`` the mean variance of F over D removed (units of F squared); NaN when not computed
            (a random design without ``system``/``times``/``gp``).
        information_gain: sum of ``gains`` = information gain of the whole chosen proxy set (nats; NaN when not
            computed).
        points: ``(K, d)`` the chosen candidates.
        method: ``"lazy"``, ``"plain"``, ``"naive"``, ``"random"`` or ``"agnostic-lazy"`` / ``"agnostic-plain"`` /
            ``"agnostic-naive"``.
        evaluations: number of single-candidate marginal-gain evaluations (the initial pass over all candidates
            included); for ``"naive"`` the number of full log-determinants.
        proxies: ``(K, T, d)`` proxy trajectories of the picks, or ``None`` when not computed.
        elapsed: wall-clock seconds spent in the selection (proxies excluded).
        diagnostics: engine details (lazy greedy with screening: ``rank`` of the kernel features and the
            ``residual`` variance e_max that sets its bounds).
    """

    indices: torch.Tensor
    gains: torch.Tensor
    information_gain: float
    points: torch.Tensor
    method: str
    evaluations: int = 0
    proxies: torch.Tensor | None = None
    elapsed: float = 0.0
    diagnostics: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.indices.numel())


# ---------------------------------------------------------------------------------------------------- the kernel
DATA_PIVOT_TOL = 1e-15  # the data factor's pivots stop at this fraction of the largest prior variance


class _PriorView:
    """The prior kernel of a GPyTorch module with the interface :func:`pivots` needs."""

    def __init__(self, module) -> None:
        self.module = module

    def __call__(self, x1: torch.Tensor, x2: torch.Tensor | None = None) -> torch.Tensor:
        return self.module.forward(x1, x1 if x2 is None else x2)

    def diag(self, x: torch.Tensor) -> torch.Tensor:
        return self.module.forward(x, x, diag=True)


class _OutputBlocks:
    """The kernel of F's outputs as one kernel on points ``(x, o)`` whose last column is the output ``o``:

        k_aug((x, o), (x', o')) = [o = o'] k_o(x, x') / s_o,

    with ``k_o`` output o's kernel (the shared one, or its own with per-output kernels) and ``s_o`` the noise variance
    of a new sample of output o. The outputs are independent, so the information of samples of all outputs is the sum
    of each output's, and dividing each block by its noise makes the sum ``(1 / 2) logdet(I + K_aug)``: one
    criterion with unit noise, exact for outputs whose kernels or data noise differ."""

    def __init__(self, module, scales: torch.Tensor, batched: bool) -> None:
        self.module, self.scales, self.batched = module, scales, batched

    def forward(self, x1: torch.Tensor, x2: torch.Tensor, diag: bool = False) -> torch.Tensor:
        o1, o2 = x1[..., -1].round().long(), x2[..., -1].round().long()
        z1, z2 = x1[..., :-1], x2[..., :-1]
        if self.batched:  # one kernel per output: (..., d_out, M1, M2), output o1's rows kept
            K = self.module.forward(z1.unsqueeze(-3), z2.unsqueeze(-3), diag=diag)
            if diag:
                idx = o1.unsqueeze(-1).expand(*K.shape[:-2], K.shape[-1], 1)
                K = K.transpose(-1, -2).gather(-1, idx).squeeze(-1)
            else:
                idx = o1.unsqueeze(-2).unsqueeze(-1).expand(*K.shape[:-3], 1, K.shape[-2], K.shape[-1])
                K = K.gather(-3, idx).squeeze(-3)
        else:
            K = self.module.forward(z1, z2, diag=diag)
        inv = 1.0 / self.scales[o1]
        if diag:
            return K * inv
        return K * (o1.unsqueeze(-1) == o2.unsqueeze(-2)) * inv.unsqueeze(-1)


def future_noise(gp: CorrectionGP) -> torch.Tensor | None:
    """``(d_out,)`` the noise variance the design assumes for a new sample of each output, ``None`` for an unfitted
    GP (its one fixed ``noise_variance`` then).

    The learned (or fixed) noise variance, plus, when the GP was fitted with known per-sample noise (a derivative
    estimator's, e.g. the GP in time), the median known variance of that output's training samples: a new
    experiment is measured and differentiated like the earlier ones, so its samples are as noisy as a typical one
    (the learned variance alone is only the floor above the known noise, often orders of magnitude smaller)."""
    if not gp.is_fitted:
        return None
    d_out = gp.output_dim
    floor = gp._floor(gp.likelihood).noise.detach().reshape(-1).expand(d_out)
    known = gp.train_noise_
    if known is None:
        return floor.clone()
    return floor + known.detach().median(dim=0).values


def _checked_gp(gp, input_dim: int | None, system: MisspecifiedSystem | None) -> tuple[torch.Tensor | None, float]:
    """A GP a design can use (hyperparameters set, inputs matching the system): its noise per output and overall."""
    if not isinstance(gp, CorrectionGP):
        raise InputError(f"gp: expected a CorrectionGP, got {type(gp).__name__}")
    if system is not None:  # a model of the system's correction inputs, by name
        check_input_names(gp, system.input_names(), f"system '{system.name}'")
    if not gp.is_fitted and gp.per_output:
        raise InputError(
            "gp: an unfitted CorrectionGP with per_output=True has no per-output hyperparameters yet; design "
            "before any data with a shared kernel (per_output=False) and given hyperparameters, or fit it first"
        )
    if not gp.is_fitted and gp.kernel_spec.terms:
        raise InputError(
            "gp: the feature kernel's weights are learned from data; fit the GP on earlier samples before "
            "designing with it (or design with an RBF, Matern or polynomial prior)"
        )
    if not gp.is_fitted:
        needed = ["noise_variance", "outputscale"] + (["lengthscale"] if gp.kernel_spec.has_lengthscale else [])
        missing = [name for name in needed if gp.fixed.get(name) is None]
        if missing:
            args = ", ".join(f"{m}=..." for m in missing)
            raise InputError(
                f"gp: expected the kernel hyperparameters a design needs before any data, got {', '.join(missing)} "
                f"not set (None) on this unfitted CorrectionGP; pass "
                f"CorrectionGP({args}) or fit the GP on earlier data first"
            )
    scales = future_noise(gp)
    noise = float(gp.noise_variance) if scales is None else float(scales.max())
    if scales is not None and not bool(torch.isfinite(scales).all() and (scales > 0).all()):
        raise InputError(f"gp: expected positive finite noise variances, got {scales.tolist()}")
    if not math.isfinite(noise) or noise <= 0:
        raise InputError(f"gp: expected a positive finite noise_variance, got {noise!r}")
    if gp.is_fitted and input_dim is not None and gp.input_dim != input_dim:
        raise ShapeError(
            f"gp: expected a GP with {input_dim} inputs (the system's correction inputs), got one "
            f"fitted on {gp.input_dim}"
        )
    return scales, noise


def _checked_condition(condition: bool | None, gp: CorrectionGP) -> bool:
    """Whether to condition on the GP's data: by default when it has data, and never without."""
    if condition is None:
        condition = gp.is_fitted
    if condition and not gp.is_fitted:
        raise InputError(
            "condition: expected a fitted gp to condition on its data, got an unfitted one; fit it first or pass False"
        )
    return condition


def _data_layout(gp: CorrectionGP, fac, scales, condition: bool) -> tuple[torch.Tensor | None, bool, bool]:
    """The data factor (dense Cholesky or None), whether the data term lives in feature space, and whether all
    outputs share one kernel, noise and data (the shared layout)."""
    in_features = isinstance(fac, FeatureFactorization)  # the data's term in feature space (no N x N factor)
    if in_features:
        shared_data = fac.cov.shape[0] == 1 or all(torch.equal(fac.cov[0], c) for c in fac.cov[1:])
        chol = None
    else:  # the data's factor: (1, N, N) when every output has the same C = K + noise, else (d_out, N, N)
        chol = None if fac is None else fac.chol.detach()
        shared_data = chol is None or chol.shape[0] == 1 or all(torch.equal(chol[0], c) for c in chol[1:])
    shared = not gp.per_output and shared_data and (scales is None or bool((scales == scales[0]).all()))
    if in_features and condition and not shared:  # per-output data terms: the dense factor (modest N only)
        chol, in_features = fac.chol.detach(), False
    return chol, in_features, shared


class GPKernel:
    """The correction GP's prior kernel k (outputscale included) and noise variance, ready for batched use.

    Calls the GP's own GPyTorch kernel module, so the design uses exactly the covariance the GP will use; inputs
    may carry batch dimensions (``(..., M1, d_in)`` with ``(..., M2, d_in)``).

    Two layouts, chosen from the GP (consumers call :meth:`expand` on their points and weigh log-determinants by
    :meth:`multiplicity`, and never ask which):

    * **shared**: one kernel, one noise variance and the same data for every output (the paper's model); the
      criterion is ``d_out`` times the single-output one.
    * **per output**: per-output kernels, or noise (learned or known per sample) that differs between outputs. Each
      output is then informed by its own data and noise: points become ``(x, o)`` pairs, one per output
      (:meth:`expand`), under the block kernel of :class:`_OutputBlocks` with unit noise. Exact: the information
      of independent outputs is the sum of each output's, and each is conditioned on its own samples.

    With ``condition`` (default: when the GP is fitted) the kernel is the *posterior* covariance of F given the GP's
    training samples (with their noise, per sample where known), k(x, x') - k(x, X) C^-1 k(X, x') with
    C = K(X, X) + noise: every information gain is then the information given the data already collected. The
    noise of *new* samples is :func:`future_noise`.
    """

    def __init__(
        self,
        gp: CorrectionGP,
        *,
        input_dim: int | None = None,
        condition: bool | None = None,
        exact_data: bool = False,
        system: MisspecifiedSystem | None = None,
    ) -> None:
        scales, noise = _checked_gp(gp, input_dim, system)
        condition = _checked_condition(condition, gp)
        self.gp = gp
        self.dtype = gp.dtype
        self.device = gp.device
        fac = gp.posterior().factor if gp.is_fitted else None
        chol, in_features, shared = _data_layout(gp, fac, scales, condition)
        #: whether points are expanded to one block per output (:meth:`expand`); False: the shared layout
        self.expanded = not shared
        self.blocks = 1 if shared else gp.output_dim
        if shared:
            self.module = gp.covar_module
            self.noise = noise
        else:
            self.module = _OutputBlocks(gp.covar_module, scales, gp.per_output)
            self.noise = 1.0
            self.scales = scales
        #: the lower Cholesky factor of K(X, X) + noise of the GP's training samples X when conditioning on them
        #: through the dense factor, else None
        self.chol: torch.Tensor | None = None
        #: the GP's training inputs when conditioning on them, else None
        self.data: torch.Tensor | None = None
        self._G: torch.Tensor | None = None  # the data term's factor (see _data_factor); None: the prior
        self._memo: tuple | None = None
        if condition and in_features:
            self.data = gp.train_inputs_.detach()
            self._feature_factor(fac, gp.covar_module.base_kernel)
        elif condition:
            X = gp.train_inputs_.detach()
            if shared:
                self.chol, self.data = chol[0], X
            else:  # block o: output o's data factor over its noise, C_o / s_o = (L_o / sqrt(s_o))(...)^T
                L = chol.expand(self.blocks, -1, -1) / scales.sqrt().reshape(-1, 1, 1)
                self.chol = torch.block_diag(*L)
                self.data = self.expand(X)
            self._data_factor(exact_data)

    def expand(self, x: torch.Tensor) -> torch.Tensor:
        """Points ``(..., M, d_in)`` as the kernel takes them: unchanged in the shared layout, else one copy per
        output with the output's index as a last column, ``(..., d_out M, d_in + 1)`` (output-major)."""
        if not self.expanded:
            return x
        labels = torch.arange(self.blocks, dtype=x.dtype, device=x.device)
        labels = labels.repeat_interleave(x.shape[-2]).reshape(*([1] * (x.dim() - 2)), -1, 1)
        copies = (
            x.unsqueeze(-3).expand(*x.shape[:-2], self.blocks, *x.shape[-2:]).reshape(*x.shape[:-2], -1, x.shape[-1])
        )
        return torch.cat([copies, labels.expand(*copies.shape[:-1], 1)], dim=-1)

    def multiplicity(self, d_out: int) -> int:
        """The factor on ``(1 / 2) logdet(I + K / noise)`` of expanded points: ``d_out`` identical outputs in the
        shared layout, 1 per output block (each output is one of the expanded points' blocks)."""
        return 1 if self.expanded else d_out

    @property
    def num_conditioned(self) -> int:
        """Training samples the kernel is conditioned on (0: the prior)."""
        return 0 if self.data is None else self.data.shape[0] // self.blocks

    def _data_factor(self, exact: bool = False) -> None:
        """A factor G (r x r) with k(x, X) C^-1 k(X, x') = (G^T k(Z, x))^T (G^T k(Z, x')) up to ``data_error``.

        The N kernel functions k(., X) of the data span few dimensions for a smooth kernel: a pivoted Cholesky of
        K(X, X) picks r pivots Z until the residual variance on X is at round-off (``DATA_PIVOT_TOL`` of the
        largest prior variance). Then k(x, X) = phi(x)^T A + e(x) with phi(x) = L_Z^-1 k(Z, x), A = L_Z^-1 K(Z, X),
        and the data term is phi^T M phi with M = A C^-1 A^T = B B^T, so G = L_Z^-T B. Each kernel block then costs
        r (not N^2) per point: the conditioned design of 10,000 candidates on 500 samples takes seconds, not a
        minute. With every point a pivot (r = N), or ``exact`` (the reference the benchmark times), it is exact.

        Certified error: |e_i(x)| <= sqrt(k(x, x) e_X) with e_X the largest residual on X, so every entry of the
        conditioned kernel is within ``data_error`` = 2 sqrt(k0 N e_X / c_min) sqrt(k0) + N k0 e_X / c_min of
        the exact one (c_min: the smallest eigenvalue of C, at least the smallest noise variance).
        """
        X, L = self.data, self.chol
        N = X.shape[0]
        with torch.no_grad():
            prior = _PriorView(self.module)
            k0 = float(prior.diag(X).max())
            piv, e_X, A = pivots(prior, X, N, DATA_PIVOT_TOL * k0, factor=True)  # A = L_Z^-1 K(Z, X): (r, N)
            if piv.numel() == N:
                e_X = 0.0
            else:  # the residuals are known to round-off of the accumulated factor at best
                e_X = max(e_X, piv.numel() * torch.finfo(X.dtype).eps * k0)
            Z = X[piv]
            LZ = A[:, piv].T.contiguous()  # lower triangular, L_Z L_Z^T = K(Z, Z)
            W = torch.linalg.solve_triangular(L, A.T, upper=False)  # L^-1 A^T: M = W^T W
            # M = W^T W; its QR R^T R = M gives B = R^T, so G = L_Z^-T R^T
            R = torch.linalg.qr(W, mode="r").R  # (r, r)
            self._Z = Z
            self._G = torch.linalg.solve_triangular(LZ.T, R.T, upper=True)  # (r, r)
            c_min = float(torch.linalg.eigvalsh(L @ L.T)[0].clamp_min(0.0)) if e_X > 0 else 1.0
            self.data_rank = piv.numel()
            self.data_error = 0.0
            if exact or not bool(torch.isfinite(self._G).all()):  # never a silent NaN: exact psi = L^-1 k(X, x)
                eye = torch.eye(N, dtype=L.dtype, device=L.device)
                self._Z, self._G = X, torch.linalg.solve_triangular(L.T, eye, upper=True)
                self.data_rank, e_X = N, 0.0
            if e_X > 0:
                q = k0 * N * max(e_X, 0.0) / max(c_min, 1e-300)
                self.data_error = 2 * math.sqrt(q * k0) + q

    def _feature_factor(self, fac, base) -> None:
        """The data term of a feature-space posterior, exactly: with the coefficients' prior ``diag(W)`` and posterior
        covariance ``S``, k(x, X) C^-1 k(X, x') = phi(x)^T (W - S) phi(x'), so G G^T = W - S (p x p, from its
        eigendecomposition) and the basis is phi(x) itself; no N x N matrix and no pivots."""
        with torch.no_grad():
            M = torch.diag(fac._W[0]) - fac.cov[0]
            lam, U = torch.linalg.eigh(0.5 * (M + M.T))
            keep = lam > lam.abs().max().clamp_min(torch.finfo(M.dtype).tiny) * torch.finfo(M.dtype).eps * M.shape[0]
            self._G = U[:, keep] * lam[keep].sqrt()
            self._features = base.features
            self.data_rank, self.data_error = int(keep.sum()), 0.0

    def _basis(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., r, M)``: what the data factor ``G`` multiplies: k(Z, x) at the pivots, or the features phi(x)^T."""
        if getattr(self, "_features", None) is not None:
            return self._features(x).transpose(-1, -2)
        return self.module.forward(self._Z, x)

    def _explained(self, x: torch.Tensor) -> torch.Tensor:
        """``psi(x)`` ``(..., r, M)`` for ``x (..., M, d_in)``, with k(x, X) C^-1 k(X, x') = psi(x)^T psi(x').

        The last large tensor's value is kept (one entry, by identity): :func:`pivots` asks for columns against the
        same points once per pivot."""
        if self._memo is not None and self._memo[0] is x:
            return self._memo[1]
        with torch.no_grad():
            psi = self._G.T @ self._basis(x)
        if x.shape[-2] >= 64:  # small blocks (a pivot's point) are cheap and must not evict the large one
            self._memo = (x, psi)
        return psi

    def cross_and_diag(self, z: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(k(z, x), diag k(x, x))`` sharing the data term of ``x`` (one pass over ``x`` instead of two)."""
        with torch.no_grad():
            K = self.module.forward(z, x)
            d = self.module.forward(x, x, diag=True)
            if self._G is None:
                return K, d
            Vx = self._G.T @ self._basis(x)
            return K - self._explained(z).transpose(-1, -2) @ Vx, (d - Vx.pow(2).sum(-2)).clamp_min(0.0)

    def __call__(self, x1: torch.Tensor, x2: torch.Tensor | None = None) -> torch.Tensor:
        """The kernel block ``(..., M1, M2)``; conditioned on the GP's data: k(x1, x2) - k(x1, X) C^-1 k(X, x2)."""
        with torch.no_grad():
            K = self.module.forward(x1, x1 if x2 is None else x2)
            if self._G is None:
                return K
            V1 = self._explained(x1)
            V2 = V1 if x2 is None else self._explained(x2)
            return K - V1.transpose(-1, -2) @ V2

    def differentiable(self, x: torch.Tensor) -> torch.Tensor:
        """The block ``k(x, x)`` ``(..., M, M)`` (conditioned like :meth:`__call__`) with autograd through ``x``, for
        gradients of the criterion in the experiments (:func:`~torchmisspec.design.refine`); the data's factor is
        a constant."""
        K = self.module.forward(x, x)
        if self._G is None:
            return K
        V = self._G.T @ self._basis(x)
        return K - V.transpose(-1, -2) @ V

    def diag(self, x: torch.Tensor) -> torch.Tensor:
        """k(x_i, x_i) for ``x (M, d_in)``: ``(M,)`` (conditioned like the blocks)."""
        with torch.no_grad():
            d = self.module.forward(x, x, diag=True)
            if self._G is None:
                return d
            return (d - self._explained(x).pow(2).sum(-2)).clamp_min(0.0)

    def block_diagonal(self, points: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
        """k(P_c, P_c) for every candidate: ``points (N, T, d_in)`` -> ``(N, T, T)`` (chunked over N)."""
        n = points.shape[0]
        if n <= chunk:
            return self(points)
        return torch.cat([self(points[i : i + chunk]) for i in range(0, n, chunk)])


# ---------------------------------------------------------------------------------------------------- input checks
def check_system(system, controls=None, *, with_controls: bool = False) -> MisspecifiedSystem:
    """The system a design runs on; one with inputs needs ``controls`` (one profile per candidate), which the design
    functions built for them take (``with_controls``)."""
    if not isinstance(system, MisspecifiedSystem):
        raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
    if system.num_controls and (controls is None or not with_controls):
        where = "pass controls=... (one input profile per candidate)"
        if not with_controls:
            where = "use design.greedy, random, agnostic, sampling_times, refine or Campaign with controls=..."
        got = "a design function without them" if not with_controls else "controls=None"
        raise InputError(
            f"controls: expected an input profile per candidate, as system '{system.name}' has inputs u(t) "
            f"{list(system.control_names)} (a candidate experiment is then an initial state and an input profile), "
            f"got {got}: {where}"
        )
    if not system.autonomous and not system.num_controls:
        raise InputError(
            f"system: expected an autonomous system or one with inputs u(t), got '{system.name}', which depends on "
            "time without inputs; designing for such systems is not built yet"
        )
    return system


def check_candidates(
    candidates, system: MisspecifiedSystem, *, dtype=None, device=None, name: str = "candidates"
) -> torch.Tensor:
    """Candidates (or other initial states, named ``name``) ``(N, d)``: 2-D, d = state_dim, finite, at least one
    row."""
    c = as_tensor(candidates, name, dtype=dtype, device=device)
    check_ndim(c, 2, name, f"(N, {system.state_dim})")
    if c.shape[1] != system.state_dim:
        raise ShapeError(
            f"{name}: expected shape (N, {system.state_dim}) (state_dim of system '{system.name}'), got "
            f"{tuple(c.shape)}"
        )
    if c.shape[0] < 1:
        raise ShapeError(f"{name}: expected at least one row, got shape (0, d)")
    check_finite(c, name)
    return c


def check_times(times, *, dtype, device) -> torch.Tensor:
    """Observation times ``(T,)``: 1-D, at least one, finite, strictly increasing."""
    return _check_times(times, "times", dtype=dtype, device=device)


def check_proxies(
    proxies, n: int, system: MisspecifiedSystem, times: torch.Tensor | None, *, dtype, device
) -> torch.Tensor:
    p = as_tensor(proxies, "proxies", dtype=dtype, device=device)
    T = "T" if times is None else str(times.shape[0])
    check_ndim(p, 3, "proxies", f"({n}, {T}, {system.state_dim})")
    if p.shape[0] != n or p.shape[2] != system.state_dim or (times is not None and p.shape[1] != times.shape[0]):
        raise ShapeError(
            f"proxies: expected shape ({n}, {T}, {system.state_dim}) to match the candidates and "
            f"times, got {tuple(p.shape)}"
        )
    if p.shape[1] < 1:
        raise ShapeError("proxies: expected at least one time, got T = 0")
    check_finite(p, "proxies")
    return p


def check_budget(budget, n: int) -> int:
    if isinstance(budget, bool) or not isinstance(budget, int):
        try:
            if isinstance(budget, bool) or int(budget) != budget:
                raise TypeError
            budget = int(budget)
        except (TypeError, ValueError, OverflowError):
            raise BudgetError(f"budget: expected a positive integer, got {budget!r}") from None
    if budget < 1:
        raise BudgetError(f"budget: expected at least 1 experiment, got {budget}")
    if budget > n:
        raise BudgetError(f"budget: expected at most the number of candidates ({n}), got budget = {budget}")
    return budget


def check_partition(partition, capacities, n: int, budget: int, device) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Region label per candidate and capacity per region, as ``(region (N,) long in 0..R-1, caps (R,) long)``.

    ``capacities`` is a mapping label -> most picks, or a sequence indexed by label (labels 0..len-1). Raises
    BudgetError when the budget exceeds what the capacities (and the region sizes) allow.
    """
    if partition is None and capacities is None:
        return None
    if partition is None or capacities is None:
        raise InputError(
            "partition and capacities: expected both (a region label per candidate and the most picks "
            "per region) or neither, got only "
            f"{'partition' if capacities is None else 'capacities'}"
        )
    try:
        lab = torch.as_tensor(partition)
    except (TypeError, ValueError, RuntimeError, OverflowError):
        raise InputError(
            f"partition: expected an integer region label per candidate, got {partition!r:.80}; number the regions "
            "0, 1, ... (e.g. [labels.index(x) for x in names])"
        ) from None
    if lab.dim() != 1 or lab.shape[0] != n:
        raise ShapeError(f"partition: expected one region label per candidate, shape ({n},), got {tuple(lab.shape)}")
    integral = not (lab.is_complex() or lab.dtype == torch.bool)
    if integral and lab.is_floating_point():
        integral = bool(torch.isfinite(lab).all() and (lab == lab.round()).all() and (lab.abs() < 2**62).all())
    if not integral:
        raise InputError(
            f"partition: expected integer region labels, got dtype {str(lab.dtype).removeprefix('torch.')} "
            f"({lab.tolist()!r:.80}); number the regions 0, 1, ..."
        )
    lab = lab.to(torch.long).cpu()
    labels = sorted(int(v) for v in torch.unique(lab))
    if isinstance(capacities, Mapping):
        caps_map = dict(capacities)
    elif isinstance(capacities, (Sequence, torch.Tensor)) and not isinstance(capacities, str):
        caps_map = {
            i: c for i, c in enumerate(capacities.tolist() if isinstance(capacities, torch.Tensor) else capacities)
        }
    else:
        raise InputError(
            f"capacities: expected a mapping label -> most picks or a sequence indexed by label, got "
            f"{type(capacities).__name__}"
        )
    clean = {}
    for key, val in caps_map.items():
        try:
            k = int(key)
            if k != key or isinstance(key, bool):
                raise TypeError
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"capacities: expected integer region labels as keys, got {key!r}") from None
        integral = isinstance(val, numbers.Integral) or (isinstance(val, float) and val.is_integer())
        if isinstance(val, bool) or not integral or int(val) < 0:
            raise InputError(f"capacities: expected non-negative integers, got {val!r} for region {k}")
        clean[k] = min(int(val), n)  # more picks than candidates allows nothing more
    missing = [lbl for lbl in labels if lbl not in clean]
    if missing:
        raise InputError(
            f"capacities: expected a capacity for every region label in partition {labels}, missing "
            f"{missing} (got capacities for {sorted(clean)})"
        )
    region = torch.searchsorted(torch.tensor(labels, dtype=torch.long), lab)  # labels -> 0..R-1
    caps = torch.tensor([clean[lbl] for lbl in labels], dtype=torch.long)
    sizes = torch.bincount(region, minlength=len(labels))
    allowed = int(torch.minimum(caps, sizes).sum())
    if budget > allowed:
        region_sizes = dict(zip(labels, sizes.tolist(), strict=True))
        raise BudgetError(
            f"budget: expected at most {allowed} experiments (what the capacities {clean} allow "
            f"with the region sizes {region_sizes}), got budget = {budget}"
        )
    return region.to(device), caps.to(device)
