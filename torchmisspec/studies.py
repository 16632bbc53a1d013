"""Studies: error of the learned correction against the number of experiments, averaged over realizations.

* :func:`linear_study` is paper Fig 5 (§5.2): on paper_linear with the 13 x 13 candidate grid, the integrated error
  of F_hat over D for the designed set + misspecified GP, random sets + misspecified GP, and the designed set + a
  fully data-driven GP (no known part), with the energies of F and G + F as reference lines.
* :func:`gravity_study` is paper Fig 8 (§5.3): on paper_gravity with 300 candidates, the mean squared error of
  F_hat over D for the agnostic design (ignores G) and the misspecified-aided design, and random sets.

A realization draws new observation noise (and new random sets); the designs depend only on the prior and are
computed once (greedy designs are nested, so the design of size K is the first K picks of the largest one). The
true trajectories of every candidate are simulated once and reused.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from . import design as _design
from ._errors import InputError
from ._validation import progress_bar
from .data import simulate
from .gp import CorrectionGP
from .metrics import box_grid, integrated_norm
from .systems import MisspecifiedSystem, gravity_candidates, paper_gravity, paper_linear

__all__ = ["StudyResult", "grid_candidates", "linear_study", "gravity_study"]


def grid_candidates(domain, size: int = 13, *, dtype=torch.float64) -> torch.Tensor:
    """A uniform ``size^n`` grid over the box ``domain``: ``(size**n, n)`` (paper §5.2: 13 x 13 on [-1, 1]^2)."""
    points, _ = box_grid(domain, size, dtype=dtype)
    return points


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
            r = err.shape[0]
            std = err.std(0, unbiased=True) if r > 1 else torch.zeros(err.shape[1], dtype=err.dtype)
            out[name] = (err.mean(0).tolist(), (std / math.sqrt(r)).tolist())
        return out

    def ratio(self, numerator: str, denominator: str) -> tuple[list[float], list[float]]:
        """Per-K mean and standard error of the paired per-realization ratio numerator / denominator."""
        ratio = self.errors[numerator] / self.errors[denominator]
        r = ratio.shape[0]
        std = ratio.std(0, unbiased=True) if r > 1 else torch.zeros(ratio.shape[1], dtype=ratio.dtype)
        return ratio.mean(0).tolist(), (std / math.sqrt(r)).tolist()

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
        from .plotting import plot_error_curves

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
        summary = self.summary()
        plot_error_curves(
            self.ks,
            {k: (v[0], v[1]) for k, v in summary.items()},
            reference_lines=self.references,
            ylabel=self.metric,
            logy=logy,
            title=f"{self.name} ({self.realizations} realizations)",
            path=paths["figure"],
        )
        return paths


# ------------------------------------------------------------------------------------------------------- helpers
def _check_ks(ks, n_candidates: int) -> list[int]:
    ks = sorted({int(k) for k in ks})
    if not ks or ks[0] < 1 or ks[-1] > n_candidates:
        raise InputError(f"ks: expected numbers of experiments in [1, {n_candidates}], got {ks}")
    return ks


def _check_realizations(realizations) -> int:
    if isinstance(realizations, bool) or not isinstance(realizations, int) or realizations < 1:
        raise InputError(f"realizations: expected a positive integer, got {realizations!r}")
    return realizations


def _grid_error(
    gp: CorrectionGP,
    truth: torch.Tensor,
    points: torch.Tensor,
    weights: torch.Tensor,
    *,
    offset: torch.Tensor | None = None,
    squared: bool = False,
) -> float:
    """Quadrature of ||mu - truth|| (or its square) on a fixed grid; ``offset`` is subtracted from mu first."""
    with torch.no_grad():
        diff = gp.predict_mean(points) - truth
        if offset is not None:
            diff = diff - offset
    value = diff.pow(2).sum(-1) if squared else torch.linalg.vector_norm(diff, dim=-1)
    return float((value * weights).sum())


def _fit_fixed(prior: CorrectionGP, inputs: torch.Tensor, targets: torch.Tensor) -> CorrectionGP:
    """A GP with the prior's (fixed) hyperparameters conditioned on the samples."""
    return CorrectionGP(
        kernel=prior.kernel,
        lengthscale=prior.lengthscale,
        outputscale=prior.outputscale,
        noise_variance=prior.noise_variance,
    ).fit(inputs, targets)


def _noisy_targets(clean: torch.Tensor, noise_std: float, gen: torch.Generator) -> torch.Tensor:
    return clean + noise_std * torch.randn(clean.shape, generator=gen, dtype=clean.dtype)


