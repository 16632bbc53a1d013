"""The demo: paper §5.1 end to end, as ``torchmisspec demo`` runs it.

:func:`linear_demo` draws K random initial conditions in D = [-1, 1]^2, takes oracle samples of F with noise std
1e-2 (sigma_eps^2 = 1e-4) at T = 11 times on [0, 6], fits a correction GP by marginal likelihood, predicts from new
initial conditions, and reports (and optionally plots) what it measured.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from .._validation import check_positive_int
from ..data import simulate
from ..design.candidates import uniform_box
from ..gp import CorrectionGP
from ..learning.samples.observations import correction_samples
from ..metrics import correction_error, integrated_norm, trajectory_rmse
from ..prediction.dynamics import CorrectedODE
from ..systems import MisspecifiedSystem, paper_linear
from ._setup import NOISE_STD

__all__ = ["DemoResult", "linear_demo"]


@dataclass
class DemoResult:
    """Numbers of one run of :func:`linear_demo` (all measured, none typed in)."""

    n_train: int
    n_test: int
    seed: int
    lengthscale: float
    outputscale: float
    noise_variance: float
    log_marginal_likelihood: float
    integrated_error: float
    energy_of_F: float
    energy_of_G_plus_F: float
    rmse_corrected: float
    rmse_misspecified: float
    rhs_evaluations: int
    seconds: dict = field(default_factory=dict)
    figures: list = field(default_factory=list)

    @property
    def rmse_ratio(self) -> float:
        return self.rmse_corrected / self.rmse_misspecified

    def to_dict(self) -> dict:
        return {**asdict(self), "rmse_ratio": self.rmse_ratio}


def linear_demo(
    out: str | Path | None = "demo-output",
    *,
    n_train: int = 40,
    n_test: int = 20,
    seed: int = 0,
    noise_std: float = NOISE_STD,
    num_times: int = 11,
    t_final: float = 6.0,
    progress: bool = False,
    system: MisspecifiedSystem | None = None,
) -> DemoResult:
    """Run paper §5.1 end to end; write figures and ``results.json`` into ``out`` (``None``: no files)."""
    n_train = check_positive_int(n_train, "n_train")
    n_test = check_positive_int(n_test, "n_test")
    num_times = check_positive_int(num_times, "num_times", minimum=2)
    system = paper_linear() if system is None else system
    gen = torch.Generator().manual_seed(seed)
    times = torch.linspace(0.0, t_final, num_times, dtype=torch.float64)
    seconds = {}

    t0 = time.perf_counter()
    y0 = uniform_box(n_train, system.domain, generator=gen)
    train = simulate(system, y0, times)
    samples = correction_samples(train, system, derivative="oracle", noise_std=noise_std, generator=gen)
    seconds["simulate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    gp = CorrectionGP().fit(samples.inputs, samples.targets, progress=progress)
    seconds["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    y_test = uniform_box(n_test, system.domain, generator=gen)
    ode = CorrectedODE(system, gp)
    corrected = ode.predict(y_test, times)
    seconds["predict"] = time.perf_counter() - t0
    test_true = simulate(system, y_test, times).states
    test_mis = simulate(system, y_test, times, known_only=True).states

    result = DemoResult(
        n_train=n_train,
        n_test=n_test,
        seed=seed,
        lengthscale=float(gp.lengthscale),
        outputscale=float(gp.outputscale),
        noise_variance=float(gp.noise_variance),
        log_marginal_likelihood=gp.log_marginal_likelihood_,
        integrated_error=correction_error(gp, system),
        energy_of_F=integrated_norm(system.true_correction, system.domain),
        energy_of_G_plus_F=integrated_norm(system.true_rhs, system.domain),
        rmse_corrected=float(trajectory_rmse(corrected, test_true)),
        rmse_misspecified=float(trajectory_rmse(test_mis, test_true)),
        rhs_evaluations=ode.nfe,
        seconds=seconds,
    )
    if out is not None:
        from .. import plotting

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        train_mis = simulate(system, y0, times, known_only=True).states
        plotting.plot_training_and_test(
            train.states, train_mis, test_true, test_mis, corrected, path=out / "trajectories.png"
        )
        plotting.plot_error_map(
            plotting.correction_error_fn(system, gp),
            system.domain,
            traces=train.states,
            title=r"$\|\hat F(y) - F(y)\|_2$ with training traces",
            path=out / "error_map.png",
        )
        result.figures = [str(out / "trajectories.png"), str(out / "error_map.png")]
        (out / "results.json").write_text(json.dumps(result.to_dict(), indent=2))
    return result
