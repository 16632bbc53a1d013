"""The paper's studies: error of the learned correction against the number of experiments, over realizations.

* :func:`linear_study` is paper Fig 5 (§5.2): on paper_linear with the 13 x 13 candidate grid, the integrated error
  of F_hat over D for the designed set + misspecified GP, random sets + misspecified GP, and the designed set + a
  fully data-driven GP (no known part), with the energies of F and G + F as reference lines.
* :func:`gravity_study` is paper Fig 8 (§5.3): on paper_gravity with 300 candidates, the mean squared error of
  F_hat over D for the agnostic design (ignores G) and the misspecified-aided design, and random sets.

A realization draws new observation noise (and new random sets); the designs depend only on the prior and are
computed once (greedy designs are nested, so the design of size K is the first K picks of the largest one). The
true trajectories of every candidate are simulated once and reused. Every GP is the prior
conditioned on the samples (:meth:`~torchmisspec.CorrectionGP.condition`: the paper's hyperparameters, not
re-learned).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .. import design as _design
from .._errors import InputError
from .._validation import check_positive_int, progress_bar
from ..data import simulate
from ..design import candidates as _candidates
from ..gp import CorrectionGP
from ..metrics import box_grid, integrated_norm, mean_and_standard_error
from ..systems import MisspecifiedSystem, paper_gravity, paper_linear
from . import _setup

__all__ = ["StudyResult", "linear_study", "gravity_study", "sequential_study"]


@dataclass
class StudyResult:
    """Errors of several strategies against the number of experiments K, over realizations.

    Attributes:
        name: the study.
        ks: the numbers of experiments.
        errors: strategy -> ``(R, len(ks))`` error of each realization and K.
        references: reference lines (e.g. the energy of F).
        metric: what the errors are.
        meta: set-up details (all the choices made).
    """

    name: str
    ks: list[int]
    errors: dict[str, torch.Tensor]
    references: dict[str, float]
    metric: str
    meta: dict = field(default_factory=dict)

    @property
    def realizations(self) -> int:
        return next(iter(self.errors.values())).shape[0]

    def summary(self) -> dict[str, tuple[list[float], list[float]]]:
        """strategy -> (mean over realizations, standard error of the mean), one value per K."""
        out = {}
        for name, err in self.errors.items():
            mean, se = mean_and_standard_error(err, dim=0)
            out[name] = (mean.tolist(), se.tolist())
        return out

    def ratio(self, numerator: str, denominator: str) -> tuple[list[float], list[float]]:
        """Per-K mean and standard error of the paired per-realization ratio numerator / denominator."""
        mean, se = mean_and_standard_error(self._errors(numerator) / self._errors(denominator), dim=0)
        return mean.tolist(), se.tolist()

    def difference(self, minuend: str, subtrahend: str) -> tuple[list[float], list[float]]:
        """Per-K mean and standard error of the paired per-realization difference minuend - subtrahend."""
        mean, se = mean_and_standard_error(self._errors(minuend) - self._errors(subtrahend), dim=0)
        return mean.tolist(), se.tolist()

    def _errors(self, name: str) -> torch.Tensor:
        if name not in self.errors:
            raise InputError(f"strategy: expected one of {list(self.errors)}, got {name!r}")
        return self.errors[name]

    def table(self, ratios: list[tuple[str, str]] = ()) -> str:
        """A Markdown table: K, mean +- standard error per strategy, and the requested paired ratios."""
        summary = self.summary()
        cols = list(summary)
        header = ["K"] + cols + [f"{a} / {b}" for a, b in ratios]
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        ratio_vals = [self.ratio(a, b) for a, b in ratios]
        for i, k in enumerate(self.ks):
            row = [str(k)] + [f"{summary[c][0][i]:.4g} ± {summary[c][1][i]:.2g}" for c in cols]
            row += [f"{m[i]:.3f} ± {s[i]:.3f}" for m, s in ratio_vals]
            lines.append("| " + " | ".join(row) + " |")
        refs = ", ".join(f"{k} = {v:.4g}" for k, v in self.references.items())
        return "\n".join(lines) + f"\n\n{self.metric}; {self.realizations} realizations; reference lines: {refs}\n"

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "ks": self.ks,
            "metric": self.metric,
            "references": self.references,
            "meta": self.meta,
            "summary": self.summary(),
            "errors": {k: v.tolist() for k, v in self.errors.items()},
        }

    def save(self, out: str | Path, *, ratios: list[tuple[str, str]] = (), logy: bool = True) -> dict[str, Path]:
        """Write ``<name>.json``, ``<name>.md`` (the table) and ``<name>.png`` (the curves) into ``out``."""
        from ..plotting import plot_error_curves

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        paths = {
            "json": out / f"{self.name}.json",
            "table": out / f"{self.name}.md",
            "figure": out / f"{self.name}.png",
        }
        data = self.to_dict()
        data["ratios"] = {f"{a}/{b}": self.ratio(a, b) for a, b in ratios}
        paths["json"].write_text(json.dumps(data, indent=2))
        paths["table"].write_text(self.table(ratios))
        plot_error_curves(
            self.ks,
            self.summary(),
            reference_lines=self.references,
            ylabel=self.metric,
            logy=logy,
            title=f"{self.name} ({self.realizations} realizations)",
            path=paths["figure"],
        )
        return paths


# ------------------------------------------------------------------------------------------------------- helpers
def _check_ks(ks, n_candidates: int) -> list[int]:
    try:
        ks = sorted({int(k) for k in ks})
    except (TypeError, ValueError) as exc:
        raise InputError(f"ks: expected numbers of experiments in [1, {n_candidates}], got {ks!r}") from exc
    if not ks or ks[0] < 1 or ks[-1] > n_candidates:
        raise InputError(f"ks: expected numbers of experiments in [1, {n_candidates}], got {ks}")
    return ks


def _grid_error(
    gp: CorrectionGP,
    truth: torch.Tensor,
    points: torch.Tensor,
    weights: torch.Tensor,
    *,
    offset: torch.Tensor | None = None,
    squared: bool = False,
) -> float:
    """Quadrature of ||mu - truth|| (or its square) with fixed points ``(M, n)`` and weights ``(M,)``.

    ``truth`` ``(M, m)`` is precomputed once per study; ``offset`` ``(M, m)`` is subtracted from mu first.
    """
    with torch.no_grad():
        diff = gp.predict_mean(points) - truth
        if offset is not None:
            diff = diff - offset
    value = diff.pow(2).sum(-1) if squared else torch.linalg.vector_norm(diff, dim=-1)
    return float((value * weights).sum())


def _times_text(times: torch.Tensor) -> str:
    return f"{times.numel()} equally spaced on [{float(times[0]):g}, {float(times[-1]):g}]"


# --------------------------------------------------------------------------------------------------- paper Fig 5
def linear_study(
    ks=(1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20),
    realizations: int = 10,
    *,
    seed: int = 0,
    noise_std: float = _setup.NOISE_STD,
    grid_size: int = _setup.LINEAR_GRID_SIZE,
    lengthscale: float = _setup.LINEAR_PRIOR["lengthscale"],
    outputscale: float = _setup.LINEAR_PRIOR["outputscale"],
    data_driven_outputscale: float = _setup.DATA_DRIVEN_OUTPUTSCALE,
    resolution: int = 101,
    system: MisspecifiedSystem | None = None,
    progress: bool = False,
) -> StudyResult:
    """Paper Fig 5: integrated error of F_hat over D against K for three strategies.

    Strategies: ``design`` (lazy-greedy design + GP of F with the known G), ``random`` (random candidates + the same
    GP), ``data-driven`` (the designed set + a GP of G + F with no known part, output scale
    ``data_driven_outputscale``; its estimate of F is mu - G). Every GP uses the paper's fixed hyperparameters
    (RBF, lengthscale 1, noise variance ``noise_std**2``). Samples follow the paper's observation model (exact
    derivatives + Gaussian noise of std ``noise_std``), T = 11 on [0, 6]. The candidates are the
    ``grid_size x grid_size`` grid on D (:func:`torchmisspec.design.candidates.grid`); the error is the
    ``resolution x resolution`` trapezoidal quadrature of ``||F_hat - F||_2`` over D.

    Returns:
        a :class:`StudyResult` with errors ``(realizations, len(ks))`` per strategy.
    """
    system = paper_linear() if system is None else system
    realizations = check_positive_int(realizations, "realizations")
    candidates = _candidates.grid(system.domain, grid_size)
    ks = _check_ks(ks, candidates.shape[0])
    times = _setup.linear_times()
    prior = CorrectionGP(lengthscale=lengthscale, outputscale=outputscale, noise_variance=noise_std**2)
    prior_dd = CorrectionGP(lengthscale=lengthscale, outputscale=data_driven_outputscale, noise_variance=noise_std**2)
    plan = _design.greedy(candidates, ks[-1], system=system, times=times, gp=prior)
    design_idx = plan.indices

    states = simulate(system, candidates, times).states  # (N, T, d) true trajectories of every candidate
    inputs = system.select_inputs(states)
    clean_f = system.select_outputs(system.true_rhs(states) - system.known(states))  # F at the states
    clean_h = system.true_rhs(states)  # G + F at the states (data-driven targets)
    points, weights = box_grid(system.domain, resolution)
    truth_f = system.true_correction(points)
    known_at_points = system.known(points)

    names = ("design", "random", "data-driven")
    errors = {n: torch.empty(realizations, len(ks), dtype=torch.float64) for n in names}
    with progress_bar(progress, realizations * len(ks), "linear study") as bar:
        for r in range(realizations):
            gen = torch.Generator().manual_seed(seed * 100_003 + r)
            noise = noise_std * torch.randn(clean_f.shape, generator=gen, dtype=clean_f.dtype)
            targets_f, targets_h = clean_f + noise, clean_h + noise
            random_idx = torch.randperm(candidates.shape[0], generator=gen)
            for j, k in enumerate(ks):
                for name, idx, gp, targets in (
                    ("design", design_idx[:k], prior, targets_f),
                    ("random", random_idx[:k], prior, targets_f),
                    ("data-driven", design_idx[:k], prior_dd, targets_h),
                ):
                    x = inputs[idx].reshape(-1, inputs.shape[-1])
                    y = targets[idx].reshape(-1, targets.shape[-1])
                    offset = known_at_points if name == "data-driven" else None
                    errors[name][r, j] = _grid_error(gp.condition(x, y), truth_f, points, weights, offset=offset)
                bar.update(1)
    references = {
        "energy of F": integrated_norm(system.true_correction, system.domain, resolution=resolution),
        "energy of G + F": integrated_norm(system.true_rhs, system.domain, resolution=resolution),
    }
    meta = {
        "system": system.name,
        "candidates": f"{grid_size} x {grid_size} grid on {system.domain}",
        "times": _times_text(times),
        "noise_std": noise_std,
        "seed": seed,
        "hyperparameters": {
            "lengthscale": lengthscale,
            "outputscale": outputscale,
            "noise_variance": noise_std**2,
            "data_driven_outputscale": data_driven_outputscale,
        },
        "design_indices": design_idx.tolist(),
        "design_gains": plan.gains.tolist(),
        "quadrature": f"trapezoid, {resolution} x {resolution}",
    }
    return StudyResult("linear_study", ks, errors, references, "integral over D of ||F_hat - F||_2", meta)


# --------------------------------------------------------------------------------------------------- paper Fig 8
def gravity_study(
    ks=(1, 2, 3, 4, 5, 6, 7),
    realizations: int = 100,
    *,
    seed: int = 0,
    n_candidates: int = _setup.GRAVITY_CANDIDATES,
    noise_std: float = _setup.NOISE_STD,
    lengthscale: float = _setup.GRAVITY_PRIOR["lengthscale"],
    outputscale: float = _setup.GRAVITY_PRIOR["outputscale"],
    resolution: int = 81,
    include_random: bool = True,
    redraw_candidates: bool = False,
    progress: bool = False,
) -> StudyResult:
    """Paper Fig 8: mean squared error of F_hat over D against K, agnostic vs misspecified-aided design.

    ``n_candidates`` from :func:`torchmisspec.design.candidates.orbits` (seeded by ``seed``), T = 20 on [0, 3],
    RBF prior with lengthscale 1, output scale 1e-3 and noise variance ``noise_std**2`` (1e-4), fixed. The error is
    ``(1 / |D|)`` times the ``resolution x resolution`` trapezoidal quadrature of ``||F_hat - F||_2^2`` over D.

    As in the paper, a realization draws new observation noise only: the candidates and both designs are fixed, so
    the standard errors say nothing about how much the result depends on the candidate set. With
    ``redraw_candidates=True`` realization r also uses its own candidate set (the one of seed ``seed + r``) and its
    own two designs, so the paired differences average over candidate sets as well.

    Returns:
        a :class:`StudyResult` with errors ``(realizations, len(ks))`` for ``misspecified-aided``, ``agnostic`` and
            (with ``include_random``) ``random`` (a new random order of the candidates per realization).
    """
    system = paper_gravity()
    realizations = check_positive_int(realizations, "realizations")
    n_candidates = check_positive_int(n_candidates, "n_candidates")
    ks = _check_ks(ks, n_candidates)
    times = _setup.gravity_times()
    prior = CorrectionGP(lengthscale=lengthscale, outputscale=outputscale, noise_variance=noise_std**2)
    seeds = [seed + r for r in range(realizations)] if redraw_candidates else [seed]
    candidates = torch.stack(
        [_candidates.orbits(n_candidates, generator=torch.Generator().manual_seed(s)) for s in seeds]
    )
    flat = candidates.reshape(-1, candidates.shape[-1])  # every set in one batched solve
    states = simulate(system, flat, times).states.reshape(len(seeds), n_candidates, times.numel(), -1)
    proxies = _design.proxy_trajectories(system, flat, times).reshape(states.shape) if redraw_candidates else None
    plans = []  # one dict name -> DesignResult per candidate set
    for i in range(len(seeds)):
        aided = dict(proxy=_design.Proxy(paths=proxies[i])) if proxies is not None else dict(times=times)
        plans.append(
            {
                "misspecified-aided": _design.greedy(candidates[i], ks[-1], system=system, gp=prior, **aided),
                "agnostic": _design.agnostic(candidates[i], ks[-1], system=system, times=times, gp=prior),
            }
        )
    inputs = system.select_inputs(states)  # (sets, N, T, d_in)
    clean = system.true_correction(inputs)
    points, weights = box_grid(system.domain, resolution)
    volume = float(weights.sum())
    weights = weights / volume  # mean over D
    truth = system.true_correction(points)

    names = list(plans[0]) + (["random"] if include_random else [])
    errors = {n: torch.empty(realizations, len(ks), dtype=torch.float64) for n in names}
    with progress_bar(progress, realizations, "gravity study") as bar:
        for r in range(realizations):
            i = r if redraw_candidates else 0
            gen = torch.Generator().manual_seed(seed * 100_003 + r)
            targets = clean[i] + noise_std * torch.randn(clean[i].shape, generator=gen, dtype=clean.dtype)
            order = {name: plan.indices for name, plan in plans[i].items()}
            if include_random:
                order["random"] = torch.randperm(n_candidates, generator=gen)
            for j, k in enumerate(ks):
                for name in names:
                    idx = order[name][:k]
                    x = inputs[i, idx].reshape(-1, inputs.shape[-1])
                    y = targets[idx].reshape(-1, targets.shape[-1])
                    errors[name][r, j] = _grid_error(prior.condition(x, y), truth, points, weights, squared=True)
            bar.update(1)
    references = {"mean energy of F": float((truth.pow(2).sum(-1) * weights).sum())}
    designs = {name: [p[name].indices.tolist() for p in plans] for name in plans[0]}
    meta = {
        "system": system.name,
        "candidates": f"{n_candidates} from design.candidates.orbits(seed={seed})"
        if not redraw_candidates
        else f"{n_candidates} from design.candidates.orbits(seed={seed} + r) for realization r",
        "times": _times_text(times),
        "noise_std": noise_std,
        "seed": seed,
        "domain": system.domain,
        "hyperparameters": {"lengthscale": lengthscale, "outputscale": outputscale, "noise_variance": noise_std**2},
        "designs": designs if redraw_candidates else {name: d[0] for name, d in designs.items()},
        "quadrature": f"trapezoid, {resolution} x {resolution}",
    }
    return StudyResult("gravity_study", ks, errors, references, "mean over D of ||F_hat - F||_2^2", meta)


# ------------------------------------------------------------------------------------ sequential design (issue 11)
SEQUENTIAL_SETUPS = ("linear", "gravity")


def _sequential_setup(setup: str, seed: int, n_candidates: int | None):
    if setup == "linear":
        system = paper_linear()
        size = _setup.LINEAR_GRID_SIZE
        candidates = _candidates.grid(system.domain, size)
        desc = f"{size} x {size} grid on {system.domain}"
        return system, candidates, _setup.linear_times(), dict(_setup.LINEAR_PRIOR), "integrated", 101, desc
    if setup == "gravity":
        system = paper_gravity()
        n = _setup.GRAVITY_CANDIDATES if n_candidates is None else check_positive_int(n_candidates, "n_candidates")
        candidates = _candidates.orbits(n, generator=torch.Generator().manual_seed(seed))
        desc = f"{n} from design.candidates.orbits(seed={seed})"
        return system, candidates, _setup.gravity_times(), dict(_setup.GRAVITY_PRIOR), "mean_squared", 81, desc
    raise InputError(f"setup: expected one of {SEQUENTIAL_SETUPS}, got {setup!r}")


@dataclass(frozen=True)
class _SequentialProblem:
    """What every strategy of the sequential study shares: the set-up, the prior, the data and the error measure."""

    system: MisspecifiedSystem
    candidates: torch.Tensor
    times: torch.Tensor
    prior: CorrectionGP
    noise_std: float
    seed: int  # the study's; campaign r draws its sample noise from seed * 1000 + r
    inputs: torch.Tensor  # (N, T, d_in) correction inputs along every candidate's true trajectory
    error: Callable[[CorrectionGP], float]


@dataclass
class _SequentialRecord:
    """The sequential study's results as realizations add them: errors, campaign picks, learned hyperparameters."""

    errors: dict[str, torch.Tensor]  # strategy -> (R, len(ks))
    picks: dict[str, list]  # sequential strategy -> its first kmax picks, one list per realization
    hyper: list[dict] = field(default_factory=list)  # the first campaign's hyperparameters at kmax, per realization


