"""Hyperparameter uncertainty: the Laplace approximation of the log hyperparameters' posterior (issue 10, item 6)."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._laplace import LOG_PRIOR_SD

DT = torch.float64


def data(seed=0, n=40):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    return X, torch.sin(2 * X) + 0.05 * torch.randn(n, 2, generator=g, dtype=DT)


def finite_difference_hessian(gp, X, Y, noise, mean, h=1e-4):
    """Second differences of the exact log marginal likelihood (the cached one) in the raw log hyperparameters."""

    def mll(theta):
        g = gp.condition(X, Y, noise=noise)
        with torch.no_grad():
            i = 0
            for _, p in g._free_parameters():
                p.copy_(theta[i : i + p.numel()].reshape(p.shape))
                i += p.numel()
        return g.posterior().log_marginal_likelihood

    P = mean.numel()
    H = torch.zeros(P, P, dtype=DT)
    for i in range(P):
        for j in range(P):

            def f(a, b, i=i, j=j):
                t = mean.clone()
                t[i] += a
                t[j] += b
                return mll(t)

            H[i, j] = (f(h, h) - f(h, -h) - f(-h, h) + f(-h, -h)) / (4 * h * h)
    return H


@pytest.mark.parametrize(
    "options, known",
    [
        ({}, False),
        ({"kernel": "matern52"}, False),
        ({"per_output": True}, False),
        ({"kernel": "polynomial"}, False),
        ({}, True),
    ],
)
def test_laplace_precision_is_the_negative_hessian_plus_the_prior(options, known):
    X, Y = data()
    noise = torch.linspace(1e-4, 1e-3, len(X), dtype=DT) if known else None
    gp = tms.CorrectionGP(**options).fit(X, Y, noise=noise)
    names, mean, cov = gp.laplace_covariance()
    assert len(names) == mean.numel() == cov.shape[0]
    H = finite_difference_hessian(gp, X, Y, noise, mean)
    assert bool(torch.linalg.eigvalsh(-H).min() > 0)  # a maximum: nothing clipped
    prior = torch.eye(len(names), dtype=DT) / LOG_PRIOR_SD**2
    torch.testing.assert_close(torch.linalg.inv(cov), -H + prior, rtol=1e-5, atol=1e-4)


def test_hyperparameter_samples_follow_the_laplace_covariance():
    X, Y = data(seed=1)
    gp = tms.CorrectionGP().fit(X, Y)
    _, mean, cov = gp.laplace_covariance()
    copies = gp.hyperparameter_samples(400, generator=torch.Generator().manual_seed(0))
    theta = torch.tensor(
        [[float(p.reshape(-1)[0]) for _, p in c._free_parameters()] for c in copies], dtype=DT
    )  # (400, 3) log values
    se = cov.diagonal().sqrt() / 20  # standard error of a mean of 400 draws
    assert bool(((theta.mean(0) - mean).abs() < 4 * se).all())
    sd = cov.diagonal().sqrt()
    # sample covariance of 400 draws: each entry within ~5 standard errors (1 / sqrt(400) in correlation units)
    assert float(((torch.cov(theta.T) - cov) / torch.outer(sd, sd)).abs().max()) < 0.25
    assert all(torch.equal(c.train_inputs_, gp.train_inputs_) for c in copies[:3])


def test_posterior_with_laplace_hyperparameters():
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(0)
    train = tms.simulate(system, torch.rand(6, 2, generator=g, dtype=DT) * 2 - 1, torch.linspace(0, 6, 11, dtype=DT))
    samples = tms.correction_samples(train, system, derivative="oracle", noise_std=1e-2, generator=g)
    gp = tms.CorrectionGP().fit(samples)
    model = tms.CorrectedODE(system, gp)
    y0 = torch.rand(3, 2, generator=g, dtype=DT) * 2 - 1
    times = torch.linspace(0, 6, 7, dtype=DT)
    fixed = model.posterior(y0, times, num_samples=10, generator=torch.Generator().manual_seed(1))
    mixed = model.posterior(
        y0,
        times,
        num_samples=10,
        generator=torch.Generator().manual_seed(1),
        hyperparameters="laplace",
        hyperparameter_samples=4,
    )
    assert mixed.samples.shape == fixed.samples.shape == (10, 3, 7, 2)
    torch.testing.assert_close(mixed.mean_path, fixed.mean_path)  # the mean path is the fitted model's
    assert not torch.equal(mixed.samples, fixed.samples)
    with pytest.raises(tms.InputError, match=r"hyperparameters: expected 'fixed' or 'laplace', got 'bayes'"):
        model.posterior(y0, times, hyperparameters="bayes")
    with pytest.raises(tms.InputError, match=r"hyperparameter_samples: expected"):
        model.posterior(y0, times, hyperparameters="laplace", hyperparameter_samples=0)
    features = tms.CorrectionGP(kernel="features").fit(samples)
    with pytest.raises(tms.InputError, match=r"the feature kernel's weights are not log hyperparameters"):
        features.laplace_covariance()
    every = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-4, noise_variance=1e-4).fit(samples)
    with pytest.raises(tms.InputError, match=r"every hyperparameter is fixed"):
        every.laplace_covariance()
