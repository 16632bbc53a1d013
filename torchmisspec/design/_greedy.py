"""Greedy maximisation of the proxy information gain (paper §4.3, Algorithms 1 and 2).

Notation: candidate c has T proxy points P_c (its known-model trajectory restricted to the correction inputs),
S is the selected set, sigma^2 the noise variance, K_ab = k(P_a, P_b). The marginal gain of c given S is

    Delta(c | S) = (d_out / 2) logdet(I_T + Sigma_{c|S} / sigma^2),
    Sigma_{c|S}  = K_cc - K_cS (K_SS + sigma^2 I)^-1 K_Sc          (T x T conditional covariance),

because logdet(K_{S+c} + sigma^2 I) = logdet(K_SS + sigma^2 I) + logdet(Sigma_{c|S} + sigma^2 I). Three engines
return the same picks:

* ``"lazy"`` (Algorithm 2, Minoux 1978): stale gains are upper bounds (submodularity); only the candidates whose
  bound could still win are re-evaluated, in batches that double while many bounds stay above the best gain. One
  exact evaluation is v = L_S^-1 K_Sc (a triangular solve against the Cholesky factor L_S of K_SS + sigma^2 I) and a
  T x T Cholesky. L_S is grown by one block row per pick ([v_n^T, chol(Sigma_{n|S} + sigma^2 I)], a Schur-complement
  update), never refactorized. Memory O(N T^2 + (K T)^2).
  Screening (``screen``, on by default from 1000 candidates): smooth kernels make every gain fall at every pick,
  so plain stale bounds stay above the best and lazy greedy re-evaluates most candidates. A low-rank (Nystrom)
  feature model of the kernel on all proxy points then gives tighter, still rigorous, upper bounds at cost
  ~ r^2 T instead of (|S| T)^2 T (see :mod:`._screening`); only candidates whose feature bound can still win get an
  exact evaluation. The exact values decide every pick, so the picks are those of plain greedy. Features are built
  only when a modest rank (memory ``8 N T r`` bytes, by default at most 256 MiB or 64 features, whichever is more)
  makes the bounds tight;
  otherwise the engine falls back to the plain lazy bounds by itself.
* ``"plain"`` (Algorithm 1, vectorised): keeps Sigma_{c|S} for every candidate ``(N, T, T)`` and downdates it
  after each pick with the rows of the partial Cholesky factor, W_c = L_nn^-1 Sigma_{n,c|S}; all gains of a step are
  one batched Cholesky. Memory O(N T^2 K) (the factor rows of all candidates), so prefer ``"lazy"`` for large N.
* ``"stochastic"`` (Mirzasoleiman et al. 2015): lazy greedy restricted, at each pick, to a uniform random draw of
  ceil((N / K) ln(1 / epsilon)) of the candidates still available; stale bounds, screening and the exact gains work
  as in ``"lazy"`` inside the draw. E[f] >= (1 - 1/e - epsilon) f(optimum) for a cardinality budget.
* ``"naive"``: Algorithm 1 literally, the reference: for every remaining candidate a fresh log-determinant of the
  whole (|S| + 1) T covariance, every step (batched over candidates, chunked).

Ties. Gains that agree to ``tie_tol`` (relative, on the scale max(|best gain|, 1 nat)) are treated as equal and
the lowest candidate index wins. Symmetric candidate sets produce exact mathematical ties whose computed values
differ in the last bits between engines; the tolerance makes all three engines pick the same set.
"""

from __future__ import annotations

import math
import time

import torch

from .._errors import InputError
from .._validation import check_flag, progress_bar
from ..gp import CorrectionGP
from ..parallel import adaptive_threads, check_executor
from ..systems import MisspecifiedSystem
from ._common import (
    DesignResult,
    GPKernel,
    check_budget,
    check_candidates,
    check_partition,
    check_proxies,
    check_system,
    check_times,
    logdet_identity_plus,
)
from ._domain import CRITERIA, DomainModel, domain_greedy
from ._options import DomainCriterion, Engine, Partition, Proxy, check_stochastic, checked_criterion, checked_options
from ._proxy import choose_proxy, proxy_paths
from ._readings import ReadoutCriterion, readout_design
from ._screening import CHUNK_BYTES, LowRank