def _clean_samples(system: MisspecifiedSystem, candidates: torch.Tensor, times: torch.Tensor):
    """Inputs and exact correction targets along every candidate's true trajectory, simulated once and reused."""
    states = simulate(system, candidates, times).states
    inputs = system.select_inputs(states)
    clean = system.select_outputs(system.true_rhs(states) - system.known(states))
    return inputs, clean


def _error_quadrature(system: MisspecifiedSystem, resolution: int, squared: bool):
    """The grid, its weights (normalised to a mean when ``squared``) and the true F on it, for every error."""
    points, weights = box_grid(system.domain, resolution)
    if squared:
        weights = weights / weights.sum()
    return points, weights, system.true_correction(points)


def _energy_reference(system: MisspecifiedSystem, truth, weights, squared: bool, resolution: int) -> dict[str, float]:
    """The energy of F in the study's metric (its mean square, or the integral of its norm): the errors' yardstick."""
    if squared:
        return {"mean energy of F": float((truth.pow(2).sum(-1) * weights).sum())}
    return {"energy of F": integrated_norm(system.true_correction, system.domain, resolution=resolution)}


def _one_shot_errors(problem: _SequentialProblem, order: dict, targets: torch.Tensor, ks, errors: dict, r: int):
    """Realization ``r``'s error at each K of the prior conditioned on the first K experiments of each fixed order."""
    inputs = problem.inputs
    for name, idx in order.items():
        for j, k in enumerate(ks):
            x = inputs[idx[:k]].reshape(-1, inputs.shape[-1])
            y = targets[idx[:k]].reshape(-1, targets.shape[-1])
            errors[name][r, j] = problem.error(problem.prior.condition(x, y))