# --------------------------------------------------------------------------------------------------- paper Fig 5
def linear_study(
    ks=(1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20),
    realizations: int = 10,
    *,
    seed: int = 0,
    noise_std: float = 1e-2,
    grid_size: int = 13,
    lengthscale: float = 1.0,
    outputscale: float = 4e-5,
    data_driven_outputscale: float = 1e-2,
    resolution: int = 101,
    system: MisspecifiedSystem | None = None,
    progress: bool = False,
) -> StudyResult:
    """Paper Fig 5: integrated error of F_hat over D against K for three strategies.

    Strategies: ``design`` (lazy-greedy design + GP of F with the known G), ``random`` (random candidates + the same
    GP), ``data-driven`` (the designed set + a GP of G + F with no known part, output scale
    ``data_driven_outputscale``; its estimate of F is mu - G). Every GP uses the paper's fixed hyperparameters
    (RBF, lengthscale 1, noise variance ``noise_std**2``). Samples follow the paper's observation model (exact
    derivatives + Gaussian noise of std ``noise_std``), T = 11 on [0, 6].
    """
    system = paper_linear() if system is None else system
    realizations = _check_realizations(realizations)
    candidates = grid_candidates(system.domain, grid_size)
    ks = _check_ks(ks, candidates.shape[0])
    times = torch.linspace(0.0, 6.0, 11, dtype=torch.float64)
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
    bar = progress_bar(progress, realizations * len(ks), "linear study")
    for r in range(realizations):
        gen = torch.Generator().manual_seed(seed * 100_003 + r)
        noise = noise_std * torch.randn(clean_f.shape, generator=gen, dtype=clean_f.dtype)
        targets_f, targets_h = clean_f + noise, clean_h + noise
        random_idx = torch.randperm(candidates.shape[0], generator=gen)
        for j, k in enumerate(ks):
            for name, idx, prior_k, targets in (
                ("design", design_idx[:k], prior, targets_f),
                ("random", random_idx[:k], prior, targets_f),
                ("data-driven", design_idx[:k], prior_dd, targets_h),
            ):
                x = inputs[idx].reshape(-1, inputs.shape[-1])
                y = targets[idx].reshape(-1, targets.shape[-1])
                gp = _fit_fixed(prior_k, x, y)
                offset = known_at_points if name == "data-driven" else None
                errors[name][r, j] = _grid_error(gp, truth_f, points, weights, offset=offset)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    references = {
        "energy of F": integrated_norm(system.true_correction, system.domain, resolution=resolution),
        "energy of G + F": integrated_norm(system.true_rhs, system.domain, resolution=resolution),
    }
    meta = {
        "system": system.name,
        "candidates": f"{grid_size} x {grid_size} grid on {system.domain}",
        "times": "11 equally spaced on [0, 6]",
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
    n_candidates: int = 300,
    noise_std: float = 1e-2,
    lengthscale: float = 1.0,
    outputscale: float = 1e-3,
    resolution: int = 81,
    include_random: bool = True,
    progress: bool = False,
) -> StudyResult:
    """Paper Fig 8: mean squared error of F_hat over D against K, agnostic vs misspecified-aided design.

    300 candidates from :func:`~torchmisspec.systems.gravity_candidates` (seeded by ``seed``), T = 20 on [0, 3],
    RBF prior with lengthscale 1, output scale 1e-3 and noise variance ``noise_std**2`` (1e-4), fixed.
    """
    system = paper_gravity()
    realizations = _check_realizations(realizations)
    candidates = gravity_candidates(n_candidates, generator=torch.Generator().manual_seed(seed))
    ks = _check_ks(ks, candidates.shape[0])
    times = torch.linspace(0.0, 3.0, 20, dtype=torch.float64)
    prior = CorrectionGP(lengthscale=lengthscale, outputscale=outputscale, noise_variance=noise_std**2)
    plans = {
        "misspecified-aided": _design.greedy(candidates, ks[-1], system=system, times=times, gp=prior),
        "agnostic": _design.agnostic(candidates, ks[-1], system=system, times=times, gp=prior),
    }

    states = simulate(system, candidates, times).states
    inputs = system.select_inputs(states)
    clean = system.true_correction(inputs)
    points, weights = box_grid(system.domain, resolution)
    volume = float(weights.sum())
    weights = weights / volume  # mean over D
    truth = system.true_correction(points)

    names = list(plans) + (["random"] if include_random else [])
    errors = {n: torch.empty(realizations, len(ks), dtype=torch.float64) for n in names}
    bar = progress_bar(progress, realizations, "gravity study")
    for r in range(realizations):
        gen = torch.Generator().manual_seed(seed * 100_003 + r)
        targets = _noisy_targets(clean, noise_std, gen)
        order = {name: plan.indices for name, plan in plans.items()}
        if include_random:
            order["random"] = torch.randperm(candidates.shape[0], generator=gen)
        for j, k in enumerate(ks):
            for name in names:
                idx = order[name][:k]
                gp = _fit_fixed(prior, inputs[idx].reshape(-1, 2), targets[idx].reshape(-1, 2))
                errors[name][r, j] = _grid_error(gp, truth, points, weights, squared=True)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    references = {"mean energy of F": float((truth.pow(2).sum(-1) * weights).sum())}
    meta = {
        "system": system.name,
        "candidates": f"{n_candidates} from gravity_candidates(seed={seed})",
        "times": "20 equally spaced on [0, 3]",
        "noise_std": noise_std,
        "seed": seed,
        "domain": system.domain,
        "hyperparameters": {"lengthscale": lengthscale, "outputscale": outputscale, "noise_variance": noise_std**2},
        "designs": {name: plan.indices.tolist() for name, plan in plans.items()},
        "quadrature": f"trapezoid, {resolution} x {resolution}",
    }
    return StudyResult("gravity_study", ks, errors, references, "mean over D of ||F_hat - F||_2^2", meta)
