import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.metrics import box_grid, integrate_over_box, mean_squared_error


def test_quadrature_closed_forms():
    box = ((-1.0, 1.0), (-1.0, 1.0))
    assert integrate_over_box(lambda x: x[:, 0].abs(), box) == pytest.approx(2.0, rel=1e-12)  # kink on a node
    assert integrate_over_box(lambda x: x[:, 0] ** 2 * x[:, 1] ** 2, box, resolution=401) == pytest.approx(
        4 / 9, rel=1e-4
    )
    box3 = ((0.0, 1.0), (0.0, 2.0), (-1.0, 0.0))
    assert integrate_over_box(lambda x: torch.ones(x.shape[0], dtype=x.dtype), box3, resolution=5) == pytest.approx(2)
    points, weights = box_grid(box, 11)
    assert points.shape == (121, 2) and weights.sum().item() == pytest.approx(4.0)


def test_energy_of_paper_correction_against_scipy(linear_system):
    integrate = pytest.importorskip("scipy.integrate")
    ref, _ = integrate.dblquad(lambda y2, y1: 0.01 * math.sqrt(y1**4 + y2**4), -1, 1, -1, 1, epsabs=1e-12)
    assert tms.integrated_norm(linear_system.correction, linear_system.domain, resolution=201) == pytest.approx(
        ref, rel=1e-4
    )


def test_integrated_error_of_zero_estimate_is_energy(linear_system):
    zero = lambda x: torch.zeros_like(x)  # noqa: E731
    energy = tms.integrated_norm(linear_system.correction, linear_system.domain)
    assert tms.integrated_error(zero, linear_system.correction, linear_system.domain) == pytest.approx(energy)
    mse = mean_squared_error(zero, linear_system.correction, linear_system.domain, resolution=401)
    # (1/4) * integral of 1e-4 (y1^4 + y2^4) over [-1,1]^2 = 1e-4 * 2 * (2/5 * 2) / 4
    assert mse == pytest.approx(1e-4 * 2 * (2 / 5) * 2 / 4, rel=1e-4)


def test_trajectory_rmse():
    a = torch.zeros(2, 3, 2, dtype=torch.float64)
    b = torch.ones(2, 3, 2, dtype=torch.float64)
    b[1] *= 3
    assert tms.trajectory_rmse(a, b).item() == pytest.approx(math.sqrt(5))
    torch.testing.assert_close(
        tms.trajectory_rmse(a, b, per_trajectory=True), torch.tensor([1.0, 3.0], dtype=torch.float64)
    )
    with pytest.raises(tms.ShapeError, match=r"predicted: expected the shape of true \(2, 3, 2\), got \(2, 3\)"):
        tms.trajectory_rmse(a[..., 0], b)


def test_metric_bad_input(linear_system):
    with pytest.raises(tms.InputError, match="domain: expected at least one interval with finite lo < hi"):
        tms.integrated_norm(linear_system.correction, ((1.0, -1.0),))
    with pytest.raises(tms.InputError, match="resolution: expected an integer >= 2"):
        box_grid(((0, 1),), 1)
    with pytest.raises(tms.InputError, match="fn\\(points\\): expected finite"):
        integrate_over_box(lambda x: 1 / x[:, 0], ((0.0, 1.0),))


def test_correction_error_metrics(linear_system):
    """A GP fitted to zero targets predicts F_hat = 0: its errors are the energies of F, in both metrics."""
    x = torch.rand(8, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-3, noise_variance=1e-4).fit(x, torch.zeros(8, 2))
    energy = tms.integrated_norm(linear_system.correction, linear_system.domain)
    assert tms.correction_error(gp, linear_system) == pytest.approx(energy, rel=1e-12)
    mean_sq = tms.correction_error(gp, linear_system, metric="mean_squared", resolution=401)
    assert mean_sq == pytest.approx(1e-4 * 2 * (2 / 5) * 2 / 4, rel=1e-4)
    with pytest.raises(tms.InputError, match=r"metric: expected one of \('integrated', 'mean_squared'\), got 'l1'"):
        tms.correction_error(gp, linear_system, metric="l1")


def test_mean_and_standard_error():
    from torchmisspec.metrics import mean_and_standard_error

    values = torch.tensor([[1.0, 2.0], [3.0, 6.0], [5.0, 10.0]], dtype=torch.float64)
    mean, se = mean_and_standard_error(values)
    torch.testing.assert_close(mean, torch.tensor([3.0, 6.0], dtype=torch.float64))
    # sample std (n - 1) of (1, 3, 5) is 2; of (2, 6, 10) is 4; divided by sqrt(3)
    torch.testing.assert_close(se, torch.tensor([2.0, 4.0], dtype=torch.float64) / math.sqrt(3))
    mean1, se1 = mean_and_standard_error([7.0])
    assert float(mean1) == 7.0 and float(se1) == 0.0
    with pytest.raises(tms.InputError, match="values: expected finite values"):
        mean_and_standard_error([1.0, float("nan")])
