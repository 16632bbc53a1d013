"""Designing for what is measured: the information about F of noisy *readings* z = H y, derived through the ODE.

The paper's criterion (:mod:`._gain`) scores correction samples F~(y(t_j)) at every state of a proxy path, as if
every state were measured and differentiated. A lab often reads only a combination of the states, z = H y (a
:class:`~torchmisspec.Readout`: a total biomass, one of two species), and such readings give no derivative samples:
the correction is learned through the ODE (:mod:`torchmisspec.learning.refinement.partial`). This module scores
what those readings tell about F.

**Linearised readings.** Let y*(t) be a candidate's proxy path, from y0 under the proxy field V (G alone, or
G + mu with mu the GP's posterior mean when the design conditions on data, as :func:`greedy` does with
``proxy="corrected"``). A perturbation f of the correction (F = mu + f, or F = f before any data) moves the path,
to first order, by the variational equation

    d(delta y)/dt = J(t) delta y + E f(x(y*(t))),    delta y(t_0) = 0,

with J(t) = dV/dy at y*(t) and E the embedding of F's d_out outputs into the d states (``system.embed``). Its
solution is delta y(t_j) = int_{t_0}^{t_j} Phi(t_j, s) E f(x(y*(s))) ds, Phi the state-transition matrix of J. On
a grid s_0 = t_0 < s_1 < ... < s_n = t_{T-1} (each observation interval cut into ``substeps`` equal steps) the
trapezoidal rule gives

    delta y(t_j) ~ sum_{i : s_i <= t_j} w_{j,i} Phi(t_j, s_i) E f(x_i),        x_i = x(y*(s_i)),

and the readings z_j = H y(t_j) + eps_j, eps_j ~ N(0, diag(sigma_z^2)), are z - H y*(t_j) = A f + eps with

    A[(j, r), (o, i)] = w_{j,i} (H Phi(t_j, s_i) E)[r, o] / sigma_z[r]        (readings whitened by their noise).

Phi(t_j, s_i) is the product of the one-step transitions Psi_k = Phi(s_{k+1}, s_k), each integrated from the
identity together with the path over its own step (``[y, Psi]' = [V(y), J(y) Psi]``, J by autograd of V; all steps
of all candidates in one batched solve). Products of one-step transitions never invert a transition matrix, so a
strongly contracting G costs no accuracy. The reading at t_0 carries nothing about f (delta y(t_0) = 0) and is left
out: a candidate contributes R = m (T - 1) readings.

**Information.** With f ~ GP(0, k) (independent outputs, output o's covariance k_o: the shared kernel, or its own
with a per-output GP; conditioned on the data the GP was fitted on when ``condition``, exactly as for derivative
samples, see :class:`._common.GPKernel`), the readings of a set S of experiments are jointly Gaussian and

    f_z(S) = (1 / 2) logdet(I + A_S K_S A_S^T),     (A_S K_S A_S^T)[a, b] = sum_o A_a^{(o)} k_o(X_a, X_b) A_b^{(o)T},

nats, the mutual information between f and the stacked readings. The readings of different experiments are
conditionally independent given f, so f_z is monotone submodular in S (it is a mutual information of conditionally
independent observations; Krause and Guestrin 2005), and greedy selection keeps its (1 - 1/e) guarantee under a
cardinality budget (1/2 under a partition matroid), relative to the best set for this (linearised, proxy) criterion.

**Relation to the derivative-sample criterion.** The paper's criterion is the special case where the "readings" are
f itself at the proxy points: A = I at the T nodes, noise sigma^2 of a correction sample. With every state read
(H = I) and dense times, differencing consecutive readings (z_{j+1} - z_j) / dt gives G + f at t_j with noise
variance about 2 sigma_z^2 / dt^2, so the readout criterion approaches the derivative one with that noise. With a
readout H of fewer rows than states the two differ in kind: F acting on a state that is not read is seen only through
how G carries it into the read states (Phi's off-diagonal terms), and a candidate whose path excites only unread,
weakly coupled states is worth little, where the derivative criterion, which assumes every state differentiated,
values it fully.

**Noise.** sigma_z is the readings' standard deviation: given (``ReadoutCriterion(noise_std=...)``), else the fitted
model's estimate (``gp.state_noise_``, the variances a fit through the ODE records for the states and readings), else
:data:`DEFAULT_NOISE_FRACTION` of the root mean square of each reading along the candidates' proxy paths (1 %: a
typical instrument's precision). Scaling sigma_z moves the criterion between logdet (precise readings: spread the
experiments) and trace (noisy readings: each experiment's own signal).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from .._errors import InputError, ShapeError
from .._linalg import logdet_identity_plus
from .._ode import solve
from .._validation import as_tensor, check_indices, check_positive_int
from ..data import Readout
from ..gp import CorrectionGP
from ..systems import MisspecifiedSystem
from ._common import DesignResult, GPKernel, check_candidates, check_system, check_times
from ._domain import DomainCriterion, DomainModel, domain_greedy
from ._proxy import PROXY_TOLERANCES, choose_proxy, proxy_paths
from ._readings_covariance import ReadingsCovariance
from ._readings_domain import readings_terms
from ._readings_theta import theta_uncertainty

__all__ = [
    "ReadoutCriterion",
    "ReadoutSensitivity",
    "readout_sensitivity",
    "readout_information_gain",
    "readout_design",
]

#: without a given noise or a fitted estimate, sigma_z is this fraction of each reading's RMS along the proxies
DEFAULT_NOISE_FRACTION = 0.01


@dataclass(frozen=True)
class ReadoutCriterion:
    """The information about F of readings z = H y (a :class:`~torchmisspec.Readout`) through the ODE, as a design
    criterion: ``greedy(..., criterion=ReadoutCriterion(readout))`` (see :mod:`torchmisspec.design._readings`).

    Attributes:
        readout: what each experiment reads, H ``(m, d)`` over the system's states.
        noise_std: the readings' noise standard deviation: a number, or one per reading ``(m,)``; ``None``: the
            fitted GP's estimate (``gp.state_noise_``) where it has one, else :data:`DEFAULT_NOISE_FRACTION` of each
            reading's RMS along the proxies.
        substeps: quadrature steps per observation interval (the integral of F's effect between readings).
        domain: ``None`` (default): score the readings' information about F anywhere; a
            :class:`~torchmisspec.design.DomainCriterion`: score the mean posterior variance of F over its box D that
            the readings remove (:mod:`torchmisspec.design._readings_domain`; not submodular).
    """

    readout: Readout
    noise_std: float | tuple | None = None
    substeps: int = 4
    domain: DomainCriterion | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.readout, Readout):
            raise InputError(
                f"readout: expected a torchmisspec.Readout (the measured combinations H y), got "
                f"{type(self.readout).__name__}; build one with Readout(matrix, names) or Readout.parse(...)"
            )
        check_positive_int(self.substeps, "substeps")
        if self.domain is not None and not isinstance(self.domain, DomainCriterion):
            raise InputError(
                f"domain: expected None (the readings' information about F anywhere) or a design.DomainCriterion "
                f"(the variance of F over a box D), got {type(self.domain).__name__}; pass "
                "domain=design.DomainCriterion(domain=((lo, hi), ...))"
            )
        if self.noise_std is not None:
            s = as_tensor(self.noise_std, "noise_std", dtype=torch.float64).reshape(-1)
            m = self.readout.num_readings
            if s.numel() not in (1, m) or not bool(torch.isfinite(s).all() and (s > 0).all()):
                raise InputError(
                    f"noise_std: expected a positive standard deviation or {m} (one per reading "
                    f"{list(self.readout.names)}), got {self.noise_std!r:.80}"
                )
            object.__setattr__(self, "noise_std", tuple(float(v) for v in s.expand(m)))

    def checked(self, system: MisspecifiedSystem) -> Readout:
        """The readout over ``system``'s states (matched by name when both name them), or a clear error."""
        if self.readout.state_dim != system.state_dim:
            raise ShapeError(
                f"readout: expected weights over the {system.state_dim} states of system '{system.name}' (an "
                f"(m, {system.state_dim}) matrix), got {self.readout.state_dim} columns "
                f"({'; '.join(self.readout.describe())})"
            )
        return self.readout.for_states(system.state_names, f"system '{system.name}'")


@dataclass(frozen=True)
class ReadoutSensitivity:
    """The linearised readings of N candidates (see the module docstring).

    Attributes:
        A: ``(N, R, d_out, S)`` sensitivity of the R = m (T - 1) readings (time-major, unwhitened) to F's outputs at
            the S quadrature nodes (quadrature weights included).
        nodes: ``(N, S, d_in)`` F's inputs at the nodes, x(y*(s_i)).
        paths: ``(N, S, d)`` the proxy paths on the quadrature grid.
        grid: ``(S,)`` the quadrature grid (the observation times are every ``substeps``-th node).
    """

    A: torch.Tensor
    nodes: torch.Tensor
    paths: torch.Tensor
    grid: torch.Tensor


def _grid(times: torch.Tensor, substeps: int) -> torch.Tensor:
    if times.numel() < 2:
        raise InputError(
            f"times: expected at least two observation times for readings (the reading at the initial time tells "
            f"nothing about F), got {times.numel()}"
        )
    frac = torch.arange(substeps, dtype=times.dtype, device=times.device) / substeps
    inner = (times[:-1, None] + (times[1:] - times[:-1])[:, None] * frac).reshape(-1)
    return torch.cat([inner, times[-1:]])


def _proxy_field(system: MisspecifiedSystem, gp: CorrectionGP | None, proxy: str):
    """V(y, t=None, u=None), the field the proxy paths follow (differentiable in y)."""
    if proxy == "known":
        return system.known_rhs
    from ..prediction.dynamics import CorrectedODE

    return CorrectedODE(system, gp).field


def _jacobian(field, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(V(y), dV/dy)`` for rows ``y (B, d)``: ``(B, d)`` and ``(B, d, d)`` (one backward pass per component)."""
    with torch.enable_grad():
        z = y.detach().requires_grad_(True)
        v = field(z)
        rows = [torch.autograd.grad(v[:, i].sum(), z, retain_graph=i + 1 < v.shape[1])[0] for i in range(v.shape[1])]
    return v.detach(), torch.stack(rows, dim=1)


def _transitions(field, paths: torch.Tensor, grid: torch.Tensor, system: MisspecifiedSystem, controls=None):
    """One-step transition matrices Psi_k = Phi(s_{k+1}, s_k) ``(N, n, d, d)`` along ``paths (N, n + 1, d)``: every
    step of every candidate integrated together, an autonomous system's in the step's own time tau in [0, 1] (the
    field scaled by h_k), any other's from s_k to s_{k+1} with candidate c's inputs ``controls[c]`` (its jumps
    never stepped across)."""
    N, S, d = paths.shape
    start = paths[:, :-1].reshape(-1, d)
    eye = torch.eye(d, dtype=paths.dtype, device=paths.device).reshape(1, d * d).expand(start.shape[0], -1)

    def augmented(z: torch.Tensor, t=None, u=None) -> torch.Tensor:
        v, J = _jacobian(lambda y: field(y, t, u), z[:, :d])
        Psi = z[:, d:].reshape(-1, d, d)
        return torch.cat([v, (J @ Psi).reshape(-1, d * d)], dim=1)

    rtol, atol = PROXY_TOLERANCES
    settings = dict(rtol=rtol, atol=atol, what="readout sensitivity")
    with torch.no_grad():
        if system.autonomous:
            h = (grid[1:] - grid[:-1]).repeat(N).unsqueeze(1)  # (N n, 1)
            tau = torch.tensor([0.0, 1.0], dtype=paths.dtype, device=paths.device)
            out, _ = solve(lambda z: h * augmented(z), torch.cat([start, eye], dim=1), tau, **settings)
        else:  # row c (S - 1) + k: candidate c's step k, its inputs looked up in candidate c's profile
            spans = torch.stack([grid[:-1], grid[1:]], dim=-1).repeat(N, 1)

            def rhs(t: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
                u = None if controls is None else controls.at(t.reshape(N, S - 1)).reshape(N * (S - 1), -1)
                return augmented(z, t, u)

            jumps = None if controls is None else controls.jumps
            out, _ = solve(rhs, torch.cat([start, eye], dim=1), spans, timed=True, jumps=jumps, **settings)
    return out[:, -1, d:].reshape(N, S - 1, d, d)


def _sensitivity(
    system: MisspecifiedSystem,
    H: torch.Tensor,
    field,
    paths: torch.Tensor,
    grid: torch.Tensor,
    substeps: int,
    forcing: torch.Tensor | None = None,
    controls=None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``A (N, m (T - 1), d_out, S)`` from the paths on the grid (see the module docstring), and with ``forcing``
    ``(N, S, d, p)`` (G's derivative in its uncertain parameters along the paths) the readings' sensitivity to them
    ``(N, m (T - 1), p)`` (:mod:`._readings_theta`), else ``None``; ``controls``: one input profile per candidate
    for a system with inputs."""
    N, S, d = paths.shape
    Psi = _transitions(field, paths, grid, system, controls)
    h = grid[1:] - grid[:-1]
    E = system.embed(torch.eye(system.output_dim, dtype=paths.dtype, device=paths.device)).T  # (d, d_out)
    # B[:, :, i, :] = Phi(s_j, s_i) for the current j (zero for i > j), advanced one step at a time
    B = paths.new_zeros(N, d, S, d)
    B[:, :, 0, :] = torch.eye(d, dtype=paths.dtype, device=paths.device)
    rows, theta_rows = [], []
    for j in range(1, S):
        B = torch.einsum("nab,nbic->naic", Psi[:, j - 1], B)
        B[:, :, j, :] = torch.eye(d, dtype=paths.dtype, device=paths.device)
        if j % substeps == 0:  # an observation time: trapezoid weights on [s_0, s_j]
            w = paths.new_zeros(S)
            w[:j] += 0.5 * h[:j]
            w[1 : j + 1] += 0.5 * h[:j]
            rows.append(torch.einsum("ra,naic,co,i->nroi", H, B, E, w))
            if forcing is not None:
                theta_rows.append(torch.einsum("ra,naic,nicp,i->nrp", H, B, forcing, w))
    return torch.cat(rows, dim=1), (torch.cat(theta_rows, dim=1) if forcing is not None else None)


def readout_sensitivity(
    system: MisspecifiedSystem,
    candidates,
    times,
    readout: Readout,
    *,
    gp: CorrectionGP | None = None,
    proxy: str = "known",
    substeps: int = 4,
) -> ReadoutSensitivity:
    """How each candidate's readings respond to a perturbation of F, linearised along its proxy path.

    Args:
        system: an autonomous system without controls.
        candidates: ``(N, d)`` initial states.
        times: ``(T,)`` observation times, T >= 2.
        readout: what is read, H ``(m, d)``.
        gp: the correction GP (needed for ``proxy="corrected"``: its posterior mean drives the path).
        proxy: ``"known"`` (G alone) or ``"corrected"`` (G + the GP's posterior mean).
        substeps: quadrature steps per observation interval.

    Returns:
        a :class:`ReadoutSensitivity`: delta z = sum_{o, i} A[:, :, o, i] f_o(nodes[:, i]) to first order.
    """
    system = _check_system(system)
    H = ReadoutCriterion(readout, substeps=substeps).checked(system).matrix
    kd = {"dtype": torch.float64 if gp is None else gp.dtype, "device": None if gp is None else gp.device}
    y0 = check_candidates(candidates, system, **kd)
    t = check_times(times, dtype=y0.dtype, device=y0.device)
    if proxy not in ("known", "corrected"):
        raise InputError(f"proxy: expected 'known' or 'corrected', got {proxy!r}")
    if proxy == "corrected" and (gp is None or not gp.is_fitted):
        raise InputError("proxy='corrected': expected a fitted gp whose posterior mean drives the path, got none")
    grid = _grid(t, substeps)
    paths = proxy_paths(proxy, system, gp, y0, grid)
    A, _ = _sensitivity(system, H.to(y0), _proxy_field(system, gp, proxy), paths, grid, substeps)
    return ReadoutSensitivity(A=A, nodes=system.select_inputs(paths), paths=paths, grid=grid)


def _check_system(system) -> MisspecifiedSystem:
    """An autonomous system without inputs (for :func:`readout_sensitivity`; ``greedy`` and
    :func:`readout_information_gain` take systems with inputs and their controls)."""
    return check_system(system)


def _noise(criterion: ReadoutCriterion, gp: CorrectionGP, H: torch.Tensor, paths: torch.Tensor) -> tuple:
    """``(sigma_z (m,), where it came from)``."""
    m, d = H.shape
    if criterion.noise_std is not None:
        return torch.tensor(criterion.noise_std, dtype=paths.dtype, device=paths.device), "given"
    var = getattr(gp, "state_noise_", None)
    if isinstance(var, torch.Tensor) and var.numel() == d + m and bool(torch.isfinite(var).all() and (var > 0).all()):
        return var.detach().reshape(-1)[d:].sqrt().to(paths), "fitted"
    rms = (paths @ H.T).pow(2).mean(dim=(0, 1)).sqrt()
    rms = torch.where(rms > 0, rms, rms.max().clamp_min(1.0))
    return DEFAULT_NOISE_FRACTION * rms, "default"


class _ReadoutProblem:
    """Everything the readout engines need: sensitivities (whitened), the kernel, budget and partition."""

    def __init__(self, criterion, candidates, budget, system, times, gp, proxy, condition, partition, capacities,
                 tie_tol, executor=None, progress=False, controls=None) -> None:  # fmt: skip
        from ._common import check_budget, check_partition

        if not isinstance(criterion, ReadoutCriterion):
            raise InputError(f"criterion: expected a ReadoutCriterion, got {type(criterion).__name__}")
        self.tie_tol = float(tie_tol)
        self.system = check_system(system, controls, with_controls=True)
        self.readout = criterion.checked(self.system)
        self.kern = GPKernel(gp, input_dim=self.system.input_dim, condition=condition, system=self.system)
        kd = {"dtype": self.kern.dtype, "device": self.kern.device}
        self.candidates = check_candidates(candidates, self.system)
        n = self.candidates.shape[0]
        controls = self.system.check_controls(controls, n)
        controls = None if controls is None else controls.to(**kd)
        self.budget = check_budget(budget, n)
        self.partition = check_partition(partition, capacities, n, self.budget, self.kern.device)
        if times is None:
            raise InputError("times: expected the observation times (T,) of the readings, got None")
        self.times = check_times(times, **kd)
        self.proxy = choose_proxy(proxy, gp)
        self.substeps = criterion.substeps
        grid = _grid(self.times, self.substeps)
        self.theta = theta_uncertainty(self.system, gp)  # G's uncertain parameters, integrated out
        dynamics = self.system if self.theta is None else self.theta.centred
        paths = proxy_paths(self.proxy, dynamics, gp, self.candidates.to(**kd), grid, controls, executor, progress)
        H = self.readout.matrix.to(**kd)
        self.noise_std, self.noise_source = _noise(criterion, gp, H, paths)
        t = None if self.system.autonomous else grid.expand(n, -1)
        u = None if controls is None else controls.at(t)
        forcing = None if self.theta is None else self.theta.forcing(paths, t, u)
        field = _proxy_field(dynamics, gp, self.proxy)
        A, B = _sensitivity(dynamics, H, field, paths, grid, self.substeps, forcing, controls)
        T1 = self.times.numel() - 1
        whiten = self.noise_std.repeat(T1).reshape(1, -1, 1)
        A = A / whiten.unsqueeze(-1)  # whitened: unit noise
        Bt = None if B is None else self.theta.whitened_factor(B / whiten)
        nodes = self.system.select_inputs(paths, u)
        self.cov = ReadingsCovariance(self.kern, A, nodes, self.system.output_dim, Bt)
        self.proxies = paths[:, :: self.substeps]
        self.R = A.shape[1]
        self.domain = None
        if criterion.domain is not None:
            self.domain = DomainModel(self.kern, self.system, criterion.domain.domain, criterion.domain.size)

    @property
    def n(self) -> int:
        return self.candidates.shape[0]

    def threshold(self, best: float) -> float:
        return best - self.tie_tol * max(abs(best), 1.0)


def _plain(prob: _ReadoutProblem, feasible) -> tuple[list[int], list[float], int]:
    """Greedy with every candidate's conditional covariance kept and downdated after each pick (as
    :func:`._greedy._plain`, on the readings' covariance): Sigma_{c|S} -= W_c^T W_c, W = L_n^-1 Sigma_{n c | S}."""
    cov, R, N = prob.cov, prob.R, prob.n
    everyone = torch.arange(N, device=cov.A.device)
    Sig = cov.blocks(everyone)  # (N, R, R)
    U: list[torch.Tensor] = []  # rows (R, N, R) of the partial Cholesky factor of the picks' readings
    feas = feasible(prob)
    picks, gains, evaluations = [], [], 0
    p = 0 if cov.Bt is None else cov.Bt.shape[-1]
    M = torch.zeros(p, p, dtype=cov.A.dtype, device=cov.A.device)  # the picks' sum of Bt_c^T Bt_c
    for k in range(prob.budget):
        idx = torch.nonzero(feas.mask()).flatten()
        ld, C = logdet_identity_plus(Sig[idx], 1.0, "I + Sigma_{c|S} (readings)")
        evaluations += idx.shape[0]
        g = 0.5 * (ld - cov.theta_gains(idx, M))  # theta integrated out (:mod:`._readings_theta`)
        j = int(torch.nonzero(g >= prob.threshold(float(g.max())))[0, 0])
        n = int(idx[j])
        picks.append(n)
        gains.append(float(g[j]))
        feas.add(n)
        if p:
            M = M + cov.Bt[n].T @ cov.Bt[n]
        if k + 1 < prob.budget:
            cross = cov.cross(n, everyone)  # (R, N, R)
            for W in U:
                cross = cross - torch.einsum("ar,acs->rcs", W[:, n, :], W)
            W = torch.linalg.solve_triangular(C[j], cross.reshape(R, N * R), upper=False).reshape(R, N, R)
            U.append(W)
            Sig = Sig - torch.einsum("anb,anc->nbc", W, W)
    return picks, gains, evaluations


def _naive(prob: _ReadoutProblem, feasible) -> tuple[list[int], list[float], int]:
    """The reference: for every remaining candidate, a fresh log-determinant of the stacked readings of S + c."""
    feas = feasible(prob)
    picks, gains, evaluations, current = [], [], 0, 0.0
    for _ in range(prob.budget):
        idx = torch.nonzero(feas.mask()).flatten().tolist()
        total = torch.tensor([prob.cov.information(picks + [c]) for c in idx], dtype=prob.cov.A.dtype)
        evaluations += len(idx)
        j = int(torch.nonzero(total >= prob.threshold(float(total.max())))[0, 0])
        picks.append(idx[j])
        gains.append(float(total[j]) - current)
        current = float(total[j])
        feas.add(idx[j])
    return picks, gains, evaluations


def readout_greedy(prob: _ReadoutProblem, method: str, feasible) -> DesignResult:
    """The greedy design for the readings' criterion (``greedy(..., criterion=ReadoutCriterion(...))``)."""
    start = time.perf_counter()
    extra = {}
    with torch.no_grad():
        if prob.domain is not None:
            terms = readings_terms(prob.domain, prob.cov.A, prob.cov.nodes, prob.cov.Bt)
            picks, gains, evaluations, extra = domain_greedy(prob, method, False, feasible, terms)
        else:
            picks, gains, evaluations = (_naive if method == "naive" else _plain)(prob, feasible)
    dev = prob.candidates.device
    idx = torch.tensor(picks, dtype=torch.long, device=dev)
    info = {
        "criterion": "readout",
        "readout": "; ".join(prob.readout.describe()),
        "noise_std": [float(s) for s in prob.noise_std],
        "noise_source": prob.noise_source,
        "substeps": prob.substeps,
        "conditioned": prob.kern.num_conditioned,
        "proxy": prob.proxy,
        **extra,
    }
    if prob.domain is not None:
        info["criterion"] = "readout over the domain"
    if prob.theta is not None:
        info["parameters"] = f"integrated out ({prob.theta.source})"
    return DesignResult(
        indices=idx,
        gains=torch.tensor(gains, dtype=prob.kern.dtype, device=dev),
        information_gain=float(sum(gains)),
        points=prob.candidates[idx],
        method=method,
        evaluations=evaluations,
        proxies=prob.proxies[idx.to(prob.proxies.device)].to(dev),
        elapsed=time.perf_counter() - start,
        diagnostics=info,
    )


def readout_information_gain(
    indices,
    candidates,
    *,
    system: MisspecifiedSystem,
    times,
    gp: CorrectionGP,
    criterion: ReadoutCriterion,
    condition: bool | None = None,
    proxy: str | None = None,
    controls=None,
) -> float:
    """The information (nats) about F of the readings of the experiments ``candidates[indices]``, one dense
    log-determinant ``(1 / 2) logdet(I + A K A^T)`` of their stacked whitened readings (see the module docstring);
    where G has uncertain parameters, with them integrated out, ``(1 / 2) logdet(I + A K A^T + B S B^T) -
    (1 / 2) logdet(I + B S B^T)`` (:mod:`torchmisspec.design._readings_theta`).

    Args:
        indices: the chosen candidates (or a :class:`DesignResult`); empty: 0.
        candidates: ``(N, d)``.
        system: the system, as for :func:`~torchmisspec.design.greedy`.
        times: the observation times, as for ``greedy``.
        gp: the correction GP, as for ``greedy``.
        criterion: the :class:`ReadoutCriterion` (readout, noise, quadrature).
        condition: whether the gains are conditioned on the GP's data, as for ``greedy``.
        proxy: the proxies' dynamics (``"known"`` or ``"corrected"``), as for ``greedy``.
        controls: for a system with inputs, one profile per candidate, as for ``greedy``.
    """
    if isinstance(indices, DesignResult):
        indices = indices.indices
    if isinstance(indices, torch.Tensor):
        indices = indices.reshape(-1).tolist()
    cand = check_candidates(candidates, check_system(system, controls, with_controls=True))
    if len(indices) == 0:
        return 0.0
    idx = list(check_indices(indices, cand.shape[0], "indices"))
    prob = _ReadoutProblem(criterion, cand, 1, system, times, gp, proxy, condition, None, None, 0.0, controls=controls)
    with torch.no_grad():
        return prob.cov.information(idx)


def readout_design(criterion: ReadoutCriterion, options: dict, feasible) -> DesignResult:
    """``greedy`` with a :class:`ReadoutCriterion`: the readings' information through the ODE
    (:mod:`torchmisspec.design._readings`); ``options``: greedy's keywords (those it does not take refused by name);
    ``feasible``: greedy's feasibility tracker (the picks left, a partition's capacities)."""
    o = options
    proxies, method = o["proxies"], o["method"]
    tie_tol = o["tie_tol"]
    given = {
        "proxies": proxies is not None,
        "method='stochastic'": method == "stochastic",
    }
    refused = [name for name, on in given.items() if on]
    if refused:
        raise InputError(
            f"criterion=ReadoutCriterion(...): expected none of {refused}, got them; the readings' criterion "
            "computes its own proxies on a finer grid and runs the plain or naive engine (method='lazy' runs the "
            "plain one)"
        )
    if isinstance(tie_tol, bool) or not isinstance(tie_tol, (int, float)) or not 0 <= tie_tol < 1e-3:
        raise InputError(f"tie_tol: expected a number in [0, 1e-3), got {tie_tol!r}")
    prob = _ReadoutProblem(
        criterion, o["candidates"], o["budget"], o["system"], o["times"], o["gp"], o["proxy"], o["condition"],
        o["partition"], o["capacities"], tie_tol, o["executor"], o["progress"], o["controls"],
    )  # fmt: skip
    return readout_greedy(prob, method, feasible)


def campaign_criterion(criterion: str, data, gp: CorrectionGP, system: MisspecifiedSystem):
    """A campaign's criterion: ``criterion``, or, when its data carry a readout (experiments that read combinations
    H y of the states), the readings' criterion through the ODE (:class:`ReadoutCriterion`: their information about
    F, or with a :class:`DomainCriterion` the variance of F over D they remove): such experiments give no derivative
    samples, so the paper's criteria would score what is not measured. The readings' noise is the fit's estimate
    (``gp.state_noise_``), else the one the data show (``estimate_observed_noise``), else the default."""
    readout = None if data is None else data.readout
    if readout is None:
        return criterion
    over = criterion if isinstance(criterion, DomainCriterion) else None
    noise = None
    var = getattr(gp, "state_noise_", None)
    d, m = system.state_dim, readout.num_readings
    if not (isinstance(var, torch.Tensor) and var.numel() == d + m):
        from ..learning.samples._gp_in_time import estimate_observed_noise

        std = estimate_observed_noise(data)
        if std is not None and std.numel() == d + m and bool((std[d:] > 0).all()):
            noise = tuple(float(v) for v in std[d:])
    return ReadoutCriterion(readout, noise_std=noise, domain=over)
