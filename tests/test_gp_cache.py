"""The cached posterior solve can never be stale: every public way of changing the hyperparameters or the data
is seen at the next prediction, which then uses the new values (compared with a hand-written Cholesky posterior)."""

import math

import pytest
import torch

import torchmisspec as tms

DT = torch.float64


def _data(seed=0, n=50):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    Y = 0.05 * torch.stack([torch.sin(2 * X[:, 0]), X.pow(2).sum(-1)], -1)
    return X, Y + 0.01 * torch.randn(n, 2, generator=g, dtype=DT)


def _posterior_mean(X, Y, Xs, lengthscale, outputscale, noise):
    """Hand-written RBF posterior mean (independent of GPyTorch)."""

    def k(a, b):
        return outputscale * torch.exp(-0.5 * torch.cdist(a, b).pow(2) / lengthscale**2)

    L = torch.linalg.cholesky(k(X, X) + noise * torch.eye(X.shape[0], dtype=DT))
    return k(Xs, X) @ torch.cholesky_solve(Y, L)


@pytest.fixture
def fitted():
    X, Y = _data()
    return tms.CorrectionGP().fit(X, Y), X, Y


XS = torch.linspace(-1, 1, 9, dtype=DT).reshape(-1, 1).expand(-1, 2) * torch.tensor([1.0, -0.5], dtype=DT)


def _check(gp, X, Y):
    expected = _posterior_mean(X, Y, XS, gp.lengthscale, gp.outputscale, gp.noise_variance)
    torch.testing.assert_close(gp.predict_mean(XS), expected, rtol=1e-9, atol=1e-13)
    torch.testing.assert_close(gp.predict(XS).mean, expected, rtol=1e-9, atol=1e-13)


def test_outputscale_changed_through_the_gpytorch_model(fitted):
    """The issue's reproducer: gp.model.covar_module.outputscale *= 10 used to leave predict_mean on the old solve."""
    gp, X, Y = fitted
    before = gp.predict_mean(XS)
    old = gp.outputscale
    gp.model.covar_module.outputscale = gp.model.covar_module.outputscale * 10
    assert gp.outputscale == pytest.approx(10 * old, rel=1e-12)
    after = gp.predict_mean(XS)
    assert (after - before).abs().max() > 1e-3 * before.abs().max()  # the change matters ...
    _check(gp, X, Y)  # ... and the prediction follows it exactly


@pytest.mark.parametrize("what", ["lengthscale", "noise", "raw_parameter_inplace"])
def test_hyperparameters_changed_through_the_modules(fitted, what):
    gp, X, Y = fitted
    gp.predict_mean(XS)
    lml = gp.log_marginal_likelihood_
    if what == "lengthscale":
        gp.covar_module.base_kernel.lengthscale = torch.tensor(0.3, dtype=DT)
    elif what == "noise":
        gp.likelihood.noise = torch.tensor([1e-2], dtype=DT)
    else:
        with torch.no_grad():
            gp.model.covar_module.base_kernel.raw_lengthscale.add_(0.5)
    _check(gp, X, Y)
    assert gp.log_marginal_likelihood_ != lml  # the reported likelihood follows the values in use


def test_training_data_replaced_or_edited(fitted):
    gp, X, Y = fitted
    gp.predict_mean(XS)
    X2, Y2 = _data(seed=1, n=30)
    gp.model.set_train_data(X2, Y2.T.contiguous(), strict=False)
    assert gp.train_inputs_.shape == (30, 2)
    _check(gp, X2, Y2)
    halved = X2 * 0.5
    with torch.no_grad():
        gp.model.train_inputs[0].mul_(0.5)  # in place (X2 itself is the model's tensor)
    _check(gp, halved, Y2)


def test_kernel_module_replaced(fitted):
    gp, X, Y = fitted
    gp.predict_mean(XS)
    new = tms.CorrectionGP(lengthscale=0.4, outputscale=2e-3, noise_variance=1e-4).covar_module
    gp.model.covar_module = new
    assert gp.lengthscale == pytest.approx(0.4)
    _check(gp, X, Y)


def test_no_refactorization_when_nothing_changed(fitted, monkeypatch):
    gp, X, Y = fitted
    gp.predict_mean(XS)

    def forbidden(*args, **kwargs):
        raise AssertionError("refactorized although nothing changed")

    monkeypatch.setattr(torch.linalg, "cholesky_ex", forbidden)
    monkeypatch.setattr(torch.linalg, "cholesky", forbidden)
    for _ in range(3):
        gp.predict_mean(XS)
        gp.predict(XS)


def test_corrected_ode_follows_a_changed_gp():
    system = tms.systems.paper_linear()
    times = torch.linspace(0, 6, 11, dtype=DT)
    y0 = tms.design.candidates.grid(system.domain, 4)
    samples = tms.correction_samples(tms.simulate(system, y0, times), system, derivative="oracle")
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4).fit(samples.inputs, samples.targets)
    ode = tms.CorrectedODE(system, gp)
    before = ode.predict(y0[:3], times)
    gp.model.covar_module.outputscale = torch.tensor(4e-3, dtype=DT)
    after = ode.predict(y0[:3], times)
    fresh = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-3, noise_variance=1e-4).fit(
        samples.inputs, samples.targets
    )
    torch.testing.assert_close(after, tms.CorrectedODE(system, fresh).predict(y0[:3], times), rtol=1e-9, atol=1e-12)
    assert not torch.allclose(before, after, rtol=0, atol=1e-9)
    assert math.isfinite(gp.log_marginal_likelihood_)
