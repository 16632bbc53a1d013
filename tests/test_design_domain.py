"""The domain criterion (issue 11, point 3): mean posterior variance of F over D removed by the samples."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.design.candidates import grid, uniform_box
from torchmisspec.metrics import box_grid
from torchmisspec.paper._setup import LINEAR_PRIOR, NOISE_STD

DT = torch.float64
TIMES = torch.linspace(0, 6, 11, dtype=DT)


def _prior(lengthscale=1.0):
    return tms.CorrectionGP(lengthscale=lengthscale, outputscale=1.0, noise_variance=0.3)


def _brute_force(gp, system, x, size, data_x=None, data_noise=None):
    """V by dense Gaussian conditioning of F at the quadrature nodes Q (FITC residual as independent noise)."""
    nodes, w = box_grid(system.domain, size)
    w = w / w.sum()
    noise = gp.noise_variance
    Kqq = gp.covariance(nodes)

    def fitc(points, point_noise):
        kxq = gp.covariance(points, nodes)
        proj = kxq @ torch.linalg.solve(Kqq, kxq.T)
        resid = gp.covariance(points).diagonal() - proj.diagonal()
        return kxq, proj + torch.diag(resid + point_noise)

    def posterior(points, point_noise):
        if points.shape[0] == 0:
            return Kqq
        kxq, C = fitc(points, point_noise)
        return Kqq - kxq.T @ torch.linalg.solve(C, kxq)

    if data_x is None:
        data_x, data_noise = x[:0], x.new_zeros(0)
    new_noise = torch.full((x.shape[0],), noise, dtype=DT)
    before = posterior(data_x, data_noise)
    after = posterior(torch.cat([data_x, x]), torch.cat([data_noise, new_noise]))
    return system.output_dim * float(((before - after).diagonal() * w).sum())


def test_variance_reduction_equals_dense_conditioning_at_the_nodes():
    system = tms.systems.paper_linear()
    gp = _prior()
    x = uniform_box(7, ((-1.5, 1.5), (-1.5, 1.5)), generator=torch.Generator().manual_seed(1))  # some outside D
    got = design.variance_reduction(x, gp, system=system, domain_size=3)
    assert got == pytest.approx(_brute_force(gp, system, x, 3), rel=1e-9)
    assert got > 0


def test_samples_on_the_nodes_give_the_exact_gp_variance_reduction():
    """On the nodes the residual is zero: V is then the exact GP's variance reduction there (no approximation)."""
    system = tms.systems.paper_linear()
    gp = _prior(0.7)
    nodes, w = box_grid(system.domain, 4)
    w = w / w.sum()
    x = nodes[[0, 5, 10, 10]]  # a repeated point too
    K = gp.covariance(nodes)
    C = gp.covariance(x) + gp.noise_variance * torch.eye(4, dtype=DT)
    kxq = gp.covariance(x, nodes)
    exact = 2 * float(((kxq.T @ torch.linalg.solve(C, kxq)).diagonal() * w).sum())
    assert design.variance_reduction(x, gp, system=system, domain_size=4) == pytest.approx(exact, rel=1e-8)
    assert float(K.diagonal().max()) == pytest.approx(1.0)


def test_far_samples_carry_nothing_about_the_domain():
    system = tms.systems.paper_linear()
    gp = _prior(0.5)
    far = torch.tensor([[8.0, 8.0], [9.0, -7.0]], dtype=DT)
    near = torch.tensor([[0.0, 0.0], [0.5, -0.5]], dtype=DT)
    assert design.variance_reduction(far, gp, system=system) < 1e-12
    assert design.variance_reduction(near, gp, system=system) > 0.1


@pytest.fixture(scope="module")
def fitted():
    """A GP with the paper's prior fitted on experiments from the left edge of paper 5.2's grid."""
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 7)
    left = [0, 1, 2]
    traj = tms.simulate(system, cand[left], TIMES)
    samples = tms.correction_samples(
        traj, system, derivative="oracle", noise_std=NOISE_STD, generator=torch.Generator().manual_seed(0)
    )
    return system, cand, tms.CorrectionGP(**LINEAR_PRIOR).fit(samples)