__all__ = ["greedy"]

METHODS = ("lazy", "plain", "naive", "stochastic")
SCREEN_MIN_CANDIDATES = 1000  # screen="auto" uses the low-rank bounds from this many candidates on
SCREEN_MEMORY = 256 * 2**20  # bytes for the features of all proxy points (sets the default max_rank) ...
SCREEN_MIN_RANK = 64  # ... but never fewer features than this: at 10^5 candidates 256 MiB allow only 16, too few
# for tight bounds on a smooth kernel, and lazy greedy then took 185 s and 11 GB instead of 13 s and 2.5 GB


class _Problem:
    """Validated inputs shared by the engines: proxy points, kernel, budget, partition."""

    def __init__(
        self,
        candidates,
        budget,
        system,
        times,
        gp,
        partition,
        capacities,
        proxies,
        tie_tol,
        *,
        condition=None,
        proxy=None,
        criterion="information",
        domain=None,
        domain_size=None,
        controls=None,
        executor=None,
        progress=False,
    ) -> None:
        if isinstance(tie_tol, bool) or not isinstance(tie_tol, (int, float)) or not 0 <= tie_tol < 1e-3:
            raise InputError(f"tie_tol: expected a number in [0, 1e-3), got {tie_tol!r}")
        self.tie_tol = float(tie_tol)
        self.system = check_system(system, controls, with_controls=True)
        self.criterion = criterion
        if criterion not in CRITERIA:
            raise InputError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
        self.kern = GPKernel(gp, input_dim=self.system.input_dim, condition=condition, system=self.system)
        self.domain = None
        if criterion == "domain":
            self.domain = DomainModel(self.kern, self.system, domain, domain_size)
        self.candidates = check_candidates(candidates, self.system)
        n = self.candidates.shape[0]
        controls = self.system.check_controls(controls, n)  # one profile per candidate (a system with inputs)
        self.budget = check_budget(budget, n)
        self.partition = check_partition(partition, capacities, n, self.budget, self.kern.device)
        kd = {"dtype": self.kern.dtype, "device": self.kern.device}
        proxy = choose_proxy(proxy, gp)
        self.proxy = proxy if proxies is None else "given"
        if proxies is None:
            if times is None:
                raise InputError(
                    "times: expected the observation times (T,) to compute the proxy trajectories, got "
                    "None (pass times=..., or proxies=(N, T, d))"
                )
            self.times = check_times(times, **kd)
            cands = self.candidates.to(**kd)
            self.proxies = proxy_paths(proxy, self.system, gp, cands, self.times, controls, executor, progress)
        else:
            self.times = None if times is None else check_times(times, **kd)
            self.proxies = check_proxies(proxies, n, self.system, self.times, **kd)
        # (N, T, d_in), or (N, d_out T, d_in + 1) when each output is informed by its own data (GPKernel.expand)
        if controls is not None and self.times is None:
            raise InputError(
                "times: expected the observation times with controls (the inputs at those times), got None"
            )
        u = None if controls is None else controls.at(self.times.expand(n, -1)).to(**kd)  # (N, T, m)
        self.points = self.kern.expand(self.system.select_inputs(self.proxies, u)).contiguous()
        self.d_out = self.kern.multiplicity(self.system.output_dim)  # the factor on (1 / 2) logdet

    @property
    def n(self) -> int:
        return self.points.shape[0]

    @property
    def T(self) -> int:
        return self.points.shape[1]

    def threshold(self, best: float) -> float:
        """Gains at or above this value tie with ``best``."""
        return best - self.tie_tol * max(abs(best), 1.0)

    def result(
        self, picks: list[int], gains: list[float], method: str, evaluations: int, elapsed: float, info: dict
    ) -> DesignResult:
        dev = self.candidates.device
        idx = torch.tensor(picks, dtype=torch.long, device=dev)
        g = torch.tensor(gains, dtype=self.kern.dtype, device=dev)
        return DesignResult(
            indices=idx,
            gains=g,
            information_gain=float(sum(gains)),
            points=self.candidates[idx],
            method=method,
            evaluations=evaluations,
            proxies=self.proxies[idx.to(self.proxies.device)].to(dev),
            elapsed=elapsed,
            diagnostics=info,
        )


