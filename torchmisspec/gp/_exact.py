"""The GPyTorch view of a fitted model (independent outputs sharing a kernel) and the data's length scale."""

from __future__ import annotations

import gpytorch
import torch


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
    inputs coincide): the length scale of the data, for starting values, bounds and candidate grids."""
    sub = X[torch.linspace(0, X.shape[0] - 1, min(X.shape[0], 500), device=X.device).long()]
    dist = torch.cdist(sub, sub)
    positive = dist[dist > 0]
    return float(positive.median()) if positive.numel() else 1.0
