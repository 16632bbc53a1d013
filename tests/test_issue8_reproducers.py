"""Each reproducer of issue 8 ("hard to break"), as reported, now gives a clear package error or a correct result.

Most classes are also covered where their module is tested (test_ode, test_persistence, test_gp, test_cli, the
fuzz module); this file keeps the reported cases together so that none can come back unnoticed.
"""

import math

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.systems import MisspecifiedSystem

DT = torch.float64


@pytest.fixture(scope="module")
def fitted():
    system = tms.systems.paper_linear()
    y0 = tms.design.candidates.grid(system.domain, 3)
    s = tms.correction_samples(tms.simulate(system, y0, torch.linspace(0, 6, 6, dtype=DT)), system, derivative="oracle")
    return system, tms.CorrectionGP(lengthscale=1.0, outputscale=1e-4, noise_variance=1e-4).fit(s.inputs, s.targets)


# ------------------------------------------------------------------------------------------- severity 1: hangs
def test_corrected_model_driven_into_a_pole_of_g_stops():
    """G = -1/(1 + 3y) from y = 0, with a GP correction that pushes y to -1/3 (used to run for minutes)."""
    x = torch.linspace(-0.5, 0.5, 11, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=10.0, noise_variance=1e-4).fit(x, -2.0 * torch.ones_like(x))
    system = MisspecifiedSystem(lambda y: -1 / (1 + 3 * y), 1, name="pole")
    with pytest.raises(tms.IntegrationError, match=r"CorrectedODE.predict: the solver stalled at t = 0.07"):
        tms.CorrectedODE(system, gp).predict(torch.zeros(3, 1, dtype=DT), torch.tensor([0.0, 5.0], dtype=DT))


def test_nan_tolerances_are_refused_before_solving():
    system = tms.systems.paper_linear()
    with pytest.raises(tms.InputError, match="rtol: expected a positive finite number, got nan"):
        tms.simulate(system, torch.ones(1, 2, dtype=DT), torch.tensor([0.0, 1.0], dtype=DT), rtol=float("nan"))


# ----------------------------------------------------------------------------------- severity 2: wrong answers
def test_integrated_error_refuses_fields_of_different_shapes():
    with pytest.raises(tms.ShapeError, match=r"same shape \(M, m\).*got \(\d+, 1\) and \(\d+, 2\)"):
        tms.integrated_error(lambda x: x[:, :1], lambda x: x, ((-1, 1), (-1, 1)), resolution=5)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"correction_inputs": [0.7]}, r"correction_inputs: expected a sequence of integers, got 0.7"),
        ({"known_matrix": torch.full((2, 2), float("nan"))}, "known_matrix: expected finite values"),
    ],
)
def test_systems_refuse_fractional_indices_and_nan_matrices(kwargs, message):
    with pytest.raises(tms.InputError, match=message):
        MisspecifiedSystem(lambda y: y, 2, **kwargs)


def test_bool_complex_and_string_values_are_refused():
    with pytest.raises(tms.InputError, match="lengthscale: expected a positive finite number, got True"):
        tms.CorrectionGP(lengthscale=True)
    with pytest.raises(tms.InputError, match="complex"):
        tms.CorrectionGP().fit(np.ones((4, 2)) * (1 + 1j), np.ones((4, 2)))
    with pytest.raises(
        tms.InputError, match=r"dtype: expected a floating torch.dtype such as torch.float64, got 'float64'"
    ):
        tms.CorrectionGP(dtype="float64")
    with pytest.raises(tms.InputError, match="max_iter: expected an integer >= 1, got 0"):
        tms.CorrectionGP(max_iter=0)


def test_nan_and_overflow_never_come_back_as_numbers(fitted):
    system, gp = fitted
    with pytest.raises(tms.InputError, match="x: expected finite values"):
        gp.predict_mean(torch.tensor([[float("nan"), 0.0]], dtype=DT))
    poly = tms.CorrectionGP(kernel="polynomial", outputscale=1e-3, noise_variance=1e-4).fit(
        gp.train_inputs_, gp.train_targets_
    )
    with pytest.raises(tms.InputError, match="the prediction is not finite"):
        poly.predict(torch.full((1, 2), 1e300, dtype=DT))
    t = torch.tensor([0.0, 5e-324, 1e-323], dtype=DT)  # one float step apart: the stencil weights overflow
    with pytest.raises(tms.InputError, match="too close in time"):
        tms.finite_difference(torch.arange(3.0, dtype=DT).reshape(1, 3, 1), t)
    with pytest.raises(tms.InputError, match="predicted: expected finite values"):
        tms.trajectory_rmse(torch.full((1, 2, 2), float("nan")), torch.zeros(1, 2, 2))
    with pytest.raises(tms.ShapeError, match="expected non-empty trajectories"):
        tms.trajectory_rmse(torch.zeros(0, 2, 2), torch.zeros(0, 2, 2))
    traj = tms.simulate(system, torch.ones(1, 2, dtype=DT), torch.linspace(0, 1, 101, dtype=DT))
    with pytest.raises(tms.InputError, match=r"correction samples with noise_std=1e\+308 added"):  # 1e308 * |z| > max
        tms.correction_samples(traj, system, derivative="central", noise_std=1e308, generator=torch.Generator())
    fast = MisspecifiedSystem(
        lambda y: y @ torch.full((2, 2), 50.0, dtype=y.dtype),
        2,
        known_matrix=torch.full((2, 2), 50.0, dtype=DT),
        name="fast",
    )
    with pytest.raises(tms.IntegrationError, match="overflow"):
        tms.design.proxy_trajectories(fast, torch.ones(1, 2, dtype=DT), torch.tensor([0.0, 100.0], dtype=DT))


# ------------------------------------------------------------------------------ severity 3: the kind of error
def test_tiny_lengthscales_and_huge_numbers_are_package_errors_or_work():
    x = torch.linspace(0, 1, 5, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(lengthscale=1e-13, outputscale=1.0, noise_variance=1e-2).fit(x, torch.sin(x))
    assert math.isfinite(float(gp.predict_mean(x).sum()))  # no floor any more: a tiny lengthscale is just legal
    with pytest.raises(tms.InputError, match="an integer of 401 digits"):
        tms.CorrectionGP(outputscale=10**400)
    with pytest.raises(tms.BudgetError, match="budget: expected a positive integer, got inf"):
        tms.design.random(torch.zeros(3, 2, dtype=DT), float("inf"))
