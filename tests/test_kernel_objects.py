"""A kernel is an object: a new stationary kernel is one class and a registration, and then fit, predict, posterior
paths, calibration, design and save / load all work with it. The example is a rational quadratic kernel
(1 + r^2 / (2 alpha l^2))^(-alpha) with alpha fixed by the object, checked against GPyTorch's ``RQKernel``."""

from __future__ import annotations

import math

import gpytorch
import pytest
import torch

import torchmisspec as tms
from torchmisspec import gp as tgp
from torchmisspec.gp._kernels import REGISTRY, as_kernel, log_positive
from torchmisspec.gp._paths import feature_map, kernel_hyperparameters, kernel_matrix

DT = torch.float64


# ---------------------------------------------------------------------------------------- the one new kernel
class RationalQuadratic(tgp.Stationary):
    """(1 + r^2 / (2 alpha))^(-alpha) of the squared scaled distance r^2: a scale mixture of RBFs."""

    name = "rq"

    def __init__(self, alpha: float = 2.0) -> None:
        self.alpha = float(alpha)

    def config(self) -> dict:
        return {"alpha": self.alpha}

    def module(self, gp, batch_shape):
        base = gpytorch.kernels.RQKernel(batch_shape=batch_shape, lengthscale_constraint=log_positive())
        base.alpha = torch.tensor(self.alpha)
        base.raw_alpha.requires_grad_(False)  # fixed by the object, not learned
        return base

    def profile(self, sq):
        return (1.0 + sq / (2.0 * self.alpha)).pow(-self.alpha)

    def spectral(self, shape, generator, dtype, device):
        # an RBF with precision tau ~ Gamma(alpha, rate alpha): frequencies z sqrt(tau), z standard normal
        z = torch.randn(shape, generator=generator, dtype=dtype, device=device)
        gamma = torch.distributions.Gamma(torch.tensor(self.alpha, dtype=dtype), torch.tensor(self.alpha, dtype=dtype))
        tau = gamma.sample((shape[0], 1, shape[2])).to(device)  # one precision per frequency
        return z * tau.sqrt()


tgp.register(RationalQuadratic)  # the registration line


# ---------------------------------------------------------------------------------------------------- checks
@pytest.fixture(scope="module")
def problem():
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(3)
    times = torch.linspace(0, 6, 11, dtype=DT)
    train = tms.simulate(system, torch.rand(8, 2, generator=g, dtype=DT) * 2 - 1, times)
    samples = tms.correction_samples(train, system, derivative="oracle", noise_std=1e-3, generator=g)
    gp = tms.CorrectionGP(kernel=RationalQuadratic(alpha=1.5)).fit(samples)
    return system, times, train, samples, gp


def test_the_name_and_the_object_are_the_same_kernel():
    assert as_kernel("rq") == RationalQuadratic() and REGISTRY["rq"] is RationalQuadratic
    assert tms.CorrectionGP(kernel="rq").kernel_spec == RationalQuadratic(alpha=2.0)
    with pytest.raises(tms.InputError, match=r"expected a Kernel object or one of .*'rq'.*got 'rational'"):
        tms.CorrectionGP(kernel="rational")


def test_fit_learns_its_hyperparameters_and_matches_gpytorch(problem):
    system, times, train, samples, gp = problem
    assert gp.kernel == "rq" and gp.kernel_spec.alpha == 1.5
    assert gp.lengthscale is not None and gp.n_iterations_ > 0
    assert float(gp.covar_module.base_kernel.alpha) == pytest.approx(1.5)  # fixed, not learned
    x = samples.inputs[:7]
    ours = kernel_matrix(gp.kernel_spec, x, samples.inputs, kernel_hyperparameters(gp), gp.degree)[0]
    theirs = gp.covar_module(x, samples.inputs).to_dense()
    torch.testing.assert_close(ours, theirs.detach(), rtol=1e-8, atol=1e-15)
    # the posterior mean recovers F = 0.01 y^2 inside the data
    grid = torch.rand(50, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 1.2 - 0.6
    error = (gp.predict_mean(grid) - system.correction(grid)).abs().max()
    assert float(error) < 2e-3


def test_random_features_follow_its_spectral_density(problem):
    *_, gp = problem
    phi = feature_map(gp, num_features=40_000, generator=torch.Generator().manual_seed(1))
    x = torch.linspace(-1, 1, 9, dtype=DT).reshape(-1, 1).expand(-1, 2).contiguous()
    approx = phi(x)[0] @ phi(x)[0].T
    exact = kernel_matrix(gp.kernel_spec, x, x, kernel_hyperparameters(gp), gp.degree)[0].detach()
    # root-mean-square error of D = 20,000 pairs is 1 / sqrt(D) of the prior variance; 5 of them leaves no flake
    assert float((approx - exact).abs().max()) < 5 * float(gp.outputscale) / math.sqrt(20_000)


def test_posterior_paths_calibration_design_and_files(problem, tmp_path):
    system, times, train, samples, gp = problem
    model = tms.CorrectedODE(system, gp)
    y0 = torch.tensor([[0.2, -0.3], [-0.5, 0.4]], dtype=DT)
    post = model.posterior(y0, times, num_samples=32, generator=torch.Generator().manual_seed(0), scale=1.0)
    truth = tms.simulate(system, y0, times).states
    assert post.samples.shape == (32, 2, 11, 2) and torch.isfinite(post.samples).all()
    assert float(post.covers(truth, 0.9)[:, 1:].double().mean()) > 0.5
    cal = model.calibrate(train, samples, num_samples=32, folds=4, progress=False)
    assert cal.scale > 0 and model.calibration_ is cal
    cand = tms.design.candidates.grid(system.domain, 7)
    plan = tms.design.greedy(cand, 3, system=system, times=times, gp=gp)
    assert len(set(plan.indices.tolist())) == 3 and plan.information_gain > 0
    loaded = tms.CorrectionGP.load(gp.save(tmp_path / "rq.pt"))
    assert loaded.kernel_spec == RationalQuadratic(alpha=1.5)
    torch.testing.assert_close(loaded.predict_mean(y0), gp.predict_mean(y0))
    assert loaded.calibration_.scale == cal.scale


def test_clone_copies_the_kernel_object(problem):
    *_, gp = problem
    copy = gp.clone()
    assert copy.kernel_spec == gp.kernel_spec and not copy.is_fitted and copy.fixed == gp.fixed
    assert gp.clone(lengthscale=0.5).fixed["lengthscale"] == 0.5
    features = gp.clone(kernel="features")
    assert features.kernel == "features" and features.fixed["lengthscale"] is None
    with pytest.raises(tms.InputError, match=r"clone: expected overrides among .*got \['alpha'\]"):
        gp.clone(alpha=3.0)


def test_register_refuses_to_replace_a_package_kernel():
    class Impostor(tgp.Stationary):
        name = "rbf"

    with pytest.raises(tms.InputError, match=r"register: the name 'rbf' is the package's RBF; give Impostor a name"):
        tgp.register(Impostor)
    assert REGISTRY["rbf"] is tgp.RBF
    tgp.register(RationalQuadratic)  # registering the same class again is harmless