def _campaign(problem: _SequentialProblem, criterion: str, batch: int, kmax: int, r: int, track: bool):
    """A campaign of ``kmax`` experiments in rounds of ``batch``; with ``track``, its own GP's error after each."""
    camp = _design.Campaign(
        problem.system,
        problem.candidates,
        problem.times,
        problem.prior,
        criterion=criterion,
        derivative="oracle",
        noise_std=problem.noise_std,
        seed=problem.seed * 1000 + r,
    )
    own = {}
    while camp.num_experiments < kmax:
        y0 = camp.ask(min(batch, kmax - camp.num_experiments))
        camp.tell(simulate(problem.system, y0, problem.times))
        if track:
            own[camp.num_experiments] = problem.error(camp.gp)
    return camp, own


def _sequential_errors(problem: _SequentialProblem, names, sequential, learned, ks, record: _SequentialRecord, r: int):
    """Realization ``r`` of every sequential strategy: the prior's error on each campaign's first K experiments
    (and the first campaign's own model's, as ``learned``), into ``record`` with the picks and hyperparameters."""
    errors, kmax, T = record.errors, ks[-1], problem.times.numel()
    for name, (crit, b) in zip(names, sequential, strict=True):
        first = name == names[0]
        camp, own = _campaign(problem, crit, b, kmax, r, track=first)
        X, Y = torch.cat(camp._inputs), torch.cat(camp._targets)
        for j, k in enumerate(ks):
            errors[name][r, j] = problem.error(problem.prior.condition(X[: k * T], Y[: k * T]))
            if learned and first:
                errors[learned][r, j] = own[k]
        record.picks[name].append(camp.asked[:kmax])
        if first:
            record.hyper.append(camp.history[-1]["hyperparameters"])