class _Feasible:
    """Which candidates may still be picked: not selected, region not full (partition matroid)."""

    def __init__(self, prob: _Problem) -> None:
        self.selected = torch.zeros(prob.n, dtype=torch.bool, device=prob.kern.device)
        self.partition = prob.partition
        if self.partition is not None:
            self.region, self.caps = self.partition
            self.counts = torch.zeros_like(self.caps)

    def mask(self) -> torch.Tensor:
        ok = ~self.selected
        if self.partition is not None:
            ok &= (self.counts < self.caps)[self.region]
        return ok

    def add(self, i: int) -> None:
        self.selected[i] = True
        if self.partition is not None:
            self.counts[self.region[i]] += 1


def _first_at_least(values: torch.Tensor, mask: torch.Tensor, thr: float) -> int:
    return int(torch.nonzero(mask & (values >= thr))[0, 0])


# ------------------------------------------------------------------------------------------------ lazy greedy
def sample_size(n: int, budget: int, epsilon: float) -> int:
    """Stochastic greedy's candidates per step, ceil((n / K) ln(1 / epsilon)) (Mirzasoleiman et al. 2015)."""
    return min(n, math.ceil(n / budget * math.log(1.0 / epsilon)))


class _LazyGreedy:
    """Lazy (or stochastic) greedy's state: stale upper bounds, the growing factor L_S and the optional screening."""

    def __init__(self, prob: _Problem, batch_size: int, screen: bool, max_rank: int, sample, generator) -> None:
        self.prob, self.batch_size, self.sample, self.generator = prob, batch_size, sample, generator
        self.kern, self.P, self.T, self.K, self.half = prob.kern, prob.points, prob.T, prob.budget, 0.5 * prob.d_out
        P, K, T, N = self.P, self.K, self.T, prob.n
        self.d_in, self.noise, self.dev = P.shape[-1], self.kern.noise, P.device
        self.Kcc = self.kern.block_diagonal(P)  # (N, T, T), kept: every exact evaluation needs its candidate's block
        ld0, _ = logdet_identity_plus(self.Kcc.clone(), self.noise, "I + K_cc / noise_variance")
        self.ub = self.half * ld0  # (N,) upper bound on every candidate's current gain (exact for S = {})
        # level of ub in the current step: 0 stale (an earlier step's bound), 1 fresh feature bound, 2 fresh exact
        self.level = torch.full((N,), 2, dtype=torch.int8, device=self.dev)
        self.L = P.new_zeros(K * T, K * T)  # Cholesky factor of K_SS + sigma^2 I, grown block by block
        self.PS = P.new_empty(K * T, self.d_in)  # proxy points of S
        low = LowRank(prob, max_rank) if screen and K > 1 else None
        self.info = {} if low is None else {"rank": low.rank, "screening": low.useful}
        self.low = low if low is not None and low.useful else None
        if sample is not None:
            self.info["sample_size"] = sample
        self.evaluations, self.n_bounds = N, 0
        self.neg_inf = torch.tensor(-math.inf, dtype=P.dtype, device=self.dev)

    def evaluate(self, idx: torch.Tensor, m: int, Lm: torch.Tensor):
        """Exact gains of candidates ``idx (b,)`` given the m selected proxy points (factor Lm): gains, V, chol."""
        T, d_in = self.T, self.d_in
        Sig = self.Kcc[idx]
        V = None
        if m > 0:
            b = idx.shape[0]
            KSc = self.kern(self.PS[:m], self.P[idx].reshape(b * T, d_in))  # (m, b T)
            V = torch.linalg.solve_triangular(Lm, KSc, upper=False).reshape(m, b, T).permute(1, 0, 2)
            Sig = Sig - V.transpose(1, 2) @ V
        ld, C = logdet_identity_plus(Sig, self.noise, "I + Sigma_{c|S} / noise_variance")
        return self.half * ld, V, C

    def draw(self, avail: torch.Tensor) -> torch.Tensor:
        """Stochastic greedy: only a random subset of ``sample`` of the available candidates competes this step."""
        if self.sample is None or self.sample >= int(avail.sum()):
            return avail
        gen = self.generator
        ids = avail.nonzero().squeeze(1)
        # drawn on the generator's own device (a CPU or a GPU generator), the same draws for the same seed there
        drawn = ids[torch.randperm(ids.shape[0], generator=gen, device=gen.device)[: self.sample].to(self.dev)]
        avail = torch.zeros_like(avail)
        avail[drawn] = True
        return avail

    def tighten(self, open_: torch.Tensor, b_bound: int, m: int) -> None:
        """Replace the top stale bounds by the (tighter, still rigorous) feature bounds of the screening."""
        sel = open_ & (self.level == 0)
        idx = torch.topk(torch.where(sel, self.ub, self.neg_inf), min(b_bound, int(sel.sum()))).indices
        self.ub[idx] = torch.minimum(self.ub[idx], self.low.bounds(idx, m))
        self.level[idx] = 1
        self.n_bounds += idx.shape[0]

    def search(self, avail: torch.Tensor, m: int, Lm: torch.Tensor, use_low: bool) -> tuple[int, list[tuple]]:
        """One pick: re-evaluate the bounds that could still win (doubling batches) until the best exact gain wins."""
        prob, ub, level = self.prob, self.ub, self.level
        batches: list[tuple] = []  # (idx, V, C) of this step's exact evaluations; only the pick's rows are kept
        b_exact, b_bound = self.batch_size, max(64, self.batch_size)
        while True:
            done = avail & (level == 2)
            best = float(ub[done].max()) if bool(done.any()) else -math.inf
            thr = prob.threshold(best) if best > -math.inf else -math.inf
            open_ = avail & (level < 2) & (ub >= thr)
            if not bool(open_.any()):
                break
            vals = torch.where(open_, ub, self.neg_inf)
            top = int(torch.argmax(vals))
            if use_low and int(level[top]) == 0:  # tighten the stale bounds at the top first
                self.tighten(open_, b_bound, m)
                b_bound *= 2
                continue
            cap = max(1, CHUNK_BYTES // (8 * max(m, 1) * self.T))
            idx = torch.topk(vals, min(b_exact, int(open_.sum()), cap)).indices
            g, V, C = self.evaluate(idx, m, Lm)
            self.evaluations += idx.shape[0]
            ub[idx] = g
            level[idx] = 2
            batches.append((idx, V, C))
            b_exact *= 2  # many bounds above the best: widen the next batch
        return _first_at_least(ub, done, thr), batches

    def factor_row(self, n: int, batches: list[tuple], m: int, Lm: torch.Tensor):
        """The pick's v = L_S^-1 K_Sn and chol(I + Sigma_{n|S} / sigma^2), from its latest exact evaluation."""
        for idx, Vb, Cb in reversed(batches):  # a few batches per step
            hit = (idx == n).nonzero()
            if hit.numel():
                j = int(hit[0, 0])
                return (None if Vb is None else Vb[j]), Cb[j]
        # step 0: the initial pass kept only the gains
        _, Vb, Cb = self.evaluate(torch.tensor([n], device=self.dev), m, Lm)
        return (None if Vb is None else Vb[0]), Cb[0]

    def grow(self, n: int, m: int, v, C) -> None:
        """Grow L_S by the block row [v_n^T, chol(Sigma_{n|S} + sigma^2 I)] (a Schur-complement update)."""
        T = self.T
        if v is not None:
            self.L[m : m + T, :m] = v.T
        self.L[m : m + T, m : m + T] = math.sqrt(self.noise) * C
        self.PS[m : m + T] = self.P[n]
        if self.low is not None:
            self.low.add(n)


def _lazy(
    prob: _Problem,
    batch_size: int,
    progress: bool,
    screen: bool,
    max_rank: int,
    sample: int | None = None,
    generator: torch.Generator | None = None,
) -> tuple[list[int], list[float], int, dict]:
    """Lazy greedy (Algorithm 2), or stochastic greedy with ``sample`` candidates drawn per pick."""
    eng = _LazyGreedy(prob, batch_size, screen, max_rank, sample, generator)
    K, T, low = prob.budget, prob.T, eng.low
    feas = _Feasible(prob)
    picks, gains = [], []
    bar = progress_bar(progress, K, f"{'stochastic' if sample else 'lazy'} greedy (N={prob.n})", "pick")
    for k in range(K):
        m = k * T
        avail = eng.draw(feas.mask())
        if k > 0:
            eng.level.zero_()
        # a feature bound costs ~ r^2 T, an exact gain ~ m^2 T: screen only once the exact gains cost more
        use_low = low is not None and m * m > 2 * low.rank * low.rank and low.slack(m) <= 1e-2 * abs(gains[-1])
        Lm = eng.L[:m, :m].contiguous()
        n, batches = eng.search(avail, m, Lm, use_low)
        v, C = eng.factor_row(n, batches, m, Lm)
        picks.append(n)
        gains.append(float(eng.ub[n]))
        feas.add(n)
        if k + 1 < K:
            eng.grow(n, m, v, C)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(gain=f"{gains[-1]:.4g}", evals=eng.evaluations)
    if bar is not None:
        bar.close()
    if low is not None:
        eng.info.update(residual=low.e_max, bounds=eng.n_bounds)
    return picks, gains, eng.evaluations, eng.info


# ------------------------------------------------------------------------------------- plain (vectorised) greedy
def _plain(prob: _Problem, progress: bool) -> tuple[list[int], list[float], int, dict]:
    kern, P, T, K, half, N = prob.kern, prob.points, prob.T, prob.budget, 0.5 * prob.d_out, prob.n
    d_in, noise = P.shape[-1], kern.noise
    Sig = kern.block_diagonal(P)  # (N, T, T): Sigma_{c|S}, downdated after every pick
    U = P.new_empty(max(K - 1, 0) * T, N, T)  # rows of the partial Cholesky factor: L_S^-1 K_{S, c} for every c
    L = P.new_zeros(K * T, K * T)  # L_S itself (its block rows are gathered from U), kept for symmetry / checks
    flat = P.reshape(N * T, d_in)
    feas = _Feasible(prob)
    evaluations = 0
    picks, gains = [], []
    bar = progress_bar(progress, K, f"greedy (N={N})", "pick")
    for k in range(K):
        m = k * T
        avail = feas.mask()
        idx = torch.nonzero(avail).flatten()
        ld, C = logdet_identity_plus(Sig[idx], noise, "I + Sigma_{c|S} / noise_variance")
        evaluations += idx.shape[0]
        g = half * ld
        best = float(g.max())
        j = _first_at_least(g, torch.ones_like(avail[idx]), prob.threshold(best))
        n = int(idx[j])
        picks.append(n)
        gains.append(float(g[j]))
        feas.add(n)
        if k + 1 < K:
            Lnn = math.sqrt(noise) * C[j]  # chol(Sigma_{n|S} + sigma^2 I)
            cross = kern(P[n], flat)  # (T, N T) = K_{n, all}
            if m > 0:
                Un = U[:m, n, :]  # (m, T) = L_S^-1 K_{S, n}
                cross = cross - Un.T @ U[:m].reshape(m, N * T)  # Sigma_{n, c | S} for all c
                L[m : m + T, :m] = Un.T
            L[m : m + T, m : m + T] = Lnn
            W = torch.linalg.solve_triangular(Lnn, cross, upper=False).reshape(T, N, T)
            U[m : m + T] = W
            Sig -= torch.einsum("anb,anc->nbc", W, W)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(gain=f"{gains[-1]:.4g}")
    if bar is not None:
        bar.close()
    return picks, gains, evaluations, {}


# ---------------------------------------------------------------------------------------------- naive reference
def _naive(prob: _Problem, progress: bool, chunk_bytes: int = 64 * 2**20) -> tuple[list[int], list[float], int, dict]:
    """Algorithm 1 literally: a fresh log-determinant of the whole (|S| + 1) T covariance per candidate per step."""
    kern, P, T, K, half = prob.kern, prob.points, prob.T, prob.budget, 0.5 * prob.d_out
    d_in, noise = P.shape[-1], kern.noise
    feas = _Feasible(prob)
    evaluations, current = 0, 0.0
    picks, gains = [], []
    bar = progress_bar(progress, K, f"naive greedy (N={prob.n})", "pick")
    for k in range(K):
        m = (k + 1) * T
        idx = torch.nonzero(feas.mask()).flatten()
        PS = P[picks].reshape(k * T, d_in)
        chunk = max(1, chunk_bytes // (8 * m * m))
        values = []
        for s in range(0, idx.shape[0], chunk):
            c = idx[s : s + chunk]
            pts = torch.cat([PS.expand(c.shape[0], k * T, d_in), P[c]], dim=1)  # (b, (k + 1) T, d_in)
            ld, _ = logdet_identity_plus(kern(pts), noise, "I + K / noise_variance")
            values.append(half * ld)
        evaluations += idx.shape[0]
        total = torch.cat(values)  # information gain of S + c for every remaining c
        j = _first_at_least(total, torch.ones_like(total, dtype=torch.bool), prob.threshold(float(total.max())))
        n = int(idx[j])
        picks.append(n)
        gains.append(float(total[j]) - current)
        current = float(total[j])
        feas.add(n)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return picks, gains, evaluations, {}


# ----------------------------------------------------------------------------------------------------- public
@adaptive_threads()
def greedy(
    candidates,
    budget: int,
    *,
    system: MisspecifiedSystem,
    times=None,
    gp: CorrectionGP,
    method: str = "lazy",
    criterion: str | DomainCriterion | ReadoutCriterion = "information",
    partition: Partition | None = None,
    proxy: Proxy | None = None,
    condition: bool | None = None,
    controls=None,
    engine: Engine | None = None,
    progress: bool = False,
    executor=None,
) -> DesignResult:
    """Choose ``budget`` initial conditions among ``candidates`` maximising the proxy information gain.

    The criterion is the information gain (nats, real-Gaussian convention: half the paper's complex-convention
    numbers, same picks) about F of noisy correction samples along the known model's trajectories from the chosen
    initial conditions, observed at ``times`` (see :func:`information_gain`). It is monotone and submodular (paper
    Lemma 1), and greedy maximisation comes with these guarantees, relative to the best set of the same size for
    the *proxy* criterion:

    * cardinality budget: ``f(greedy) >= (1 - 1/e) f(optimum)`` (Nemhauser, Wolsey, Fisher 1978);
    * partition-matroid budget (:class:`Partition`: at most ``capacities[r]`` picks in region r): plain greedy
      guarantees only ``f(greedy) >= 1/2 f(optimum)`` (Fisher, Nemhauser, Wolsey 1978); the (1 - 1/e) algorithms
      for matroids (continuous greedy, Calinescu et al. 2007) are not implemented.

    * stochastic greedy (``method="stochastic"``, Mirzasoleiman et al. 2015, "Lazier than lazy greedy"), cardinality
      budget only: each pick is the best of ``ceil((N / K) ln(1 / epsilon))`` candidates drawn at random (lazy
      bounds inside the draw), and ``E[f(stochastic)] >= (1 - 1/e - epsilon) f(optimum)``. Its cost per pick does
      not grow with N beyond the draw, for 10^5 candidates and more; on a smooth kernel its gain is within a
      fraction of a percent of lazy greedy's (BENCHMARKS.md, ``scripts/benchmark_large_design.py``).

    Lazy greedy (``method="lazy"``, the default, Minoux 1978) returns exactly the set plain greedy returns (same picks,
    same order) while evaluating far fewer gains; ``method="naive"`` is the literal Algorithm 1 with fresh
    log-determinants, kept as the reference. Theorem 1 of the paper bounds how far the proxy criterion is from the
    true one (:func:`proxy_gap_bound`).

    Args:
        candidates: ``(N, d)`` candidate initial conditions (full states).
        budget: number of experiments K to choose, 1 <= K <= N (and <= what the capacities allow).
        system: the misspecified system (known model G, correction inputs and outputs; d_out = system.output_dim).
        times: ``(T,)`` strictly increasing observation times; the first is the time of the initial condition.
            May be omitted when ``Proxy(paths=...)`` is given.
        gp: :class:`CorrectionGP` with a shared kernel whose hyperparameters are set (given, or fitted on earlier
            data); its kernel is evaluated on the proxy points restricted to ``system.correction_inputs``.
        method: ``"lazy"`` (Algorithm 2, the default), ``"plain"`` (Algorithm 1, vectorised over candidates) or
            ``"naive"`` (Algorithm 1 with fresh log-determinants, the reference): all three pick the same set; or
            ``"stochastic"`` (the best of a random draw per pick, see above; :class:`Engine`'s ``epsilon`` and
            ``generator``).
        criterion: ``"information"`` (the paper's: information about F anywhere, monotone submodular, the
            guarantees above); a :class:`DomainCriterion` (or ``"domain"``, its defaults): the mean posterior
            variance of F over a box D that the samples remove, which aims the design at D but is not submodular
            (no (1 - 1/e) guarantee; ``method="lazy"`` then evaluates every remaining gain, the same picks as
            ``"plain"``); or a :class:`~torchmisspec.design.ReadoutCriterion`: experiments that read only
            combinations H y of the states (a :class:`~torchmisspec.Readout`), scored by the information about F
            of their noisy readings, linearised through the ODE along the proxy paths (monotone submodular: the
            guarantees above hold; see :mod:`torchmisspec.design._readings`). It computes its own proxies (on a
            finer grid), takes conditioning, both proxy dynamics and partitions, and refuses ``Proxy(paths=...)``,
            ``controls`` and ``method="stochastic"``; ``"lazy"`` and ``"plain"`` run its vectorised engine,
            ``"naive"`` the reference.
        partition: a :class:`Partition` (a region label per candidate and the most picks per region), or ``None``
            for a cardinality budget.
        proxy: a :class:`Proxy`: the trajectories the samples are predicted along, ``"known"`` (G alone) or
            ``"corrected"`` dynamics, or given paths (e.g. the agnostic design's constant ones). Default: corrected
            for a fitted GP, known otherwise. ``result.diagnostics["proxy"]`` says which.
        condition: condition every gain on the GP's training samples (with their noise, per sample where known):
            the marginal gain of a candidate is then its information given the data already collected plus the
            picks so far, and candidates whose trajectories revisit measured states gain little. Default: when the
            GP is fitted (an unfitted prior holds no data: nothing changes). ``result.diagnostics["conditioned"]``
            is the number of samples conditioned on.
        controls: for a system with inputs u(t), each candidate's input profile (a
            :class:`~torchmisspec.signals.Controls` of N profiles): a candidate experiment is an initial state and a
            profile (repeat a state with several profiles to choose among profiles); the proxies run under them and
            the samples' inputs include u where F depends on it. ``criterion="information"`` only.
        engine: an :class:`Engine`: lazy greedy's batches and low-rank screening, the tie tolerance, stochastic
            greedy's ``epsilon`` and ``generator`` (default ``Engine()``).
        progress: show tqdm progress bars over the proxies' chunks (many candidates) and the picks.
        executor: a ``concurrent.futures.Executor`` that solves the proxy trajectories (chunks of ``PROXY_CHUNK``
            candidates, :mod:`torchmisspec.parallel`), or ``None`` (here): the same design either way.

    Memory: ``"lazy"`` O(N T^2 + (K T)^2 + N T r) (r features when screening); ``"plain"`` O(N T^2 K), about
    ``8 N K T^2`` bytes, so 1.6 GB for N = 10,000, K = 50, T = 20; ``"naive"`` O(N T^2 + chunk).

    Returns:
        :class:`DesignResult` (indices in pick order, marginal gains, total information gain, points, ...).

    Raises:
        BudgetError: budget < 1, > N, or more than the capacities allow.
        InputError / ShapeError: bad candidates, times, proxy paths, partition, or a GP without hyperparameters.
    """
    if method not in METHODS:
        raise InputError(f"method: expected one of {METHODS}, got {method!r}")
    criterion, domain = checked_criterion(criterion)
    partition, proxy, engine = checked_options(partition, proxy, engine)
    check_stochastic(method, engine, partition, criterion)
    regions, capacities = (None, None) if partition is None else (partition.regions, partition.capacities)
    if isinstance(criterion, ReadoutCriterion):
        options = dict(
            candidates=candidates, budget=budget, system=system, times=times, gp=gp, method=method,
            partition=regions, capacities=capacities, proxies=proxy.paths, tie_tol=engine.tie_tol,
            condition=condition, proxy=proxy.dynamics, controls=controls,
            executor=executor, progress=progress,
        )  # fmt: skip
        return readout_design(criterion, options, _Feasible)
    prob = _Problem(
        candidates, budget, system, times, gp, regions, capacities, proxy.paths, engine.tie_tol,
        condition=condition, proxy=proxy.dynamics, criterion=criterion, domain=domain.domain,
        domain_size=domain.size, controls=controls, executor=check_executor(executor),
        progress=check_flag(progress, "progress"),
    )  # fmt: skip
    start = time.perf_counter()
    with torch.no_grad():
        picks, gains, evals, info = _run(prob, method, engine, progress)
    info = {**info, "conditioned": prob.kern.num_conditioned, "proxy": prob.proxy, "criterion": prob.criterion}
    return prob.result(picks, gains, method, evals, time.perf_counter() - start, info)


def _run(prob: _Problem, method: str, engine: Engine, progress: bool) -> tuple[list[int], list[float], int, dict]:
    """The engine ``method`` on the validated problem: picks, gains, evaluations, diagnostics."""
    if prob.domain is not None:
        return domain_greedy(prob, method, progress, _Feasible)
    screen = prob.n >= SCREEN_MIN_CANDIDATES if engine.screen == "auto" else engine.screen
    max_rank = engine.max_rank
    if max_rank is None:
        max_rank = int(min(1024, max(SCREEN_MIN_RANK, SCREEN_MEMORY // (8 * prob.n * prob.T))))
    batch_size = int(engine.batch_size)
    if method == "lazy":
        return _lazy(prob, batch_size, progress, bool(screen), int(max_rank))
    if method == "stochastic":
        gen = torch.Generator().manual_seed(0) if engine.generator is None else engine.generator
        epsilon = float(engine.epsilon)
        draw = sample_size(prob.n, prob.budget, epsilon)
        picks, gains, evals, info = _lazy(prob, batch_size, progress, bool(screen), int(max_rank), draw, gen)
        info["epsilon"] = epsilon
        return picks, gains, evals, info
    if method == "plain":
        return _plain(prob, progress)
    return _naive(prob, progress)
