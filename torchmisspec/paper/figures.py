"""Regenerate the eight figures of the paper's §5 ("Numerical Experiments"), with the numbers behind each one.

One function per figure, ``figure_N(out, *, smoke=False, seed=0, progress=False, session=None) -> dict``: it writes
``figN.png`` (and, where a figure has panels worth reading alone, ``figN_<panel>.png``) into ``out`` and returns a
JSON-serialisable dict of what the package measured for that figure (nothing is typed in: every number comes from
the run). :func:`reproduce` runs a list of figures and writes ``results.json`` (figure -> numbers, timings, the
smoke flag and the realization counts). ``scripts/reproduce_paper.py`` is the command-line front end.

What each figure reproduces:

* Fig 1 (§5.1): 40 random initial conditions in D = [-1, 1]^2, T = 11 on [0, 6], oracle samples of F with noise std
  1e-2; the correction GP with the paper's fixed RBF prior (l = 1, output scale 4e-5, noise 1e-4; plotted) and by
  marginal likelihood; training (left) and test (right) trajectories; test RMSE ratios over realizations.
* Fig 2 (§5.1): `||F_hat - F||_2` over D with the training traces; error near vs far from the traces.
* Fig 3 (§5.2): 13 x 13 candidate grid, the K = 9 lazy-greedy design and 9 random picks with their trajectories;
  predictions of both corrected models on a test set.
* Fig 4 (§5.2): `|F_hat_i - F_i|` maps, random (top) vs design (bottom).
* Fig 5 (§5.2): integrated error vs K for design / random / data-driven over realizations (:func:`linear_study`).
* Fig 6 (§5.3): gravity; 300 candidates, the masses, the agnostic and misspecified-aided designs of size 7 with
  their trajectories; predictions on a random test set.
* Fig 7 (§5.3): `||F_hat_{3,4} - F_{3,4}||_2` maps of both designs over a box larger than D (D dashed).
* Fig 8 (§5.3): mean squared error over D vs K over noise realizations (:func:`gravity_study`).

Choices the paper leaves open are those of the package (see :func:`~torchmisspec.systems.paper_gravity` for the
gravity domain D and :func:`~torchmisspec.design.candidates.orbits` for the candidate set). Trajectories are
*plotted and scored* on a finer time grid (61 times) than the one observed for training (T = 11 or 20), so the
test RMSEs measure the whole predicted paths. Information gains are in nats of a real Gaussian (half the paper's
complex-convention numbers; see :mod:`torchmisspec.design`).

Work is shared between figures through a :class:`Session` (the Fig 1 fit serves Fig 2, the Fig 3 designs serve
Fig 4, the gravity set-up serves Figs 6 and 7): :func:`reproduce` makes one per run and passes it to every figure;
a figure called without one builds what it needs. Nothing is cached at module level.
"""

from __future__ import annotations

import functools
import json
import numbers
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import design as _design
from .. import plotting
from .._errors import InputError, TorchMisspecWarning
from .._validation import check_positive_int, progress_bar
from ..data import Trajectories, simulate
from ..design import candidates as _candidates
from ..dynamics import CorrectedODE
from ..gp import CorrectionGP
from ..metrics import (
    box_grid,
    correction_error,
    integrate_over_box,
    integrated_norm,
    mean_and_standard_error,
    mean_squared_error,
    trajectory_rmse,
)
from ..observations import correction_samples
from ..systems import MisspecifiedSystem, paper_gravity, paper_linear
from . import _layout
from ._setup import (
    GRAVITY_CANDIDATES,
    GRAVITY_PRIOR,
    LINEAR_GRID_SIZE,
    LINEAR_PRIOR,
    NOISE_STD,
    gravity_times,
    linear_times,
)
from .studies import StudyResult, gravity_study, linear_study

__all__ = [
    "FIGURES",
    "Session",
    "LINEAR_PRIOR",
    "GRAVITY_PRIOR",
    "NOISE_STD",
    "figure_1",
    "figure_2",
    "figure_3",
    "figure_4",
    "figure_5",
    "figure_6",
    "figure_7",
    "figure_8",
    "reproduce",
]

FINE_TIMES = 61  # plotting / scoring grid

# Sizes: (full, smoke).
_FIG1_REALIZATIONS = (20, 3)
#: Posterior draws of F for the bands of Figs 1 and 6 (full run, smoke run).
_BAND_SAMPLES = (128, 16)
#: Central band probabilities whose empirical coverage of the true test trajectories Figs 1 and 6 report.
_BAND_LEVELS = (0.5, 0.9, 0.95)
_FIG3_RANDOM_DRAWS = (200, 10)
_FIG5_KS = ((1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20), (1, 2, 4, 9))
_FIG5_REALIZATIONS = (10, 2)
_FIG8_REALIZATIONS = (400, 3)
_FIG7_BOX = ((-2.5, 2.5), (-2.5, 2.5))


def _pick(sizes: tuple, smoke: bool):
    return sizes[1] if smoke else sizes[0]


