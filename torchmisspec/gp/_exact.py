"""The GPyTorch view of a model (independent outputs sharing a kernel), the modules it is built from, and the data's
length scale."""

from __future__ import annotations

import gpytorch
import torch


def log_positive() -> gpytorch.constraints.Interval:
    """A positive constraint whose raw value is the log of the hyperparameter.

    No absolute floor: an absolute floor (GPyTorch's default 1e-4 on the noise, or any fixed number) breaks the
    scale-equivariance of the fit (targets of size 1e-6 would be fitted differently from the same targets in other
    units). Optimising in log space keeps every value positive.
    """
    return gpytorch.constraints.GreaterThan(0.0, transform=torch.exp, inv_transform=torch.log)


class IndependentOutputsGP(gpytorch.models.ExactGP):
    """GPyTorch ExactGP: d_out independent outputs (a batch) sharing one kernel (or one kernel per output)."""

    def __init__(self, train_x, train_y, likelihood, covar_module, num_outputs: int) -> None:
        super().__init__(train_x, train_y, likelihood)  # train_y: (d_out, N)
        self.num_outputs = num_outputs
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=torch.Size([num_outputs]))
        self.covar_module = covar_module

    def forward(self, x):
        mean = self.mean_module(x)
        covar = self.covar_module(x)
        if covar.dim() == 2:  # shared kernel: the same covariance for every output
            covar = covar.expand(self.num_outputs, *covar.shape)
        return gpytorch.distributions.MultivariateNormal(mean, covar)


def median_distance(X: torch.Tensor) -> float:
    """The median distance between distinct inputs of an evenly spaced subsample of at most 500 (1.0 when all the
    inputs coincide): the length scale of the data, for starting values, bounds and candidate grids.

    Each pair once, from the differences of its inputs (``torch.pdist``): ``torch.cdist``'s matrix-product form
    gives some inputs a distance of ~1e-8 to themselves, how many depending on rounding, so that the same inputs in
    other units (divided by a power of ten and back) moved the median by 1e-3 relative."""
    sub = X[torch.linspace(0, X.shape[0] - 1, min(X.shape[0], 500), device=X.device).long()]
    dist = torch.pdist(sub.reshape(sub.shape[0], -1))
    positive = dist[dist > 0]
    return float(positive.median()) if positive.numel() else 1.0


def build_modules(gp, batch: int, noise: torch.Tensor | None = None):
    """A fresh kernel and likelihood holding the fixed values (batch of ``batch`` when ``per_output``).

    ``noise``: known per-sample noise ``(d_out, N)`` (model dtype and device), or ``None``. With it the likelihood
    is a ``FixedNoiseGaussianLikelihood`` whose learned additional noise is the floor ``noise_variance``.
    """
    shape = torch.Size([batch]) if gp.per_output else torch.Size([])
    base = gp.kernel_spec.module(gp, shape)
    covar = gpytorch.kernels.ScaleKernel(base, batch_shape=shape, outputscale_constraint=log_positive())
    if noise is None:
        lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=shape, noise_constraint=log_positive())
    else:
        # min_fixed_noise 0: GPyTorch would otherwise round known variances below 1e-6 up (and warn), and the
        # ExactGP view would no longer be the model that is fitted
        with gpytorch.settings.min_fixed_noise(float_value=0.0, double_value=0.0, half_value=0.0):
            lik = gpytorch.likelihoods.FixedNoiseGaussianLikelihood(
                noise=noise, learn_additional_noise=True, batch_shape=shape, noise_constraint=log_positive()
            )
    covar, lik = covar.to(gp.device, gp.dtype), lik.to(gp.device, gp.dtype)

    # GPyTorch's setters would round a Python float through float32: pass tensors of the model's dtype
    def value(name):
        return torch.tensor(gp.fixed[name], dtype=gp.dtype, device=gp.device)

    if gp.fixed["lengthscale"] is not None:
        base.lengthscale = value("lengthscale")
    if gp.fixed["outputscale"] is not None:
        covar.outputscale = value("outputscale")
    if gp.fixed["noise_variance"] is not None:
        noise_module(lik).noise = value("noise_variance")
    return covar, lik


def noise_module(lik) -> gpytorch.likelihoods.noise_models.HomoskedasticNoise:
    """The module of the learned (or fixed) noise variance: the whole noise, or the floor over known noise."""
    if isinstance(lik, gpytorch.likelihoods.FixedNoiseGaussianLikelihood):
        return lik.second_noise_covar
    return lik.noise_covar
