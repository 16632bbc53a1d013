"""gp.posterior(): the public posterior object, checked against a hand-written Cholesky posterior."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms

DT = torch.float64


def data(d_out=2, n=25, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=DT) * 2 - 1
    Y = torch.stack([torch.sin(2 * X[:, 0]) * X[:, 1], X[:, 0] ** 2 - 0.3 * X[:, 1]][:d_out], -1)
    return X, Y + 0.01 * torch.randn(Y.shape, generator=g, dtype=DT)


def rbf(a, b, ell, s):
    return s * torch.exp(-0.5 * torch.cdist(a / ell, b / ell).pow(2))


def reference(gp, x1, x2, X, Y, noise=None):
    """Per output o: the mean k(x1, X) C_o^-1 y_o and covariance k(x1, x2) - k(x1, X) C_o^-1 k(X, x2), by hand."""
    means, covs = [], []
    for o in range(Y.shape[1]):
        ell = gp.lengthscale[o] if gp.per_output else gp.lengthscale
        s = gp.outputscale[o] if gp.per_output else gp.outputscale
        s2 = gp.noise_variance[o] if gp.per_output else gp.noise_variance
        D = torch.full((X.shape[0],), float(s2), dtype=DT) + (0.0 if noise is None else noise[:, o])
        L = torch.linalg.cholesky(rbf(X, X, ell, s) + torch.diag(D))
        means.append(rbf(x1, X, ell, s) @ torch.cholesky_solve(Y[:, o : o + 1], L))
        V1 = torch.linalg.solve_triangular(L, rbf(X, x1, ell, s), upper=False)
        V2 = torch.linalg.solve_triangular(L, rbf(X, x2, ell, s), upper=False)
        covs.append(rbf(x1, x2, ell, s) - V1.T @ V2)
    return torch.cat(means, -1), torch.stack(covs)


@pytest.mark.parametrize("layout", ["shared", "per_output", "noise_per_output"])
def test_mean_and_covariance_match_a_hand_written_cholesky_posterior(layout):
    X, Y = data()
    noise = None
    if layout == "noise_per_output":  # one factor per output with a shared kernel
        noise = torch.stack([torch.full((25,), 1e-4, dtype=DT), torch.linspace(1e-5, 1e-3, 25, dtype=DT)], -1)
    gp = tms.CorrectionGP(per_output=layout == "per_output").fit(X, Y, noise=noise)
    post = gp.posterior()
    x1 = torch.rand(7, 2, generator=torch.Generator().manual_seed(1), dtype=DT)
    x2 = torch.rand(5, 2, generator=torch.Generator().manual_seed(2), dtype=DT)
    mean, cov = reference(gp, x1, x2, X, Y, noise)
    torch.testing.assert_close(post.mean(x1), mean, rtol=1e-9, atol=1e-12)
    got = post.covariance(x1, x2)
    assert got.shape[0] == (1 if layout == "shared" else 2)
    torch.testing.assert_close(got.expand(2, -1, -1), cov, rtol=1e-7, atol=1e-12)
    # the covariance's diagonal is predict's variance; the weights reproduce the mean
    diag = post.covariance(x1).diagonal(dim1=-2, dim2=-1).T.expand(-1, 2)
    torch.testing.assert_close(diag, post.predict(x1).variance, rtol=1e-9, atol=1e-14)
    assert post.weights.shape == (25, 2)
    assert post.factor.chol.shape[0] == (1 if layout == "shared" else 2)


def test_feature_kernel_posterior_covariance_agrees_with_its_variance():
    """In feature space (C never formed) the covariance's diagonal is predict's variance, removed terms included."""
    X, Y = data()
    gp = tms.CorrectionGP(kernel="features", degree=2).fit(X, Y)
    post = gp.posterior()
    x = torch.rand(9, 2, generator=torch.Generator().manual_seed(3), dtype=DT)
    cov = post.covariance(x)
    torch.testing.assert_close(
        cov.diagonal(dim1=-2, dim2=-1).T.expand(-1, 2), post.predict(x).variance, rtol=1e-9, atol=1e-14
    )
    assert torch.allclose(cov, cov.transpose(-1, -2))


def test_cached_until_the_model_changes():
    X, Y = data()
    gp = tms.CorrectionGP().fit(X, Y)
    post = gp.posterior()
    assert gp.posterior() is post
    with torch.no_grad():
        gp.covar_module.base_kernel.lengthscale = 0.7
    again = gp.posterior()
    assert again is not post and not post.is_current(gp)
    mean, _ = reference(gp, X[:3], X[:3], X, Y)
    torch.testing.assert_close(again.mean(X[:3]), mean, rtol=1e-9, atol=1e-12)


def test_with_targets_is_conditioning_on_other_targets_and_differentiable():
    X, Y = data()
    gp = tms.CorrectionGP().fit(X, Y)
    Y2 = Y.flip(0).clone().requires_grad_(True)
    x = torch.rand(4, 2, generator=torch.Generator().manual_seed(4), dtype=DT)
    pseudo = gp.posterior().with_targets(Y2)
    torch.testing.assert_close(pseudo.mean(x, check=False), gp.condition(X, Y2.detach()).predict_mean(x))
    # linear in the targets: the gradient of sum(mean) is k(x, X) C^-1 summed over x, for every output
    pseudo.mean(x, check=False).sum().backward()
    C = gp.posterior().training_covariance()[0]
    expected = torch.linalg.solve(C, rbf(X, x, gp.lengthscale, gp.outputscale).sum(-1))
    torch.testing.assert_close(Y2.grad, expected.unsqueeze(-1).expand(-1, 2), rtol=1e-8, atol=1e-10)


def test_differentiable_posterior_reaches_the_hyperparameters():
    X, Y = data()
    gp = tms.CorrectionGP().fit(X, Y)
    x = torch.tensor([[0.3, -0.2]], dtype=DT)
    raw = gp.covar_module.base_kernel.raw_lengthscale
    assert raw.grad is None  # the fit leaves no stale gradient to add to this one
    raw.requires_grad_(True)
    try:
        gp.posterior(differentiable=True).mean(x, check=False).sum().backward()
        grad = float(raw.grad.sum())
    finally:
        raw.requires_grad_(False)
    # the same derivative by autograd through a hand-written posterior mean
    r = raw.detach().clone().requires_grad_(True)
    ell = gp.covar_module.base_kernel.raw_lengthscale_constraint.transform(r)
    C = rbf(X, X, ell, gp.outputscale) + gp.noise_variance * torch.eye(X.shape[0], dtype=DT)
    (rbf(x, X, ell, gp.outputscale) @ torch.linalg.solve(C, Y)).sum().backward()
    assert grad == pytest.approx(float(r.grad.sum()), rel=1e-8)
    assert abs(grad) > 1e-3  # not trivially zero


def test_sample_functions_through_the_posterior():
    X, Y = data()
    gp = tms.CorrectionGP().fit(X, Y)
    draws = gp.posterior().sample_functions(3, generator=torch.Generator().manual_seed(0))
    assert draws(X[:5]).shape == (3, 5, 2)
    assert "Posterior(N=25, d_out=2, dense factor" in repr(gp.posterior())


def test_condition_is_the_one_conditioning_path_for_given_and_fitted_hyperparameters():
    X, Y = data()
    given = tms.CorrectionGP(lengthscale=0.8, outputscale=0.5, noise_variance=1e-4)  # unfitted, every value given
    conditioned = given.condition(X, Y)
    assert not given.is_fitted and conditioned.lengthscale == pytest.approx(0.8) and conditioned.fixed == given.fixed
    mean, _ = reference(conditioned, X[:4], X[:4], X, Y)
    torch.testing.assert_close(conditioned.predict_mean(X[:4]), mean, rtol=1e-9, atol=1e-12)
    assert not hasattr(given, "fixed_copy")  # one path: fit learns what is not given, condition learns nothing
    with pytest.raises(tms.NotFittedError, match=r"condition: expected a fitted GP.*\['lengthscale'\]"):
        tms.CorrectionGP(outputscale=0.5, noise_variance=1e-4).condition(X, Y)


@pytest.mark.parametrize(
    "template",
    [
        lambda: tms.CorrectionGP(lengthscale=0.7, outputscale=0.5, noise_variance=1e-3),
        lambda: tms.CorrectionGP(kernel="features", degree=2, per_output=True),
        lambda: tms.CorrectionGP(kernel="rbf-features", lengthscale=0.7, outputscale=0.5, noise_variance=1e-3),
    ],
    ids=["rbf", "features per output", "rbf-features"],
)
def test_training_covariance_times_is_the_dense_product(template):
    """C V without forming C in feature space: the product with the dense C (known noise per sample included)."""
    X, Y = data(n=30)
    noise = torch.linspace(1e-4, 1e-3, 30, dtype=DT).unsqueeze(-1).expand(30, 2).contiguous()
    gp = template().fit(X, Y, noise=noise)
    post = gp.posterior()
    B = post.factor.alpha.shape[0]
    V = torch.randn(B, 30, 3, generator=torch.Generator().manual_seed(1), dtype=DT)
    torch.testing.assert_close(post.training_covariance_times(V), post.training_covariance() @ V, rtol=1e-12, atol=0)
