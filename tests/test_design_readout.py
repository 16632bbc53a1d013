"""Tests of the readings' design criterion (torchmisspec.design.ReadoutCriterion, design/_readings.py)."""

from __future__ import annotations

import itertools
import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec._errors import InputError, ShapeError
from torchmisspec.data import Readout
from torchmisspec.design._readings import _ReadoutProblem
from torchmisspec.gp import CorrectionGP

DT = torch.float64
NAMES = ["x", "p"]
TIMES = torch.linspace(0, 3, 7, dtype=DT)
PRIOR = {"lengthscale": 1.0, "outputscale": 0.5, "noise_variance": 1e-3}


def _lv(y):
    x, p = y[..., 0], y[..., 1]
    return torch.stack([x - 0.6 * x * p, -0.8 * p + 0.5 * x * p], dim=-1)


def lv(correction=None, outputs=(0,), inputs=(0,)) -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        _lv, 2, correction=correction, correction_inputs=list(inputs), correction_outputs=list(outputs),
        state_names=NAMES, name="lv",
    )  # fmt: skip


def total() -> Readout:
    return Readout.parse(["total = x + p"], NAMES)


def candidates(n: int = 6, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.4 + 2.0 * torch.rand(n, 2, generator=g, dtype=DT)


def rbf(x: torch.Tensor, y: torch.Tensor, outputscale: float, lengthscale: float) -> torch.Tensor:
    """Independent RBF formula (not the package's kernel)."""
    d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    return outputscale * torch.exp(-0.5 * d2 / lengthscale**2)


# ------------------------------------------------------------------------------------------------ sensitivity
@pytest.mark.parametrize("outputs,inputs", [((0,), (0,)), ((0, 1), (0, 1))])
def test_sensitivity_matches_finite_differences_of_the_solve(outputs, inputs):
    """delta z predicted by A for F = eps phi matches (z(eps) - z(-eps)) / (2 eps) of the batched solve."""
    y0 = candidates(3)
    phi = lambda x: torch.sin(x.sum(-1, keepdim=True) + torch.arange(len(outputs), dtype=DT))  # noqa: E731
    sens = design.readout_sensitivity(lv(outputs=outputs, inputs=inputs), y0, TIMES, total(), substeps=32)
    predicted = torch.einsum("nroi,nio->nr", sens.A, phi(sens.nodes))  # (N, m (T - 1))
    eps = 1e-5
    z = []
    for e in (eps, -eps):
        sys_e = lv(correction=lambda x, e=e: e * phi(x), outputs=outputs, inputs=inputs)
        z.append(total()(tms.simulate(sys_e, y0, TIMES).states)[:, 1:].reshape(3, -1))
    fd = (z[0] - z[1]) / (2 * eps)
    assert sens.A.shape == (3, len(TIMES) - 1, len(outputs), 32 * (len(TIMES) - 1) + 1)
    assert torch.allclose(predicted, fd, rtol=2e-3, atol=2e-5 * float(fd.abs().max()))


def test_sensitivity_is_exact_for_a_linear_known_model_with_constant_perturbation():
    """G(y) = M y and constant f: delta y(t) = int_0^t expm(M (t - s)) ds E f, here in closed form."""
    M = torch.tensor([[-1.0, 0.5], [0.0, -0.3]], dtype=DT)
    system = tms.MisspecifiedSystem(lambda y: y @ M.T, 2, correction_outputs=[1], state_names=NAMES, name="lin")
    sens = design.readout_sensitivity(system, candidates(2), TIMES, Readout([[1.0, 0.0]], ["x_read"]), substeps=64)
    predicted = sens.A.sum(dim=(2, 3))  # f = 1 everywhere
    exact = []
    for t in TIMES[1:]:
        # int_0^t expm(M u) du e_1 via the augmented matrix exponential
        aug = torch.zeros(4, 4, dtype=DT)
        aug[:2, :2], aug[:2, 2:] = M * t, torch.eye(2, dtype=DT) * t
        exact.append(torch.linalg.matrix_exp(aug)[:2, 2:][0, 1])
    assert torch.allclose(predicted, torch.stack(exact).expand(2, -1), rtol=1e-4)


# ------------------------------------------------------------------------------------------------------ gains
def test_gain_matches_a_brute_force_gaussian_logdet():
    cands = candidates(5)
    crit = design.ReadoutCriterion(total(), noise_std=0.05)
    gp = CorrectionGP(**PRIOR)
    sens = design.readout_sensitivity(lv(), cands, TIMES, total(), substeps=crit.substeps)
    chosen = [1, 3, 4]
    A = torch.cat([sens.A[c, :, 0, :] for c in chosen], dim=0)  # rows of every reading, one column block per c
    blocks = [sens.A[c, :, 0, :] for c in chosen]
    nodes = torch.cat([sens.nodes[c] for c in chosen])
    A = torch.block_diag(*blocks)
    K = rbf(nodes, nodes, PRIOR["outputscale"], PRIOR["lengthscale"])
    Sigma = A @ K @ A.T / 0.05**2
    brute = 0.5 * float(torch.logdet(torch.eye(Sigma.shape[0], dtype=DT) + Sigma))
    got = design.readout_information_gain(chosen, cands, system=lv(), times=TIMES, gp=gp, criterion=crit)
    assert got == pytest.approx(brute, rel=1e-8)
    assert design.readout_information_gain([], cands, system=lv(), times=TIMES, gp=gp, criterion=crit) == 0.0


def test_greedy_engines_agree_and_gains_sum_to_the_joint_information():
    cands = candidates(12, seed=3)
    crit = design.ReadoutCriterion(total(), noise_std=0.05)
    kw = dict(system=lv(), times=TIMES, gp=CorrectionGP(**PRIOR), criterion=crit)
    plain = design.greedy(cands, 4, method="plain", **kw)
    lazy = design.greedy(cands, 4, **kw)
    naive = design.greedy(cands, 4, method="naive", **kw)
    assert plain.indices.tolist() == lazy.indices.tolist() == naive.indices.tolist()
    assert torch.allclose(plain.gains, naive.gains, rtol=1e-8)
    joint = design.readout_information_gain(plain, cands, **kw)
    assert plain.information_gain == pytest.approx(joint, rel=1e-8)
    assert plain.diagnostics["criterion"] == "readout" and plain.diagnostics["noise_source"] == "given"
    assert plain.proxies.shape == (4, len(TIMES), 2)
    assert bool((plain.gains[1:] <= plain.gains[:-1] + 1e-9).all())  # diminishing returns along the greedy path


def test_monotone_and_submodular_on_a_small_set():
    cands = candidates(5, seed=7)
    crit = design.ReadoutCriterion(total(), noise_std=0.1)
    prob = _ReadoutProblem(crit, cands, 1, lv(), TIMES, CorrectionGP(**PRIOR), None, None, None, None, 0.0)

    def f(S) -> float:
        if not S:
            return 0.0
        return 0.5 * float(torch.logdet(torch.eye(len(S) * prob.R, dtype=DT) + prob.cov.joint(sorted(S))))

    everything = range(5)
    for r in range(5):
        for S in itertools.combinations(everything, r):
            for c in set(everything) - set(S):
                gain_S = f(set(S) | {c}) - f(set(S))
                assert gain_S >= -1e-9  # monotone
                for extra in set(everything) - set(S) - {c}:
                    T = set(S) | {extra}
                    assert gain_S >= f(T | {c}) - f(T) - 1e-9  # submodular


def test_a_path_that_moves_only_an_unread_state_is_worth_nothing_when_it_is_not_read():
    """F acts on y2; y2 reaches y1 only through y1 y2: from y1 = 0 the readings of y1 see nothing of F, while the
    derivative criterion and the readout of every state value that path (it explores F over a wide range)."""
    system = tms.MisspecifiedSystem(
        lambda y: torch.stack([-y[..., 0] + y[..., 0] * y[..., 1], -0.5 * y[..., 1]], -1), 2,
        correction_inputs=[1], correction_outputs=[1], state_names=NAMES, name="coupled",
    )  # fmt: skip
    cands = torch.tensor([[0.5, 0.5], [0.0, 3.0]], dtype=DT)  # the second moves only y2
    gp = CorrectionGP(**PRIOR)
    both = Readout(torch.eye(2, dtype=DT), ["x_read", "p_read"])
    first = Readout([[1.0, 0.0]], ["x_read"])
    kw = dict(system=system, times=TIMES, gp=gp)
    pick = {
        name: int(design.greedy(cands, 1, criterion=design.ReadoutCriterion(H, noise_std=0.05), **kw).indices[0])
        for name, H in (("both", both), ("first", first))
    }
    assert pick == {"both": 1, "first": 0}
    assert int(design.greedy(cands, 1, **kw).indices[0]) == 1  # the paper's criterion: as if every state were read
    crit = design.ReadoutCriterion(first, noise_std=0.05)
    assert design.readout_information_gain([1], cands, criterion=crit, **kw) == pytest.approx(0.0, abs=1e-10)


def test_noise_default_and_from_a_fit_record():
    cands = candidates(4)
    gp = CorrectionGP(**PRIOR)
    r = design.greedy(cands, 2, system=lv(), times=TIMES, gp=gp, criterion=design.ReadoutCriterion(total()))
    assert r.diagnostics["noise_source"] == "default"
    paths = design.proxy_trajectories(lv(), cands, torch.linspace(0, 3, 25, dtype=DT))
    rms = float(total()(paths).pow(2).mean().sqrt())
    assert r.diagnostics["noise_std"][0] == pytest.approx(0.01 * rms, rel=1e-3)
    # a smaller noise makes every reading more informative
    precise = design.greedy(
        cands, 2, system=lv(), times=TIMES, gp=gp, criterion=design.ReadoutCriterion(total(), noise_std=1e-3)
    )
    assert precise.information_gain > r.information_gain


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_readouts_and_options_are_refused_clearly():
    cands = candidates(4)
    kw = dict(system=lv(), times=TIMES, gp=CorrectionGP(**PRIOR))
    with pytest.raises(InputError, match="expected a torchmisspec.Readout"):
        design.ReadoutCriterion([[1.0, 1.0]])
    with pytest.raises(ShapeError, match="expected weights over the 2 states"):
        design.greedy(cands, 2, criterion=design.ReadoutCriterion(Readout([[1.0, 1.0, 1.0]], ["z"])), **kw)
    with pytest.raises(InputError, match="expected weights over the states"):
        other = Readout.parse(["z = a + b"], ["a", "b"])
        design.greedy(cands, 2, criterion=design.ReadoutCriterion(other), **kw)
    with pytest.raises(InputError, match="noise_std: expected a positive"):
        design.ReadoutCriterion(total(), noise_std=[0.1, 0.2])
    with pytest.raises(InputError, match="noise_std: expected a positive"):
        design.ReadoutCriterion(total(), noise_std=0.0)
    with pytest.raises(InputError, match="substeps"):
        design.ReadoutCriterion(total(), substeps=0)
    crit = design.ReadoutCriterion(total(), noise_std=0.1)
    with pytest.raises(InputError, match="at least two observation times"):
        design.greedy(cands, 2, system=lv(), times=TIMES[:1], gp=CorrectionGP(**PRIOR), criterion=crit)
    with pytest.raises(InputError, match="expected none of \\['proxies'\\]"):
        design.greedy(cands, 2, criterion=crit, proxy=design.Proxy(paths=torch.zeros(4, len(TIMES), 2, dtype=DT)), **kw)
    with pytest.raises(InputError, match="method='stochastic'"):
        design.greedy(cands, 2, criterion=crit, method="stochastic", **kw)
    with pytest.raises(InputError, match="criterion: expected one of"):
        design.greedy(cands, 2, criterion="readout", **kw)


def test_no_readout_keeps_the_paper_criterion():
    """Without a ReadoutCriterion the design is the derivative-sample one, untouched."""
    cands = candidates(10)
    kw = dict(system=lv(), times=TIMES, gp=CorrectionGP(**PRIOR))
    r = design.greedy(cands, 3, **kw)
    assert r.diagnostics["criterion"] == "information"
    brute = design.information_gain(
        lv().select_inputs(design.proxy_trajectories(lv(), cands[r.indices], TIMES)).reshape(-1, 1), kw["gp"], d_out=1
    )
    assert r.information_gain == pytest.approx(brute, rel=1e-8)


# ------------------------------------------------------------------------------------ with data: a campaign
def _readout_data(y0: torch.Tensor, seed: int = 0) -> tms.Trajectories:
    truth = lv(correction=lambda x: -0.4 * x**2 / (1 + x))
    times = torch.linspace(0, 6, 13, dtype=DT)
    clean = tms.simulate(truth, y0, times).states
    g = torch.Generator().manual_seed(seed)
    z = total()(clean) + 0.02 * torch.randn(clean.shape[0], clean.shape[1], 1, generator=g, dtype=DT)
    states = torch.full_like(clean, math.nan)
    states[:, 0] = y0
    return tms.Trajectories(times, states, state_names=NAMES, readout=total(), readings=z)


@pytest.fixture(scope="module")
def fitted():
    y0 = torch.tensor([[0.5, 0.5], [2.0, 1.0], [1.0, 2.5], [2.5, 2.0]], dtype=DT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        return tms.fit_correction(_readout_data(y0), lv(), progress=False)


@pytest.mark.slow
def test_conditioned_design_on_a_fit_through_the_ode(fitted):
    cands = candidates(15, seed=2)
    crit = design.ReadoutCriterion(total())
    kw = dict(system=lv(), times=torch.linspace(0, 6, 13, dtype=DT), gp=fitted, criterion=crit)
    cond = design.greedy(cands, 3, **kw)
    prior = design.greedy(cands, 3, condition=False, proxy=design.Proxy("known"), **kw)
    assert cond.diagnostics["noise_source"] == "fitted" and cond.diagnostics["proxy"] == "corrected"
    assert cond.diagnostics["conditioned"] > 0
    assert cond.information_gain < prior.information_gain  # what the data told already is not counted again


@pytest.mark.slow
def test_a_campaign_whose_data_carry_a_readout_designs_through_it(fitted):
    campaign = design.Campaign(lv(), candidates(15, seed=5), torch.linspace(0, 6, 13, dtype=DT), fitted)
    assert campaign.data is not None and campaign.data.readout is not None
    picks = campaign.ask(2)
    assert picks.shape == (2, 2)
    info = campaign.history[-1]["design"]
    assert info["criterion"] == "readout" and info["readout"] == "total = x + p"
    assert info["noise_source"] == "fitted"


# ------------------------------------------------------------------------------------------- over the domain
def _brute_domain_reduction(sens, chosen, box, size, noise):
    """The mean over D of var(F) removed by the readings of ``chosen``: the exact Gaussian posterior of F at the
    quadrature nodes (no features), trapezoid weights normalised to one."""
    from torchmisspec.metrics import box_grid

    A = torch.block_diag(*[sens.A[c, :, 0, :] / noise for c in chosen])
    X = torch.cat([sens.nodes[c] for c in chosen])
    Q, w = box_grid(box, size, dtype=DT)
    w = w / w.sum()
    S = torch.eye(A.shape[0], dtype=DT) + A @ rbf(X, X, 0.5, 1.0) @ A.T
    M = rbf(Q, X, 0.5, 1.0) @ A.T
    return float((w * (M @ torch.linalg.solve(S, M.T)).diagonal()).sum())


@pytest.mark.parametrize("method", ["plain", "naive"])
def test_the_readings_variance_over_the_domain_matches_the_exact_gaussian_posterior(method):
    """Inside a box that holds every path, the pivot features are exact to 1e-8 of the prior variance: the gains of
    ``ReadoutCriterion(domain=...)`` sum to the exact reduction of F's mean variance over D, and each gain is the
    increment of that reduction along the picks."""
    cands = candidates(10, seed=5)
    box, size = [(-3.0, 8.0)], 200
    crit = design.ReadoutCriterion(total(), noise_std=0.05, domain=design.DomainCriterion(domain=box, size=size))
    plan = design.greedy(cands, 3, method=method, system=lv(), times=TIMES, gp=CorrectionGP(**PRIOR), criterion=crit)
    sens = design.readout_sensitivity(lv(), cands, TIMES, total(), substeps=crit.substeps)
    picks = plan.indices.tolist()
    along = [_brute_domain_reduction(sens, picks[: k + 1], box, size, 0.05) for k in range(3)]
    assert plan.gains.tolist() == pytest.approx([along[0], along[1] - along[0], along[2] - along[1]], rel=1e-6)
    assert plan.diagnostics["criterion"] == "readout over the domain"
    # the first pick is the candidate whose readings alone remove the most
    alone = [_brute_domain_reduction(sens, [c], box, size, 0.05) for c in range(10)]
    assert picks[0] == max(range(10), key=alone.__getitem__)


def test_readings_of_a_path_outside_the_domain_are_worth_less_there():
    """The domain aims the readings: with D = the low prey values a path stays in, a candidate whose prey stays there
    gains more than over D = the high values it never reaches."""
    cands = candidates(8, seed=2)
    kw = dict(system=lv(), times=TIMES, gp=CorrectionGP(**PRIOR))
    sens = design.readout_sensitivity(lv(), cands, TIMES, total())
    low = int(sens.nodes[..., 0].max(dim=1).values.argmin())
    top = float(sens.nodes[low, :, 0].max())
    gains = {}
    for name, box in (("near", [(0.0, top)]), ("far", [(top + 3.0, top + 6.0)])):
        crit = design.ReadoutCriterion(total(), noise_std=0.05, domain=design.DomainCriterion(domain=box))
        plan = design.greedy(cands[low : low + 1], 1, criterion=crit, **kw)
        gains[name] = float(plan.gains[0])
    assert gains["near"] > 100 * gains["far"] > 0


def test_a_readout_criterions_domain_must_be_a_domain_criterion():
    with pytest.raises(InputError, match="domain: expected None .* or a design.DomainCriterion"):
        design.ReadoutCriterion(total(), domain=[(0.0, 1.0)])


# ------------------------------------------------------------------------------ with G's uncertain parameters
def _lv_theta(y, a):
    x, p = y[..., 0], y[..., 1]
    return torch.stack([x - a * x * p, -0.8 * p + 0.5 * x * p], dim=-1)


def lv_theta(scale: float = 0.1) -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        _lv_theta, 2, correction_inputs=[0], correction_outputs=[0], state_names=NAMES, name="lv-theta",
        parameters={"a": (0.6, scale)},
    )  # fmt: skip


def _theta_sensitivity(system, cands, h=1e-5):
    """The readings' derivative in theta by central differences of two solves (readings after t_0): ``(N, R)``."""
    theta = system.theta.clone()
    z = []
    for step in (h, -h):
        paths = tms.simulate(system.at(theta + step), cands, TIMES).states  # (N, T, d)
        z.append(paths[:, 1:] @ total().matrix.T.to(paths))
    return ((z[0] - z[1]) / (2 * h)).reshape(cands.shape[0], -1)


def _brute_with_theta(system, cands, chosen, noise, scale, substeps):
    sens = design.readout_sensitivity(system.at(system.theta), cands, TIMES, total(), substeps=substeps)
    A = torch.block_diag(*[sens.A[c, :, 0, :] for c in chosen]) / noise
    X = torch.cat([sens.nodes[c] for c in chosen])
    B = _theta_sensitivity(system, cands)[chosen].reshape(-1, 1) / noise
    eye = torch.eye(A.shape[0], dtype=DT)
    both = eye + A @ rbf(X, X, 0.5, 1.0) @ A.T + scale**2 * B @ B.T
    return 0.5 * float(torch.logdet(both) - torch.logdet(eye + scale**2 * B @ B.T)), A, X, B


def test_the_information_with_theta_integrated_out_matches_a_brute_force_from_perturbed_solves():
    """Readings of a system with an uncertain parameter: (1/2) logdet(I + A K A^T + B S B^T) - (1/2) logdet(I + B S
    B^T) with B the readings' derivative in theta from two perturbed solves (not the package's variational
    equation), S the prior's variance; and the plug-in information (theta fixed) is larger."""
    cands, chosen, noise = candidates(5, seed=7), [0, 2, 3], 0.05
    crit = design.ReadoutCriterion(total(), noise_std=noise, substeps=16)  # the trapezoid rule's error: 1e-5
    kw = dict(times=TIMES, gp=CorrectionGP(**PRIOR), criterion=crit)
    brute, *_ = _brute_with_theta(lv_theta(), cands, chosen, noise, 0.1, 16)
    got = design.readout_information_gain(chosen, cands, system=lv_theta(), **kw)
    assert got == pytest.approx(brute, rel=1e-4)
    plug_in = design.readout_information_gain(chosen, cands, system=lv_theta().at(torch.tensor([0.6])), **kw)
    assert plug_in > got
    # as theta's spread vanishes, the criterion becomes the plug-in one
    tiny = design.readout_information_gain(chosen, cands, system=lv_theta(scale=1e-6), **kw)
    assert tiny == pytest.approx(plug_in, rel=1e-6)


def _engines_agree_with_theta_integrated_out(cands, kw) -> None:
    """The plain and naive engines pick alike, their gains agree and sum to the picks' joint information."""
    plain = design.greedy(cands, 3, method="plain", **kw)
    naive = design.greedy(cands, 3, method="naive", **kw)
    assert plain.indices.tolist() == naive.indices.tolist()
    assert torch.allclose(plain.gains, naive.gains, rtol=1e-8)
    assert plain.information_gain == pytest.approx(design.readout_information_gain(plain, cands, **kw), rel=1e-8)
    assert plain.diagnostics["parameters"] == "integrated out (prior)"


def test_greedy_engines_agree_with_theta_integrated_out():
    cands = candidates(10, seed=4)
    crit = design.ReadoutCriterion(total(), noise_std=0.05)
    kw = dict(system=lv_theta(0.2), times=TIMES, gp=CorrectionGP(**PRIOR), criterion=crit)
    _engines_agree_with_theta_integrated_out(cands, kw)


def test_the_variance_over_the_domain_with_theta_integrated_out_matches_the_exact_posterior():
    """F's mean variance over D removed by the readings when theta is unknown: the exact Gaussian posterior of F at
    the quadrature nodes given readings z = A f + B eta + noise, eta ~ N(0, S), B from perturbed solves."""
    from torchmisspec.metrics import box_grid

    cands, noise, scale = candidates(6, seed=9), 0.05, 0.2
    box, size = [(-3.0, 8.0)], 200
    over = design.DomainCriterion(domain=box, size=size)
    crit = design.ReadoutCriterion(total(), noise_std=noise, substeps=16, domain=over)
    plan = design.greedy(cands, 2, system=lv_theta(scale), times=TIMES, gp=CorrectionGP(**PRIOR), criterion=crit)
    _, A, X, B = _brute_with_theta(lv_theta(scale), cands, plan.indices.tolist(), noise, scale, 16)
    Q, w = box_grid(box, size, dtype=DT)
    S = torch.eye(A.shape[0], dtype=DT) + A @ rbf(X, X, 0.5, 1.0) @ A.T + scale**2 * B @ B.T
    M = rbf(Q, X, 0.5, 1.0) @ A.T
    brute = float((w / w.sum() * (M @ torch.linalg.solve(S, M.T)).diagonal()).sum())
    assert float(plan.gains.sum()) == pytest.approx(brute, rel=1e-4)


@pytest.mark.slow
def test_a_campaign_on_readings_with_an_uncertain_parameter_integrates_it_out():
    """A campaign whose data read the total and whose G has an uncertain parameter designs through the readings
    with theta integrated out about the fit's posterior (issue 42: Campaign with readouts and parameters)."""
    y0 = torch.tensor([[0.5, 0.5], [2.0, 1.0], [1.0, 2.5], [2.5, 2.0]], dtype=DT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(_readout_data(y0), lv_theta(), progress=False)
    assert gp.parameters_ is not None
    campaign = design.Campaign(lv_theta(), candidates(12, seed=5), torch.linspace(0, 6, 13, dtype=DT), gp)
    assert campaign.ask(2).shape == (2, 2)
    info = campaign.history[-1]["design"]
    assert info["criterion"] == "readout" and info["parameters"] == "integrated out (fitted)"


# ------------------------------------------------------------------------------------------- with inputs u(t)
def _lv_fed(t, y, u, *theta):
    x, p = y[..., 0], y[..., 1]
    a = theta[0][0] if theta else 0.6
    return torch.stack([x - a * x * p + u[..., 0], -0.8 * p + 0.5 * x * p], dim=-1)


def lv_fed(correction=None, parameters=None) -> tms.MisspecifiedSystem:
    """Prey fed at a rate u(t) the lab sets: F(x) missing from the prey's equation."""
    return tms.MisspecifiedSystem(
        _lv_fed, 2, correction=correction, correction_inputs=[0], correction_outputs=[0], state_names=NAMES,
        num_controls=1, control_names=["feed"], parameters=parameters, name="lv-fed",
    )  # fmt: skip


def feeds(n: int, seed: int = 0):
    from torchmisspec.signals import Controls

    g = torch.Generator().manual_seed(seed)
    return Controls(torch.tensor([0.0, 1.0, 2.0], dtype=DT), 0.5 * torch.rand(n, 3, 1, generator=g, dtype=DT))


def test_the_readings_sensitivity_with_inputs_matches_perturbed_solves():
    """With piecewise-constant feeds, a constant perturbation eps of F moves the readings by eps times the sum of
    the sensitivity over the nodes (to first order): checked against two solves of the system with F = +-eps."""
    cands, controls, eps = candidates(4, seed=1), feeds(4), 1e-4
    crit = design.ReadoutCriterion(total(), noise_std=1.0, substeps=16)
    prob = _ReadoutProblem(crit, cands, 1, lv_fed(), TIMES, CorrectionGP(**PRIOR), "known", None, None, None, 0.0,
                           controls=controls)  # fmt: skip
    moved = [
        total()(tms.simulate(lv_fed(lambda x, s=s: s * eps + 0 * x), cands, TIMES, controls=controls).states)[:, 1:]
        for s in (1.0, -1.0)
    ]
    finite = ((moved[0] - moved[1]) / (2 * eps)).reshape(4, -1)
    linear = prob.cov.A[:, :, 0, :].sum(-1)
    torch.testing.assert_close(linear, finite, rtol=2e-3, atol=1e-5)


def test_a_design_with_inputs_and_an_uncertain_parameter_through_readings():
    """Greedy over candidates that differ in their feed, theta integrated out: the engines agree, and the gains sum
    to the joint information of the picks."""
    cands, controls = candidates(8, seed=3), feeds(8, seed=2)
    system = lv_fed(parameters={"a": (0.6, 0.1)})
    kw = dict(system=system, times=TIMES, gp=CorrectionGP(**PRIOR), controls=controls,
              criterion=design.ReadoutCriterion(total(), noise_std=0.05))  # fmt: skip
    _engines_agree_with_theta_integrated_out(cands, kw)


@pytest.mark.slow
def test_a_campaign_with_inputs_readings_and_an_uncertain_parameter():
    """Issue 42: Campaign with inputs, readouts and parameters. Fitted from readings of the total with the feeds
    known, it asks for experiments (initial state and feed) designed through the readings, theta integrated out."""
    truth = lv_fed(correction=lambda x: -0.4 * x**2 / (1 + x))
    y0, controls = candidates(4, seed=11), feeds(4, seed=12)
    times = torch.linspace(0, 6, 13, dtype=DT)
    clean = tms.simulate(truth, y0, times, controls=controls).states
    g = torch.Generator().manual_seed(0)
    z = total()(clean) + 0.02 * torch.randn(clean.shape[0], clean.shape[1], 1, generator=g, dtype=DT)
    states = torch.full_like(clean, math.nan)
    states[:, 0] = y0
    data = tms.Trajectories(times, states, state_names=NAMES, readout=total(), readings=z, controls=controls)
    system = lv_fed(parameters={"a": (0.6, 0.1)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, system, progress=False)
    campaign = design.Campaign(system, candidates(10, seed=13), times, gp, controls=feeds(10, seed=14))
    states, profiles = campaign.ask(2)
    assert states.shape == (2, 2) and profiles.num_experiments == 2
    info = campaign.history[-1]["design"]
    assert info["criterion"] == "readout" and info["parameters"] == "integrated out (fitted)"


@pytest.mark.slow
def test_a_campaign_on_readings_aimed_at_a_domain_says_what_is_not_built(fitted):
    """A fit through the ODE keeps its GP per output (one output here): the domain criterion is not built for it,
    and the campaign says so, naming the criterion that works, instead of the shared-kernel advice."""
    campaign = design.Campaign(lv(), candidates(10, seed=5), torch.linspace(0, 6, 13, dtype=DT), fitted,
                               criterion="domain", domain=[(0.3, 3.0)])  # fmt: skip
    with pytest.raises(InputError, match="not built for a GP kept per output.*criterion='information'"):
        campaign.ask(2)
