import pytest
import torch

import torchmisspec as tms
from torchmisspec.systems import MisspecifiedSystem


def _fitted(system, times, generator, n_train=40):
    y0 = torch.rand(n_train, system.state_dim, generator=generator, dtype=torch.float64) * 2 - 1
    trajs = tms.simulate(system, y0, times)
    samples = tms.correction_samples(trajs, system, derivative="oracle", noise_std=1e-2, generator=generator)
    return tms.CorrectionGP().fit(samples.inputs, samples.targets)


@pytest.fixture
def fitted(linear_system, paper_times, generator):
    return _fitted(linear_system, paper_times, generator)


def _rmse_ratio(seed, n_train=40, n_test=20):
    """Corrected / misspecified trajectory RMSE of one realization of paper 5.1 (the demo's set-up)."""
    from torchmisspec.paper.demo import linear_demo

    result = linear_demo(None, n_train=n_train, n_test=n_test, seed=seed)
    return result.rmse_ratio


def test_corrected_predictions_beat_misspecified_model_demo_realization():
    """Paper §5.1 as ``torchmisspec demo`` runs it (seed 0): corrected RMSE <= 0.3 x misspecified RMSE."""
    ratio = _rmse_ratio(seed=0)
    assert ratio <= 0.3, f"corrected / misspecified RMSE = {ratio:.3f}"


@pytest.mark.slow
def test_corrected_predictions_beat_misspecified_model_over_realizations():
    """Over 10 realizations (new training and test sets each): always better, 0.45 on average.

    With the paper's noise (sigma_eps = 1e-2 on samples of F whose size is ~1e-2) the ratio is noise-limited:
    measured over 20 realizations it ranges 0.20 .. 0.57 with mean 0.36 (see the closing note of issue 2).
    """
    ratios = torch.tensor([_rmse_ratio(seed) for seed in range(10)])
    assert (ratios < 0.7).all(), ratios
    assert ratios.mean() <= 0.45, ratios


def test_rhs_is_gradcheckable(linear_system, fitted, generator):
    ode = tms.CorrectedODE(linear_system, fitted)
    y = (torch.rand(5, 2, generator=generator, dtype=torch.float64) * 2 - 1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: ode(torch.tensor(0.0), y), (y,), eps=1e-6, atol=1e-8)


def test_rhs_equals_known_plus_posterior_mean(linear_system, fitted, generator):
    ode = tms.CorrectedODE(linear_system, fitted)
    y = torch.rand(8, 2, generator=generator, dtype=torch.float64)
    expected = linear_system.known(y) + fitted.predict(y).mean
    torch.testing.assert_close(ode(torch.tensor(0.0), y), expected, rtol=1e-12, atol=1e-15)


def test_prediction_never_refactorizes(linear_system, paper_times, fitted, monkeypatch, generator):
    def forbidden(*args, **kwargs):
        raise AssertionError("a factorization was attempted inside the ODE solve")

    for name in ("cholesky", "cholesky_ex", "solve", "inv", "eigh"):
        monkeypatch.setattr(torch.linalg, name, forbidden)
    monkeypatch.setattr(torch, "cholesky_solve", forbidden)
    ode = tms.CorrectedODE(linear_system, fitted)
    states = ode.predict(torch.rand(30, 2, generator=generator, dtype=torch.float64), paper_times)
    assert torch.isfinite(states).all() and ode.nfe > 10


def test_batched_prediction_equals_single_solves(linear_system, paper_times, fitted, generator):
    ode = tms.CorrectedODE(linear_system, fitted)
    y0 = torch.rand(4, 2, generator=generator, dtype=torch.float64)
    batched = ode.predict(y0, paper_times, solver=tms.Solver(rtol=1e-10, atol=1e-12))
    for k in range(4):
        single = ode.predict(y0[k], paper_times, solver=tms.Solver(rtol=1e-10, atol=1e-12))
        torch.testing.assert_close(batched[k], single[0], rtol=0, atol=1e-8)


def test_structured_correction_on_gravity(generator):
    system = tms.systems.paper_gravity()
    angle = torch.rand(12, generator=generator, dtype=torch.float64) * 2 * torch.pi
    r = 1.5 + torch.rand(12, generator=generator, dtype=torch.float64)
    v = torch.sqrt(0.2 / r)
    y0 = torch.stack([r * angle.cos(), r * angle.sin(), -v * angle.sin(), v * angle.cos()], -1)
    times = torch.linspace(0, 3, 20, dtype=torch.float64)
    samples = tms.correction_samples(
        tms.simulate(system, y0, times), system, derivative="oracle", noise_std=1e-2, generator=generator
    )
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-3, noise_variance=1e-4).fit(samples.inputs, samples.targets)
    ode = tms.CorrectedODE(system, gp)
    y = y0[:3]
    rhs = ode(torch.tensor(0.0), y)
    torch.testing.assert_close(rhs[:, :2], y[:, 2:])  # the correction leaves the position equations alone
    torch.testing.assert_close(rhs[:, 2:], system.known(y)[:, 2:] + gp.predict_mean(y[:, :2]))


# ------------------------------------------------------------------------------------------------------ bad input
def test_rejects_mismatched_models(linear_system, fitted):
    with pytest.raises(
        tms.ShapeError,
        match=r"gp: expected a GP with 2 inputs and 2 outputs.*got one fitted with 2 "
        r"inputs and 1 outputs",
    ):
        tms.CorrectedODE(
            linear_system, tms.CorrectionGP(**{"lengthscale": 1.0}).fit(torch.rand(5, 2), torch.rand(5, 1))
        )
    with pytest.raises(tms.NotFittedError, match="expected a fitted CorrectionGP"):
        tms.CorrectedODE(linear_system, tms.CorrectionGP())
    ode = tms.CorrectedODE(linear_system, fitted)
    with pytest.raises(tms.ShapeError, match=r"y0: expected a last dimension of size state_dim=2.*\(3, 4\)"):
        ode.predict(torch.zeros(3, 4), torch.arange(3.0))
    with pytest.raises(tms.InputError, match="times: expected strictly increasing"):
        ode.predict(torch.zeros(3, 2), torch.tensor([0.0, 1.0, 0.5]))
    with pytest.raises(tms.InputError, match="y0: expected finite"):
        ode.predict(torch.tensor([[float("inf"), 0.0]]), torch.arange(3.0))


def test_blow_up_is_reported_not_returned_as_nan(generator):
    system = MisspecifiedSystem(lambda y: y**2, 1, name="riccati")
    x = torch.linspace(-1, 3, 30, dtype=torch.float64).unsqueeze(-1)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1.0, noise_variance=1e-4).fit(x, 0.1 * x**2)
    with pytest.raises(tms.IntegrationError, match="blows up"):
        tms.CorrectedODE(system, gp).predict(torch.tensor([[2.0]]), torch.linspace(0, 2, 5))
