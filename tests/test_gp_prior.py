"""Hyperparameters before any data: CorrectionGP.prior (issue 11, point 4)."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.paper._setup import LINEAR_PRIOR
from torchmisspec.systems import LinearField, MisspecifiedSystem

DT = torch.float64


def test_the_rule_on_the_paper_linear_system():
    system = tms.systems.paper_linear()
    gp = tms.CorrectionGP.prior(system, noise_variance=1e-4)
    assert not gp.is_fitted and gp.kernel == "rbf"
    assert gp.lengthscale == pytest.approx(1.0)  # half the side of D = [-1, 1]^2, the paper's value
    # independent evaluation: G(y) = A y on a 33 x 33 grid over D, median of ||A y|| / sqrt(2)
    axis = torch.linspace(-1, 1, 33, dtype=DT)
    y = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    A = torch.tensor([[0.02, 0.10], [-0.10, -0.06]], dtype=DT)
    g = float((y @ A.T).norm(dim=-1).median()) / 2**0.5
    assert gp.outputscale == pytest.approx((0.1 * g) ** 2, rel=1e-12)
    assert 0.5 < gp.outputscale / LINEAR_PRIOR["outputscale"] < 2  # the paper's choice, within a factor 2
    assert gp.noise_variance == 1e-4
    # a design can start from it
    plan = tms.design.greedy(
        tms.design.candidates.grid(system.domain, 5), 2, system=system, times=torch.linspace(0, 6, 11), gp=gp
    )
    assert plan.indices.numel() == 2 and plan.diagnostics["conditioned"] == 0
    wider = tms.CorrectionGP.prior(system, noise_variance=1e-4, relative_size=0.2, lengthscale_fraction=0.25)
    assert wider.outputscale == pytest.approx(4 * gp.outputscale) and wider.lengthscale == pytest.approx(0.5)


def test_a_singular_known_model_uses_the_median():
    # the gravity set-up: G is a point mass at the origin, a grid point of D; its norm there is infinite
    gp = tms.CorrectionGP.prior(tms.systems.paper_gravity(), noise_variance=1e-4)
    assert 0 < gp.outputscale < float("inf") and gp.lengthscale == pytest.approx(2.0)


def test_bad_input():
    system = tms.systems.paper_linear()
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(tms.InputError, match="relative_size"):
            tms.CorrectionGP.prior(system, noise_variance=1e-4, relative_size=bad)
    with pytest.raises(tms.InputError, match="noise_variance"):
        tms.CorrectionGP.prior(system, noise_variance=0.0)
    with pytest.raises(TypeError):
        tms.CorrectionGP.prior(system)  # the samples' noise only the experimenter knows
    with pytest.raises(tms.InputError, match="size: expected an integer >= 2, got 1"):
        tms.CorrectionGP.prior(system, noise_variance=1e-4, grid_size=1)
    with pytest.raises(
        tms.InputError,
        match="kernel: expected a stationary kernel with a lengthscale such as 'rbf' or 'matern52', got 'polynomial'",
    ):
        tms.CorrectionGP.prior(system, noise_variance=1e-4, kernel="polynomial")
    with pytest.raises(tms.ShapeError, match=r"states: expected \(M, 2\) full states"):
        tms.CorrectionGP.prior(system, noise_variance=1e-4, states=torch.zeros(5, 3))
    no_domain = MisspecifiedSystem(LinearField(torch.eye(2, dtype=DT)), 2)
    with pytest.raises(tms.InputError, match="has no domain D"):
        tms.CorrectionGP.prior(no_domain, noise_variance=1e-4)
    zero = MisspecifiedSystem(LinearField(torch.zeros(2, 2, dtype=DT)), 2, domain=((-1, 1), (-1, 1)))
    with pytest.raises(tms.InputError, match="G is zero or not finite"):
        tms.CorrectionGP.prior(zero, noise_variance=1e-4)
    with pytest.raises(tms.InputError, match="system: expected a MisspecifiedSystem"):
        tms.CorrectionGP.prior("paper_linear", noise_variance=1e-4)


def test_a_prior_for_f_on_an_input_evaluates_g_at_the_inputs_and_scales_each_side():
    """F on a biomass (side 3) and a temperature the lab sets (side 12): G is evaluated on the grid over both, the
    temperature given to G as its control, and each input's lengthscale is the fraction of its own side (issue 42:
    this raised IndexError, and one lengthscale served both units)."""

    def growth(t, y, u):  # G(t, y, u): logistic growth at a rate set by the temperature
        rate = 0.05 * u[..., 0]
        return torch.stack([rate * y[..., 0] * (1 - y[..., 0] / 3.0), -0.1 * y[..., 1]], dim=-1)

    system = tms.MisspecifiedSystem(
        growth, 2, num_controls=1, correction_inputs=[0, 2], correction_outputs=[0], domain=[(0.0, 3.0), (10.0, 22.0)]
    )
    gp = tms.CorrectionGP.prior(system, noise_variance=1e-4, grid_size=9)
    x = design.candidates.grid(system.domain, 9)
    g = 0.05 * x[:, 1] * x[:, 0] * (1 - x[:, 0] / 3.0)  # G's output 0 on the grid, by hand
    assert gp.outputscale == pytest.approx((0.1 * float(g.abs().median())) ** 2)
    assert gp.kernel_spec.input_scale == pytest.approx((3 / 7.5, 12 / 7.5))
    per_input = [gp.lengthscale * c for c in gp.kernel_spec.input_scale]
    assert per_input == pytest.approx([0.5 * 3.0, 0.5 * 12.0])
    with pytest.raises(tms.InputError, match="expected None for system .* with 1 control"):
        tms.CorrectionGP.prior(system, noise_variance=1e-4, states=torch.zeros(4, 2))