# ------------------------------------------------------------------------------------------------------ helpers
def _generator(seed: int, tag: int) -> torch.Generator:
    """An independent stream per (seed, figure/purpose tag)."""
    return torch.Generator().manual_seed(int(seed) * 1_000_003 + int(tag))


def _hyper(gp: CorrectionGP) -> dict:
    return {
        "lengthscale": float(gp.lengthscale),
        "outputscale": float(gp.outputscale),
        "noise_variance": float(gp.noise_variance),
        "log_marginal_likelihood": gp.log_marginal_likelihood_,
    }


def _mean_se(values: Sequence[float]) -> dict:
    mean, se = mean_and_standard_error(values)
    return {"mean": float(mean), "stderr": float(se), "n": len(values), "values": [float(v) for v in values]}


def _rmse(pred: torch.Tensor, true: torch.Tensor) -> float:
    return float(trajectory_rmse(pred, true))


def _jsonable(x: Any) -> Any:
    """Tensors, arrays and numpy scalars -> lists and Python numbers, recursively."""
    if isinstance(x, torch.Tensor):
        return _jsonable(x.detach().cpu().tolist())
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def _true_and_known(system: MisspecifiedSystem, y0: torch.Tensor, times: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The true ``(K, T, d)`` and the known model's (misspecified) trajectories from ``y0``."""
    return simulate(system, y0, times).states, simulate(system, y0, times, known_only=True).states


# ================================================================================ §5.1 set-up (Figs 1 and 2)
@dataclass(frozen=True)
class _LinearFit:
    system: MisspecifiedSystem
    times: torch.Tensor  # (11,) observed
    fine: torch.Tensor  # (61,) plotted / scored
    y0: torch.Tensor  # (40, 2)
    train: Trajectories  # observed, T = 11
    train_fine: torch.Tensor
    train_mis_fine: torch.Tensor
    gp_paper: CorrectionGP
    gp_ml: CorrectionGP
    y_test: torch.Tensor
    test_true: torch.Tensor
    test_mis: torch.Tensor
    corrected_paper: torch.Tensor
    corrected_ml: torch.Tensor
    seconds: dict


def _linear_fit_run(
    seed: int, realization: int, *, n_train: int = 40, n_test: int = 10, progress: bool = False
) -> _LinearFit:
    system = paper_linear()
    gen = _generator(seed, 100 + realization)
    times, fine = linear_times(), linear_times(FINE_TIMES)
    sec = {}
    t0 = time.perf_counter()
    y0 = _candidates.uniform_box(n_train, system.domain, generator=gen)
    train = simulate(system, y0, times)
    samples = correction_samples(train, system, derivative="oracle", noise_std=NOISE_STD, generator=gen)
    y_test = _candidates.uniform_box(n_test, system.domain, generator=gen)
    sec["simulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    gp_paper = CorrectionGP(**LINEAR_PRIOR).fit(samples.inputs, samples.targets)
    sec["fit_paper"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    gp_ml = CorrectionGP().fit(samples.inputs, samples.targets, progress=progress)
    sec["fit_marginal_likelihood"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    corrected_paper = CorrectedODE(system, gp_paper).predict(y_test, fine)
    corrected_ml = CorrectedODE(system, gp_ml).predict(y_test, fine)
    sec["predict"] = time.perf_counter() - t0
    train_fine, train_mis_fine = _true_and_known(system, y0, fine)
    test_true, test_mis = _true_and_known(system, y_test, fine)
    return _LinearFit(
        system=system,
        times=times,
        fine=fine,
        y0=y0,
        train=train,
        train_fine=train_fine,
        train_mis_fine=train_mis_fine,
        gp_paper=gp_paper,
        gp_ml=gp_ml,
        y_test=y_test,
        test_true=test_true,
        test_mis=test_mis,
        corrected_paper=corrected_paper,
        corrected_ml=corrected_ml,
        seconds=sec,
    )


def _fit_numbers(run: _LinearFit) -> dict:
    mis = _rmse(run.test_mis, run.test_true)
    out = {}
    for name, gp, pred in (
        ("paper_prior", run.gp_paper, run.corrected_paper),
        ("marginal_likelihood", run.gp_ml, run.corrected_ml),
    ):
        cor = _rmse(pred, run.test_true)
        out[name] = {
            "hyperparameters": _hyper(gp),
            "rmse_corrected": cor,
            "rmse_misspecified": mis,
            "rmse_ratio": cor / mis,
            "integrated_error": correction_error(gp, run.system),
        }
    return out


def figure_1(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 1: training set (true vs misspecified) and test set (true, misspecified, corrected).

    Returns the test RMSEs of the corrected model (paper prior and marginal-likelihood fits) and of the
    misspecified one, their ratio, the hyperparameters, and the RMSE ratio over several realizations (new initial
    conditions, noise and test set each time; realization 0 is the one plotted).
    """
    out = Path(out)
    files: list[str] = []
    run = _session(session, seed).linear_fit
    fig = plotting.plot_training_and_test(
        run.train_fine,
        run.train_mis_fine,
        run.test_true,
        run.test_mis,
        run.corrected_paper,
        titles=(
            f"Training set: {run.y0.shape[0]} random initial conditions",
            f"Test set ({run.y_test.shape[0]} new initial conditions), paper prior",
        ),
        legend="below",
    )
    fig.suptitle(r"Paper Fig 1 (§5.1): $G(y) = Ay$, $F(y) = 0.01\,[y_1^2, y_2^2]$, $t \in [0, 6]$")
    _layout.save(fig, out / "fig1.png", files)
    bands = _bands(
        CorrectedODE(run.system, run.gp_paper),
        run.y_test,
        run.fine,
        run.test_true,
        run.test_mis,
        samples=_pick(_BAND_SAMPLES, smoke),
        generator=_generator(seed, 901),
        title="Fig 1 with bands: test initial condition 1, paper prior",
        path=out / "fig1_bands.png",
        files=files,
    )

    n_real = _pick(_FIG1_REALIZATIONS, smoke)
    ratios = {"paper_prior": [], "marginal_likelihood": []}
    with progress_bar(progress, n_real, "Fig 1 realizations") as bar:
        for r in range(n_real):
            nums = _fit_numbers(run if r == 0 else _linear_fit_run(seed, r))
            for name in ratios:
                ratios[name].append(nums[name]["rmse_ratio"])
            bar.update(1)
    t_final = float(run.times[-1])
    return {
        "setup": {
            "n_train": int(run.y0.shape[0]),
            "n_test": int(run.y_test.shape[0]),
            "T": int(run.times.numel()),
            "t_final": t_final,
            "noise_std": NOISE_STD,
            "paper_prior": LINEAR_PRIOR,
            "rmse_on": f"{run.fine.numel()} equally spaced times on [0, {t_final:g}], all test trajectories",
        },
        "plotted_fit": "paper_prior",
        "fits": _fit_numbers(run),
        "bands": bands,
        "rmse_ratio_over_realizations": {name: _mean_se(v) for name, v in ratios.items()},
        "realizations": n_real,
        "files": files,
    }


def _bands(model, y0, times, true, mis, *, samples, generator, title, path, files) -> dict:
    """Posterior draws of F integrated from the test initial conditions (``CorrectedODE.posterior``): a figure of the
    bands of the first one, and the empirical coverage of the true test trajectories by the central bands."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TorchMisspecWarning)
        post = model.posterior(y0, times, num_samples=samples, generator=generator)
    fig = plotting.plot_prediction_bands(post, index=0, true_states=true, misspecified_states=mis, title=title)
    _layout.save(fig, path, files)
    lower, upper = post.interval(0.9)
    return {
        "num_samples": samples,
        "coverage_of_true_paths": {f"{v:g}": float(post.covers(true, v).double().mean()) for v in _BAND_LEVELS},
        "mean_band_width_90": float((upper - lower).mean()),
        "extrapolating_paths": int(post.extrapolating.sum()),
        "warnings": [str(w.message) for w in caught if issubclass(w.category, TorchMisspecWarning)],
    }


def figure_2(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 2: ||F_hat - F||_2 over D (paper prior fit of Fig 1) with the training traces.

    Returns the integrated error, the energies of F and G + F, and the mean error over the grid points nearest
    to the training traces (lowest quartile of the distance) vs the farthest ones (highest quartile).
    """
    out = Path(out)
    files: list[str] = []
    run = _session(session, seed).linear_fit
    system = run.system
    err_fn = plotting.correction_error_fn(system, run.gp_paper)
    fig = plotting.plot_error_map(
        err_fn,
        system.domain,
        traces=run.train.states,
        title=r"$\|\hat F(y) - F(y)\|_2$, training traces in white (paper prior)",
    )
    _layout.save(fig, out / "fig2.png", files)

    points, _ = box_grid(system.domain, 101)
    with torch.no_grad():
        err = err_fn(points)
    trace_pts = run.train_fine.reshape(-1, 2)
    dist = torch.cdist(points, trace_pts).min(-1).values
    q1, q3 = torch.quantile(dist, torch.tensor([0.25, 0.75], dtype=dist.dtype)).tolist()
    near, far = float(err[dist <= q1].mean()), float(err[dist >= q3].mean())
    return {
        "integrated_error": {
            "paper_prior": correction_error(run.gp_paper, system),
            "marginal_likelihood": correction_error(run.gp_ml, system),
        },
        "energy_of_F": integrated_norm(system.true_correction, system.domain),
        "energy_of_G_plus_F": integrated_norm(system.true_rhs, system.domain),
        "max_error": float(err.max()),
        "near_vs_far": {
            "distance_quartiles": [q1, q3],
            "mean_error_near": near,
            "mean_error_far": far,
            "far_over_near": far / near,
            "definition": "grid points of D (101 x 101) by distance to the training trajectories: "
            "nearest quarter vs farthest quarter",
        },
        "files": files,
    }


# ===================================================================================== §5.2 design (Figs 3-4)
@dataclass(frozen=True)
class _Designs:
    """Designs compared on one system (Figs 3-4 and 6-7): the fits of their samples and their test predictions."""

    system: MisspecifiedSystem
    candidates: torch.Tensor  # (N, d)
    times: torch.Tensor  # (T,) observed
    fine: torch.Tensor  # (61,) plotted / scored
    prior: CorrectionGP
    plans: dict  # name -> DesignResult
    traj_obs: dict  # name -> (K, T, d) true trajectories of the picks, observed
    traj_fine: dict  # name -> (K, 61, d) the same on the fine grid
    gps: dict  # name -> CorrectionGP conditioned on the picks' samples
    y_test: torch.Tensor  # (K', d)
    test_idx: torch.Tensor | None  # (K',) indices of the test set in the candidates, or None
    test_true: torch.Tensor  # (K', 61, d)
    test_mis: torch.Tensor
    corrected: dict  # name -> (K', 61, d)


def _compare_designs(
    system: MisspecifiedSystem,
    candidates: torch.Tensor,
    plans: dict,
    prior: CorrectionGP,
    times: torch.Tensor,
    fine: torch.Tensor,
    gen: torch.Generator,
    *,
    y_test: torch.Tensor | None = None,
    n_test_unchosen: int = 0,
) -> _Designs:
    """Sample each plan's true trajectories (oracle + noise), fit the prior's fixed copy, predict a test set.

    The test set is ``y_test`` or, when it is None, ``n_test_unchosen`` random candidates no plan picked (drawn
    from ``gen`` after the samples).
    """
    traj_obs, traj_fine, gps = {}, {}, {}
    for name, plan in plans.items():
        y0 = candidates[plan.indices]
        obs = simulate(system, y0, times)
        samples = correction_samples(obs, system, derivative="oracle", noise_std=NOISE_STD, generator=gen)
        traj_obs[name] = obs.states
        traj_fine[name] = simulate(system, y0, fine).states
        gps[name] = prior.fixed_copy().fit(samples.inputs, samples.targets)
    test_idx = None
    if y_test is None:
        chosen = set(torch.cat([p.indices for p in plans.values()]).tolist())
        free = torch.tensor([i for i in range(candidates.shape[0]) if i not in chosen])
        test_idx = free[torch.randperm(free.numel(), generator=gen)[:n_test_unchosen]]
        y_test = candidates[test_idx]
    corrected = {name: CorrectedODE(system, gp).predict(y_test, fine) for name, gp in gps.items()}
    test_true, test_mis = _true_and_known(system, y_test, fine)
    return _Designs(
        system=system,
        candidates=candidates,
        times=times,
        fine=fine,
        prior=prior,
        plans=plans,
        traj_obs=traj_obs,
        traj_fine=traj_fine,
        gps=gps,
        y_test=y_test,
        test_idx=test_idx,
        test_true=test_true,
        test_mis=test_mis,
        corrected=corrected,
    )


def _setup_numbers(d: _Designs, candidates: str, prior: dict) -> dict:
    """The set-up of a design comparison, read from it: candidates, K, T, final time, prior, scoring grid."""
    t_final = float(d.times[-1])
    return {
        "candidates": candidates,
        "K": len(next(iter(d.plans.values()))),
        "T": int(d.times.numel()),
        "t_final": t_final,
        "prior": prior,
        "rmse_on": f"{d.fine.numel()} times on [0, {t_final:g}]",
    }


def _linear_design(seed: int, n_test: int = 30) -> _Designs:
    """The Fig 3/4 set-up: the K = 9 design and a random set of 9 on the 13 x 13 grid, their fits, a test set."""
    system = paper_linear()
    times = linear_times()
    candidates = _candidates.grid(system.domain, LINEAR_GRID_SIZE)
    prior = CorrectionGP(**LINEAR_PRIOR)
    gen = _generator(seed, 300)
    plans = {
        "design": _design.greedy(candidates, 9, system=system, times=times, gp=prior),
        "random": _design.random(candidates, 9, generator=gen, system=system, times=times, gp=prior),
    }
    y_test = _candidates.uniform_box(n_test, system.domain, generator=gen)
    return _compare_designs(system, candidates, plans, prior, times, linear_times(FINE_TIMES), gen, y_test=y_test)


def figure_3(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 3: the 13 x 13 candidates, the K = 9 lazy-greedy design (squares) and 9 random picks (circles)
    with their trajectories (left); predictions of both corrected models on test initial conditions (right).

    Returns the picks, their marginal gains and total (proxy) information gain, the information gain along the
    true trajectories, how the design's gain ranks among many random draws, the test RMSE of both corrected
    models and of the misspecified model (all test trajectories), and the integrated errors of both F_hat.
    """
    out = Path(out)
    files: list[str] = []
    s = _session(session, seed).linear_design
    system = s.system
    picks = {name: plan.indices for name, plan in s.plans.items()}
    design_panel = dict(
        picks=picks,
        styles={name: _layout.DESIGN_STYLES[name] for name in picks},
        proxies=s.traj_fine,
        domain=system.domain,
        title=f"Candidates ({LINEAR_GRID_SIZE} x {LINEAR_GRID_SIZE}), design vs random (K = 9)",
    )
    _layout.save(plotting.plot_design(s.candidates, **design_panel), out / "fig3_design.png", files)
    fig, left, right = _layout.side_by_side(12.0, (1.3, 1.0))
    plotting.plot_design(s.candidates, ax=left, **design_panel)
    n_plot = 6
    plotting.plot_trajectories(
        s.test_true[:n_plot],
        s.test_mis[:n_plot],
        s.corrected["design"][:n_plot],
        series={"corrected, random-trained": s.corrected["random"][:n_plot]},
        styles={
            "corrected": {"label": "corrected, design-trained"},
            "corrected, random-trained": {
                **_layout.SECOND_CORRECTED,
                "color": _layout.DESIGN_STYLES["random"]["color"],
            },
        },
        ax=right,
        title=f"Test set ({n_plot} of {s.y_test.shape[0]} initial conditions)",
    )
    fig.suptitle("Paper Fig 3 (§5.2): experimental design on the linear system")
    _layout.save(fig, out / "fig3.png", files)

    # how the design's proxy information gain compares with many random sets of the same size
    gen = _generator(seed, 301)
    draws = _pick(_FIG3_RANDOM_DRAWS, smoke)
    proxies = _design.proxy_trajectories(system, s.candidates, s.times)
    rand_gain = [
        float(
            _design.marginal_gains(
                torch.randperm(s.candidates.shape[0], generator=gen)[:9],
                s.candidates,
                system=system,
                gp=s.prior,
                proxies=proxies,
            ).sum()
        )
        for _ in range(draws)
    ]
    mis = _rmse(s.test_mis, s.test_true)
    res = {"misspecified_test_rmse": mis, "energy_of_F": integrated_norm(system.true_correction, system.domain)}
    for name, plan in s.plans.items():
        cor = _rmse(s.corrected[name], s.test_true)
        res[name] = {
            "indices": plan.indices,
            "points": plan.points,
            "gains_nats": plan.gains,
            "information_gain_nats": plan.information_gain,
            "exact_information_gain_nats": _design.true_information_gain(
                plan.indices, s.candidates, system=system, times=s.times, gp=s.prior
            ),
            "test_rmse_corrected": cor,
            "rmse_ratio_to_misspecified": cor / mis,
            "integrated_error": correction_error(s.gps[name], system),
        }
    res["design_over_random"] = {
        "test_rmse": res["design"]["test_rmse_corrected"] / res["random"]["test_rmse_corrected"],
        "integrated_error": res["design"]["integrated_error"] / res["random"]["integrated_error"],
        "information_gain": res["design"]["information_gain_nats"] / res["random"]["information_gain_nats"],
    }
    arr = np.asarray(rand_gain)
    res["random_sets_information_gain_nats"] = {
        **{k: v for k, v in _mean_se(rand_gain).items() if k != "values"},
        "max": float(arr.max()),
        "fraction_below_design": float((arr < res["design"]["information_gain_nats"]).mean()),
    }
    res["setup"] = {
        **_setup_numbers(s, f"{LINEAR_GRID_SIZE} x {LINEAR_GRID_SIZE} grid on D", LINEAR_PRIOR),
        "n_test": int(s.y_test.shape[0]),
        "n_plotted": n_plot,
        "design_method": s.plans["design"].method,
    }
    res["files"] = files
    return res


def figure_4(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 4: |F_hat_i - F_i| over D, random picks (top row) vs design (bottom row), one column per component.

    Returns the integral over D of |F_hat_i - F_i| per component for both, and the energy of each F_i.
    """
    out = Path(out)
    files: list[str] = []
    s = _session(session, seed).linear_design
    system = s.system
    fns = {name: plotting.correction_error_fn(system, s.gps[name], component="all") for name in ("random", "design")}
    fig = plotting.plot_component_error_maps(
        fns,
        system.domain,
        traces=s.traj_obs,
        title=r"Paper Fig 4 (§5.2): $|\hat F_i - F_i|$, random (top) vs "
        r"design (bottom), K = 9",
    )
    _layout.save(fig, out / "fig4.png", files)
    res = {}
    with torch.no_grad():
        for name, fn in fns.items():
            res[name] = {
                "integrated_abs_error": [
                    integrate_over_box(lambda x, c=c, fn=fn: fn(x)[:, c], system.domain)
                    for c in range(system.output_dim)
                ]
            }
        res["energy_of_F_i"] = [
            integrate_over_box(lambda x, c=c: system.true_correction(x)[:, c].abs(), system.domain)
            for c in range(system.output_dim)
        ]
    res["design_over_random"] = [
        d / r for d, r in zip(res["design"]["integrated_abs_error"], res["random"]["integrated_abs_error"], strict=True)
    ]
    res["files"] = files
    return res


# ======================================================================================== §5.2 study (Fig 5)
def _study_numbers(study: StudyResult, ratios: Iterable[tuple[str, str]]) -> dict:
    data = {
        "ks": study.ks,
        "metric": study.metric,
        "realizations": study.realizations,
        "references": study.references,
        "summary": {k: {"mean": m, "stderr": e} for k, (m, e) in study.summary().items()},
        "ratios": {},
        "meta": study.meta,
    }
    for a, b in ratios:
        mean, se = study.ratio(a, b)
        data["ratios"][f"{a}/{b}"] = {"mean": mean, "stderr": se}
    data["table"] = study.table(list(ratios))
    return data


def _study_figure(study, path: Path, labels: dict, ylabel: str, title: str, ratios: list[tuple[str, str]]) -> dict:
    """Error-vs-K curves of a study (Figs 5 and 8) and the numbers behind them."""
    files: list[str] = []
    fig = _layout.curves_figure(
        study.ks, study.summary(), references=study.references, ylabel=ylabel, title=title, labels=labels
    )
    _layout.save(fig, path, files)
    data = _study_numbers(study, ratios)
    data["files"] = files
    return data


def figure_5(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 5: integrated error of F_hat vs K for design / random / data-driven, with the energies of F and
    G + F (:func:`~torchmisspec.paper.studies.linear_study`, 10 realizations; smoke: 2 and fewer K).

    Returns the study's summary (mean and standard error per K) and the paired per-K ratios design/random,
    data-driven/design and random/design (mean and standard error over realizations).
    """
    _session(session, seed)  # nothing shared; checks the arguments
    study = linear_study(_pick(_FIG5_KS, smoke), _pick(_FIG5_REALIZATIONS, smoke), seed=seed, progress=progress)
    labels = {
        "design": "design + misspecified model",
        "random": "random sets + misspecified model",
        "data-driven": "design + fully data-driven GP",
    }
    data = _study_figure(
        study,
        Path(out) / "fig5.png",
        labels,
        r"$\int_D \|\hat F(y) - F(y)\|_2\,dy$",
        f"Paper Fig 5 (§5.2): estimation error vs training set size\n"
        f"linear system, {study.realizations} realizations, mean ± standard error",
        [("design", "random"), ("data-driven", "design"), ("random", "design")],
    )
    return data


# ============================================================================== §5.3 gravity (Figs 6, 7 and 8)
_GRAVITY_NAMES = ("agnostic", "misspecified-aided")


def _gravity(seed: int, n_test: int = 5) -> _Designs:
    """The Fig 6/7 set-up; candidates and designs are those of :func:`gravity_study` with the same seed."""
    system = paper_gravity()
    candidates = _candidates.orbits(GRAVITY_CANDIDATES, generator=torch.Generator().manual_seed(seed))
    times = gravity_times()
    prior = CorrectionGP(**GRAVITY_PRIOR)
    plans = {
        "agnostic": _design.agnostic(candidates, 7, system=system, times=times, gp=prior),
        "misspecified-aided": _design.greedy(candidates, 7, system=system, times=times, gp=prior),
    }
    return _compare_designs(
        system,
        candidates,
        plans,
        prior,
        times,
        gravity_times(FINE_TIMES),
        _generator(seed, 600),
        n_test_unchosen=n_test,
    )


def _masses(system: MisspecifiedSystem) -> dict:
    """Rows (x, y, m) of the known and unknown point masses, read from the system's fields."""

    def rows(field):
        return torch.cat([field.positions, field.masses.unsqueeze(-1)], -1)

    return {"known mass": rows(system.known), "unknown masses": rows(system.correction)}


def figure_6(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 6: gravity; candidate positions, masses, agnostic and misspecified-aided designs (K = 7) with their
    trajectories, D dashed (left); predictions on a random test set of unchosen candidates (right).

    Returns the picks, their gains (each design's own criterion) and the information gain of each design's true
    trajectories, and the test RMSE (positions and velocities) of the misspecified model and both corrected ones.
    """
    out = Path(out)
    files: list[str] = []
    g = _session(session, seed).gravity
    system = g.system
    design_panel = dict(
        picks={n: g.plans[n].indices for n in _GRAVITY_NAMES},
        styles={n: _layout.DESIGN_STYLES[n] for n in _GRAVITY_NAMES},
        proxies=g.traj_fine,
        masses=_masses(system),
        domain=system.domain,
        axis_labels=("$x_1$", "$x_2$"),
        title=f"{g.candidates.shape[0]} candidates, designs of size K = 7",
    )
    _layout.save(plotting.plot_design(g.candidates[:, :2], **design_panel), out / "fig6_design.png", files)
    fig, left, right = _layout.side_by_side(12.5, (1.2, 1.0))
    plotting.plot_design(g.candidates[:, :2], ax=left, **design_panel)
    plotting.plot_trajectories(
        g.test_true,
        g.test_mis,
        g.corrected["misspecified-aided"],
        series={"corrected, agnostic design": g.corrected["agnostic"]},
        styles={
            "corrected": {"label": "corrected, aided design"},
            "corrected, agnostic design": {
                **_layout.SECOND_CORRECTED,
                "color": _layout.DESIGN_STYLES["agnostic"]["color"],
            },
        },
        ax=right,
        axis_labels=("$x_1$", "$x_2$"),
        title=f"Test set: {g.test_idx.numel()} random unchosen candidates",
    )
    right.set_aspect("equal", adjustable="datalim")
    fig.suptitle("Paper Fig 6 (§5.3): misspecified gravitational field")
    _layout.save(fig, out / "fig6.png", files)
    bands = _bands(
        CorrectedODE(system, g.gps["misspecified-aided"]),
        g.y_test,
        g.fine,
        g.test_true,
        g.test_mis,
        samples=_pick(_BAND_SAMPLES, smoke),
        generator=_generator(seed, 906),
        title="Fig 6 with bands: test candidate 1, aided design",
        path=out / "fig6_bands.png",
        files=files,
    )

    mis = _rmse(g.test_mis, g.test_true)
    res = {"misspecified_test_rmse": mis, "test_indices": g.test_idx, "bands": bands}
    for name in _GRAVITY_NAMES:
        plan = g.plans[name]
        cor = _rmse(g.corrected[name], g.test_true)
        res[name] = {
            "indices": plan.indices,
            "positions": plan.points[:, :2],
            "gains_nats_own_criterion": plan.gains,
            "information_gain_nats_own_criterion": plan.information_gain,
            "exact_information_gain_nats": _design.true_information_gain(
                plan.indices, g.candidates, system=system, times=g.times, gp=g.prior
            ),
            "test_rmse_corrected": cor,
            "rmse_ratio_to_misspecified": cor / mis,
            "test_rmse_positions": _rmse(g.corrected[name][..., :2], g.test_true[..., :2]),
        }
    res["misspecified_test_rmse_positions"] = _rmse(g.test_mis[..., :2], g.test_true[..., :2])
    res["aided_over_agnostic_test_rmse"] = (
        res["misspecified-aided"]["test_rmse_corrected"] / res["agnostic"]["test_rmse_corrected"]
    )
    res["setup"] = {
        **_setup_numbers(g, f"design.candidates.orbits({GRAVITY_CANDIDATES}, seed)", GRAVITY_PRIOR),
        "domain": system.domain,
    }
    res["files"] = files
    return res


def figure_7(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 7: ||F_hat_{3,4} - F_{3,4}||_2 for the agnostic (left) and aided (right) designs over a box larger
    than D (D dashed), log colour scale.

    Returns the mean squared error over D of both (and over the larger box), and the mean energy of F over D.
    """
    out = Path(out)
    files: list[str] = []
    g = _session(session, seed).gravity
    system = g.system
    fns = {name: plotting.correction_error_fn(system, g.gps[name]) for name in _GRAVITY_NAMES}
    fig = plotting.plot_component_error_maps(
        fns,
        _FIG7_BOX,
        traces={n: g.traj_fine[n] for n in _GRAVITY_NAMES},
        settings_as_columns=True,
        log_scale=True,
        dashed_box=system.domain,
        axis_labels=("$x_1$", "$x_2$"),
        component_labels=[r"$\|\hat F_{3,4} - F_{3,4}\|_2$"],
        title="Paper Fig 7 (§5.3): estimation error, D dashed, training trajectories in white",
    )
    _layout.save(fig, out / "fig7.png", files)
    res = {}
    for name in _GRAVITY_NAMES:
        res[name] = {
            "mse_over_D": correction_error(g.gps[name], system, metric="mean_squared"),
            "mse_over_box": correction_error(g.gps[name], system, domain=_FIG7_BOX, metric="mean_squared"),
        }
    res["aided_over_agnostic_mse_over_D"] = res["misspecified-aided"]["mse_over_D"] / res["agnostic"]["mse_over_D"]
    res["mean_energy_of_F_over_D"] = mean_squared_error(
        lambda x: torch.zeros_like(x), system.true_correction, system.domain
    )
    res["box"] = _FIG7_BOX
    res["domain"] = system.domain
    res["files"] = files
    return res


def figure_8(
    out: Path, *, smoke: bool = False, seed: int = 0, progress: bool = False, session: Session | None = None
) -> dict:
    """Paper Fig 8: mean squared error of F_hat over D vs K = 1..7, agnostic vs aided design (and random sets),
    over noise realizations (:func:`~torchmisspec.paper.studies.gravity_study`; the paper uses 400; smoke: 3).

    Returns the summary per K and the paired ratios aided/agnostic and aided/random per K with standard errors.
    """
    _session(session, seed)  # nothing shared; checks the arguments
    study = gravity_study(realizations=_pick(_FIG8_REALIZATIONS, smoke), seed=seed, progress=progress)
    labels = {
        "misspecified-aided": "misspecified-aided design",
        "agnostic": "agnostic design",
        "random": "random sets (new each realization)",
    }
    return _study_figure(
        study,
        Path(out) / "fig8.png",
        labels,
        r"$\frac{1}{|D|}\int_D \|\hat F_{3,4} - F_{3,4}\|_2^2\,dy$",
        f"Paper Fig 8 (§5.3): average estimation error vs training set size\n"
        f"gravity, {study.realizations} noise realizations, mean ± standard error",
        [("misspecified-aided", "agnostic"), ("misspecified-aided", "random")],
    )


# ============================================================================================ shared work
class Session:
    """The work several figures share, for one seed: built on first use, kept as long as this object lives.

    * :attr:`linear_fit`: realization 0 of §5.1 (Figs 1 and 2);
    * :attr:`linear_design`: the K = 9 design and random set of §5.2 with their fits (Figs 3 and 4);
    * :attr:`gravity`: the §5.3 candidates, designs and fits (Figs 6 and 7).

    :func:`reproduce` makes one per run and passes it to every figure (``figure_N(out, session=...)``); a figure
    called without one makes its own. The fitted models live in this object, not in the module.
    """

    def __init__(self, seed: int = 0) -> None:
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
            raise InputError(f"seed: expected an integer, got {seed!r} ({type(seed).__name__})")
        self.seed = int(seed)

    @functools.cached_property
    def linear_fit(self) -> _LinearFit:
        return _linear_fit_run(self.seed, 0)

    @functools.cached_property
    def linear_design(self) -> _Designs:
        return _linear_design(self.seed)

    @functools.cached_property
    def gravity(self) -> _Designs:
        return _gravity(self.seed)

    def __repr__(self) -> str:
        built = [name for name in ("linear_fit", "linear_design", "gravity") if name in self.__dict__]
        return f"Session(seed={self.seed}, built={built})"


def _session(session: Session | None, seed: int) -> Session:
    """``session``, checked against ``seed``, or a new one for ``seed``."""
    if session is None:
        return Session(seed)
    if not isinstance(session, Session):
        raise InputError(f"session: expected a Session or None, got {type(session).__name__}")
    if session.seed != seed:
        raise InputError(f"session: expected a Session for seed={seed} (the seed argument), got seed={session.seed}")
    return session


# ==================================================================================================== driver
FIGURES: dict[int, Callable[..., dict]] = {
    1: figure_1,
    2: figure_2,
    3: figure_3,
    4: figure_4,
    5: figure_5,
    6: figure_6,
    7: figure_7,
    8: figure_8,
}


def reproduce(
    figures: Iterable[int],
    out: str | Path = "reproduction-output",
    *,
    smoke: bool = False,
    seed: int = 0,
    progress: bool = False,
    threads: int | None = 1,
) -> dict:
    """Run the given figures (numbers 1-8) into ``out`` and write ``out/results.json``.

    ``results.json`` holds ``{"smoke", "seed", "figures": {"fig1": numbers, ...}, "seconds": {"fig1": s, ...,
    "total": s}, "realizations": {"fig1": n, "fig5": n, "fig8": n}, "torch_threads"}``; it is rewritten after
    every figure, so a long run leaves the finished figures' numbers behind. Returns the same dict.

    ``threads``: torch intra-op threads during the run (restored afterwards; ``None`` leaves torch's setting).
    The matrices here are small (at most a few hundred samples), so one thread loses nothing, and it keeps the
    timings stable on a shared machine: with every core's thread spinning, a busy neighbour made single
    factorizations of a 440 x 440 matrix take 100x longer.
    """
    if threads is not None:
        threads = check_positive_int(threads, "threads")
    try:
        numbers = [int(n) for n in figures]
    except (TypeError, ValueError) as exc:
        raise InputError(f"figures: expected figure numbers in 1..8, got {figures!r}") from exc
    bad = [n for n in numbers if n not in FIGURES]
    if not numbers or bad:
        raise InputError(f"figures: expected at least one figure number in 1..8, got {numbers}")
    numbers = sorted(set(numbers))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {
        "smoke": bool(smoke),
        "seed": int(seed),
        "figures": {},
        "seconds": {},
        "realizations": {},
    }
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _run(numbers, out, results, smoke=smoke, session=Session(seed), progress=progress)
    finally:
        torch.set_num_threads(previous)


def _run(numbers: list[int], out: Path, results: dict, *, smoke: bool, session: Session, progress: bool) -> dict:
    results["torch_threads"] = torch.get_num_threads()
    say = None
    if progress:
        from tqdm.auto import tqdm

        say = tqdm.write
    start = time.perf_counter()
    for n in numbers:
        key = f"fig{n}"
        if say is not None:
            say(f"Figure {n}: running ...")
        t0 = time.perf_counter()
        nums = _jsonable(FIGURES[n](out, smoke=smoke, seed=session.seed, progress=progress, session=session))
        results["seconds"][key] = time.perf_counter() - t0
        results["figures"][key] = nums
        if "realizations" in nums:
            results["realizations"][key] = int(nums["realizations"])
        results["seconds"].pop("total", None)  # keep "total" last
        results["seconds"]["total"] = time.perf_counter() - start
        (out / "results.json").write_text(json.dumps(results, indent=2))
        if say is not None:
            say(f"Figure {n}: done in {results['seconds'][key]:.1f} s -> {', '.join(nums.get('files', []))}")
    return results