@pytest.mark.parametrize("conditioned", [False, True])
def test_greedy_gains_are_brute_force_increments(fitted, conditioned):
    system, cand, gp = fitted
    plan = design.greedy(
        cand, 4, system=system, times=TIMES, gp=gp, criterion=design.DomainCriterion(size=5), condition=conditioned
    )
    assert plan.diagnostics["criterion"] == "domain"
    assert plan.diagnostics["conditioned"] == (33 if conditioned else 0)
    pts = system.select_inputs(plan.proxies)
    data = dict(data_x=gp.train_inputs_, data_noise=torch.full((33,), gp.noise_variance, dtype=DT))
    previous = 0.0
    for j in range(4):
        x = pts[: j + 1].reshape(-1, 2)
        total = _brute_force(gp, system, x, 5, **(data if conditioned else {}))
        assert float(plan.gains[j]) == pytest.approx(total - previous, rel=1e-7, abs=1e-14)
        previous = total
        assert design.variance_reduction(x, gp, system=system, domain_size=5, condition=conditioned) == (
            pytest.approx(total, rel=1e-8)
        )


def test_conditioning_moves_the_picks_away_from_measured_states(fitted):
    system, cand, gp = fitted
    cond = design.greedy(
        cand,
        3,
        system=system,
        times=TIMES,
        gp=gp,
        criterion="domain",
        proxy=design.Proxy("known"),
    )
    prior = design.greedy(
        cand, 3, system=system, times=TIMES, gp=gp, criterion="domain", proxy=design.Proxy("known"), condition=False
    )
    # the data sit at y1 = -1; the conditioned picks lie further right on average than the prior's
    assert float(cond.points[:, 0].mean()) > float(prior.points[:, 0].mean())
    assert cond.gains.sum() < prior.gains.sum()


@pytest.mark.parametrize("conditioned", [False, True])
@pytest.mark.parametrize("proxy", ["known", "corrected"])
def test_lazy_plain_naive_agree(fitted, conditioned, proxy):
    system, cand, gp = fitted
    part = (torch.arange(cand.shape[0]) % 3).tolist()
    kw = dict(system=system, times=TIMES, gp=gp, criterion="domain", condition=conditioned, proxy=design.Proxy(proxy))
    for extra in ({}, dict(partition=design.Partition(part, [1, 2, 3]))):
        plans = [design.greedy(cand, 6, method=m, **kw, **extra) for m in ("lazy", "plain", "naive")]
        assert plans[0].indices.tolist() == plans[1].indices.tolist() == plans[2].indices.tolist()
        torch.testing.assert_close(plans[0].gains, plans[2].gains, rtol=1e-8, atol=1e-15)
        if extra:
            counts = torch.bincount(torch.tensor(part)[plans[0].indices], minlength=3)
            assert (counts <= torch.tensor([1, 2, 3])).all()


def test_unfitted_prior_design_stays_in_the_domain():
    """From the paper's prior: the domain criterion's first picks are inside D, not the grid's corners."""
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 13)
    prior = tms.CorrectionGP(**LINEAR_PRIOR)
    dom = design.greedy(cand, 4, system=system, times=TIMES, gp=prior, criterion="domain")
    info = design.greedy(cand, 4, system=system, times=TIMES, gp=prior)
    corners = {0, 12, 156, 168}
    assert set(info.indices.tolist()) == corners
    assert not corners & set(dom.indices.tolist())


def test_bad_input(fitted):
    system, cand, gp = fitted
    kw = dict(system=system, times=TIMES, gp=gp)
    with pytest.raises(tms.InputError, match="criterion: expected one of"):
        design.greedy(cand, 2, criterion="variance", **kw)
    with pytest.raises(tms.InputError, match="domain.*expected"):
        design.greedy(cand, 2, criterion=design.DomainCriterion(domain=((-1, 1),)), **kw)
    with pytest.raises(tms.InputError, match="domain_size"):
        design.greedy(cand, 2, criterion=design.DomainCriterion(size=1), **kw)
    bare = tms.MisspecifiedSystem(known=system.known, state_dim=2, name="no-domain")
    with pytest.raises(tms.InputError, match="has none"):
        design.greedy(
            cand,
            2,
            system=bare,
            times=TIMES,
            gp=gp,
            criterion="domain",
            proxy=design.Proxy("known"),
        )
    with pytest.raises(tms.ShapeError, match="columns"):
        design.variance_reduction(torch.zeros(3, 3, dtype=DT), gp, system=system)
