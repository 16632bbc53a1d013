"""Posterior.means_of: every parameter's absorbed term from one kernel block, equal to the means one by one (to the
rounding of the sums: large representer weights cancel)."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp import _posterior

DT = torch.float64


@pytest.mark.parametrize("kernel", ["rbf", "features"])
@pytest.mark.parametrize("per_output", [False, True])
def test_means_of_equals_each_mean(kernel, per_output, monkeypatch):
    g = torch.Generator().manual_seed(0)
    X = torch.rand(60, 2, dtype=DT, generator=g)
    Y = torch.stack([torch.sin(3 * X[:, 0]), X[:, 1] ** 2], -1) + 0.01 * torch.randn(60, 2, dtype=DT, generator=g)
    gp = tms.CorrectionGP(kernel=kernel, per_output=per_output).fit(X, Y, progress=False)
    post = gp.posterior()
    parts = [post.with_targets(torch.randn(60, 2, dtype=DT, generator=g)) for _ in range(5)]
    x = torch.rand(300, 2, dtype=DT, generator=g)
    one_by_one = torch.stack([p.mean(x, check=False) for p in parts], -1)
    assert one_by_one.shape == (300, 2, 5)
    together = post.means_of(parts, x)  # one product for all: equal up to the order of the sums
    assert (together - one_by_one).abs().max() <= 1e-9 * one_by_one.abs().max(), (together - one_by_one).abs().max()
    monkeypatch.setattr(_posterior, "MEAN_BLOCK", 64 * 60)  # row blocks of 64: the blocks are put back in order
    blocked = post.means_of(parts, x)
    assert (blocked - one_by_one).abs().max() <= 1e-9 * one_by_one.abs().max(), (blocked - one_by_one).abs().max()


def test_the_mean_keeps_its_gradient_to_the_targets_after_a_first_call_without_grad():
    """The trajectory fit differentiates F's mean through pseudo-targets, and a solver first checks the field under
    no_grad: the weights stacked at that first call must still carry the graph (it did not, and the fit stood still)."""
    g = torch.Generator().manual_seed(1)
    X = torch.rand(40, 1, dtype=DT, generator=g)
    gp = tms.CorrectionGP().fit(X, torch.sin(4 * X), progress=False)
    x = torch.rand(30, 1, dtype=DT, generator=g)
    first, fresh = (torch.sin(4 * X).clone().requires_grad_(True) for _ in range(2))
    pseudo = gp.posterior().with_targets(first)
    with torch.no_grad():
        pseudo.mean(x, check=False)
    pseudo.mean(x, check=False).sum().backward()
    gp.posterior().with_targets(fresh).mean(x, check=False).sum().backward()
    assert float(fresh.grad.abs().max()) > 0
    torch.testing.assert_close(first.grad, fresh.grad)
