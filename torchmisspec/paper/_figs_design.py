"""§5.2, experimental design on the linear system: Fig 3 (the design, the random picks and their predictions),
Fig 4 (the per-component error maps of both) and Fig 5 (error against K)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .. import design as _design
from .. import plotting
from ..metrics import correction_error, integrate_over_box, integrated_norm
from . import _layout
from ._measures import _mean_se, _pick, _rmse, _setup_numbers, _study_figure
from ._session import Session, _Designs, _generator, _session
from ._setup import LINEAR_GRID_SIZE, LINEAR_PRIOR
from .studies import linear_study

# Sizes: (full, smoke).
_FIG3_RANDOM_DRAWS = (200, 10)
_FIG5_KS = ((1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20), (1, 2, 4, 9))
_FIG5_REALIZATIONS = (10, 2)


def _fig3_draw(s: _Designs, out: Path, files: list[str], n_plot: int) -> None:
    """Fig 3's PNGs: the design panel alone, and beside the test predictions of both corrected models."""
    picks = {name: plan.indices for name, plan in s.plans.items()}
    design_panel = dict(
        picks=picks,
        styles={name: _layout.DESIGN_STYLES[name] for name in picks},
        proxies=s.traj_fine,
        domain=s.system.domain,
        title=f"Candidates ({LINEAR_GRID_SIZE} x {LINEAR_GRID_SIZE}), design vs random (K = 9)",
    )
    _layout.save(plotting.plot_design(s.candidates, **design_panel), out / "fig3_design.png", files)
    fig, left, right = _layout.side_by_side(12.0, (1.3, 1.0))
    plotting.plot_design(s.candidates, ax=left, **design_panel)
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


def _random_set_gains(s: _Designs, seed: int, smoke: bool) -> list[float]:
    """The proxy information gain of many random sets of 9 candidates: what the design's gain is ranked among."""
    gen = _generator(seed, 301)
    draws = _pick(_FIG3_RANDOM_DRAWS, smoke)
    proxies = _design.proxy_trajectories(s.system, s.candidates, s.times)
    return [
        float(
            _design.marginal_gains(
                torch.randperm(s.candidates.shape[0], generator=gen)[:9],
                s.candidates,
                system=s.system,
                gp=s.prior,
                proxies=proxies,
            ).sum()
        )
        for _ in range(draws)
    ]


def _plan_numbers(s: _Designs, name: str, plan, mis: float) -> dict:
    """One set's picks, gains (proxy and along the true trajectories), test RMSE and integrated error of F_hat."""
    cor = _rmse(s.corrected[name], s.test_true)
    return {
        "indices": plan.indices,
        "points": plan.points,
        "gains_nats": plan.gains,
        "information_gain_nats": plan.information_gain,
        "exact_information_gain_nats": _design.true_information_gain(
            plan.indices, s.candidates, system=s.system, times=s.times, gp=s.prior
        ),
        "test_rmse_corrected": cor,
        "rmse_ratio_to_misspecified": cor / mis,
        "integrated_error": correction_error(s.gps[name], s.system),
    }


def _design_over_random(design: dict, random: dict) -> dict[str, float]:
    """The design's test RMSE, integrated error and information gain over the random picks'."""
    return {
        "test_rmse": design["test_rmse_corrected"] / random["test_rmse_corrected"],
        "integrated_error": design["integrated_error"] / random["integrated_error"],
        "information_gain": design["information_gain_nats"] / random["information_gain_nats"],
    }


def _random_sets_summary(rand_gain: list[float], design_gain: float) -> dict:
    """Mean, standard error and largest gain of the random sets, and the fraction of them below the design's."""
    arr = np.asarray(rand_gain)
    return {
        **{k: v for k, v in _mean_se(rand_gain).items() if k != "values"},
        "max": float(arr.max()),
        "fraction_below_design": float((arr < design_gain).mean()),
    }


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
    n_plot = 6
    _fig3_draw(s, out, files, n_plot)
    rand_gain = _random_set_gains(s, seed, smoke)
    mis = _rmse(s.test_mis, s.test_true)
    res = {"misspecified_test_rmse": mis, "energy_of_F": integrated_norm(system.true_correction, system.domain)}
    for name, plan in s.plans.items():
        res[name] = _plan_numbers(s, name, plan, mis)
    res["design_over_random"] = _design_over_random(res["design"], res["random"])
    res["random_sets_information_gain_nats"] = _random_sets_summary(rand_gain, res["design"]["information_gain_nats"])
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
