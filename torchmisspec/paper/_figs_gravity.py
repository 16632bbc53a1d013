"""§5.3, the misspecified gravitational field: Fig 6 (the agnostic and misspecified-aided designs and their
predictions), Fig 7 (the error maps of both over a box larger than D) and Fig 8 (error against K)."""

from __future__ import annotations

from pathlib import Path

import torch

from .. import design as _design
from .. import plotting
from ..metrics import correction_error, mean_squared_error
from ..prediction.dynamics import CorrectedODE
from ..systems import MisspecifiedSystem
from . import _layout
from ._measures import _BAND_SAMPLES, _bands, _pick, _rmse, _setup_numbers, _study_figure
from ._session import Session, _generator, _session
from ._setup import GRAVITY_CANDIDATES, GRAVITY_PRIOR
from .studies import gravity_study

# Sizes: (full, smoke).
_FIG8_REALIZATIONS = (400, 3)
_FIG7_BOX = ((-2.5, 2.5), (-2.5, 2.5))
_GRAVITY_NAMES = ("agnostic", "misspecified-aided")


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
