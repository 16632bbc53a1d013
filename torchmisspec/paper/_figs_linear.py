"""§5.1, the linear system: Fig 1 (training and test trajectories, and their bands) and Fig 2 (the error map of
the correction)."""

from __future__ import annotations

from pathlib import Path

import torch

from .. import plotting
from .._validation import progress_bar
from ..gp import CorrectionGP
from ..metrics import box_grid, correction_error, integrated_norm
from ..prediction.dynamics import CorrectedODE
from . import _layout
from ._measures import _BAND_SAMPLES, _bands, _mean_se, _pick, _rmse
from ._session import Session, _generator, _linear_fit_run, _LinearFit, _session
from ._setup import LINEAR_PRIOR, NOISE_STD

# Sizes: (full, smoke).
_FIG1_REALIZATIONS = (20, 3)


def _hyper(gp: CorrectionGP) -> dict:
    return {
        "lengthscale": float(gp.lengthscale),
        "outputscale": float(gp.outputscale),
        "noise_variance": float(gp.noise_variance),
        "log_marginal_likelihood": gp.log_marginal_likelihood_,
    }


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