def sequential_study(
    setup: str = "linear",
    ks=None,
    realizations: int = 20,
    *,
    seed: int = 0,
    sequential=(("information", 1), ("information", 3), ("domain", 1)),
    noise_std: float = _setup.NOISE_STD,
    n_candidates: int | None = None,
    progress: bool = False,
) -> StudyResult:
    """Error vs K of one-shot and sequential designs (issue 11): what designing in rounds, given the data, buys.

    Strategies (every one on the same candidates, times and observation model: exact derivatives + noise):

    * ``paper design``: the paper's one-shot greedy design of the information about F, from the prior;
    * ``domain design``: one-shot, ``criterion="domain"`` (variance of F over D), from the prior;
    * ``sequential <criterion> (rounds of b)``: a :class:`~torchmisspec.design.Campaign` from the same prior, ``b``
      experiments per round, each round designed with ``criterion`` given every sample so far (conditioned gains,
      corrected proxies) with the hyperparameters learned by marginal likelihood once the data hold 4 T samples;
    * ``random``: a random order of the candidates per realization.

    The estimate compared at each K is the same for every strategy: the prior's GP (its fixed hyperparameters, as
    in the paper's studies) conditioned on the samples of the first K experiments, so differences come from the
    choice of experiments alone. ``... learned GP`` is the first sequential strategy's own model (learned
    hyperparameters) on the same experiments (when it runs in rounds of 1). Sequential strategies draw their
    sample noise in the campaign (a seed per realization), the one-shot strategies share one draw per realization.

    Args:
        setup: ``"linear"`` (paper 5.2: 13 x 13 grid, T = 11, the integral over D of ``||F_hat - F||``) or
            ``"gravity"`` (paper 5.3: 300 orbits, T = 20, the mean over D of ``||F_hat - F||^2``).
        ks: numbers of experiments (default 1..20 for linear, 1..10 for gravity).
        realizations: noise realizations (and random orders, campaigns).
        sequential: ``(criterion, batch size)`` of each sequential strategy.
    """
    system, candidates, times, prior_kw, metric, resolution, desc = _sequential_setup(setup, seed, n_candidates)
    prior_kw["noise_variance"] = noise_std**2
    realizations = check_positive_int(realizations, "realizations")
    ks = _check_ks(range(1, 21 if setup == "linear" else 11) if ks is None else ks, candidates.shape[0])
    sequential = [(c, check_positive_int(b, "batch size")) for c, b in sequential]
    prior = CorrectionGP(**prior_kw)
    plans = {
        "paper design": _design.greedy(candidates, ks[-1], system=system, times=times, gp=prior),
        "domain design": _design.greedy(candidates, ks[-1], system=system, times=times, gp=prior, criterion="domain"),
    }
    inputs, clean = _clean_samples(system, candidates, times)
    squared = metric == "mean_squared"
    points, weights, truth = _error_quadrature(system, resolution, squared)

    def error(gp) -> float:
        return _grid_error(gp, truth, points, weights, squared=squared)

    problem = _SequentialProblem(system, candidates, times, prior, noise_std, seed, inputs, error)
    seq = [f"sequential {c} (rounds of {b})" for c, b in sequential]
    learned = f"{seq[0]}, learned GP" if sequential[0][1] == 1 else None  # its model after every experiment
    names = list(plans) + seq + ([learned] if learned else []) + ["random"]
    errors = {n: torch.empty(realizations, len(ks), dtype=torch.float64) for n in names}
    record = _SequentialRecord(errors, {n: [] for n in seq})
    with progress_bar(progress, realizations, f"sequential study ({setup})") as bar:
        for r in range(realizations):
            gen = torch.Generator().manual_seed(seed * 100_003 + r)
            targets = clean + noise_std * torch.randn(clean.shape, generator=gen, dtype=clean.dtype)
            order = {name: plan.indices for name, plan in plans.items()}
            order["random"] = torch.randperm(candidates.shape[0], generator=gen)
            _one_shot_errors(problem, order, targets, ks, errors, r)
            _sequential_errors(problem, seq, sequential, learned, ks, record, r)
            bar.update(1)
    references = _energy_reference(system, truth, weights, squared, resolution)
    meta = {
        "system": system.name,
        "setup": setup,
        "candidates": desc,
        "times": _times_text(times),
        "noise_std": noise_std,
        "seed": seed,
        "prior": prior_kw,
        "designs": {name: plan.indices.tolist() for name, plan in plans.items()},
        "sequential_picks": record.picks,
        "learned_hyperparameters_at_kmax": record.hyper,
        "quadrature": f"trapezoid, {resolution} x {resolution}",
    }
    what = "mean over D of ||F_hat - F||_2^2" if squared else "integral over D of ||F_hat - F||_2"
    return StudyResult(f"sequential_{setup}", ks, errors, references, what, meta)
