"""Designs conditioned on the data a fitted GP already holds (issue 11, point 1)."""

from __future__ import annotations

import math
import re
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.design._proxy import PROXY_TOLERANCES
from torchmisspec.design.candidates import grid
from torchmisspec.paper._setup import LINEAR_PRIOR, NOISE_STD

DT = torch.float64
TIMES = torch.linspace(0, 6, 11, dtype=DT)


@pytest.fixture(scope="module")
def corners():
    """paper 5.2's 13 x 13 grid; a GP with the paper's prior fitted on the experiments from the four corners."""
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 13)
    corner_idx = [0, 12, 156, 168]
    assert torch.equal(cand[corner_idx].abs(), torch.ones(4, 2, dtype=DT))
    traj = tms.simulate(system, cand[corner_idx], TIMES)
    samples = tms.correction_samples(
        traj, system, derivative="oracle", noise_std=NOISE_STD, generator=torch.Generator().manual_seed(0)
    )
    fitted = tms.CorrectionGP(**LINEAR_PRIOR).fit(samples)
    return system, cand, corner_idx, fitted


def _joint_logdet(gp, data_x, data_noise, new_x, noise):
    """Brute force: logdet of the joint covariance of (data, new) samples minus the data's."""
    x = torch.cat([data_x, new_x])
    C = gp.covariance(x) + torch.diag(torch.cat([data_noise, torch.full((new_x.shape[0],), noise, dtype=DT)]))
    Cd = gp.covariance(data_x) + torch.diag(data_noise)
    return float(torch.linalg.slogdet(C)[1] - torch.linalg.slogdet(Cd)[1])


def test_conditioned_gains_are_brute_force_log_determinants(corners):
    system, cand, corner_idx, fitted = corners
    plan = design.greedy(cand, 5, system=system, times=TIMES, gp=fitted)
    assert plan.diagnostics["conditioned"] == 44
    proxies = system.select_inputs(plan.proxies)  # (5, T, d_in)
    data_noise = torch.full((44,), fitted.noise_variance, dtype=DT)
    sigma2 = fitted.noise_variance
    previous = 0.0
    for j in range(5):
        new_x = proxies[: j + 1].reshape(-1, 2)
        total = (
            0.5
            * system.output_dim
            * (
                _joint_logdet(fitted, fitted.train_inputs_, data_noise, new_x, sigma2)
                - new_x.shape[0] * math.log(sigma2)
            )
        )
        assert float(plan.gains[: j + 1].sum()) == pytest.approx(total, rel=1e-8)
        assert float(plan.gains[j]) == pytest.approx(total - previous, rel=1e-6, abs=1e-9)
        previous = total
    # information_gain conditions the same way
    assert design.information_gain(proxies.reshape(-1, 2), fitted) == pytest.approx(previous, rel=1e-8)
    prior = design.information_gain(proxies.reshape(-1, 2), fitted, condition=False)
    assert prior > previous  # data already collected make new samples less informative


def test_known_per_sample_noise_is_conditioned_on(corners):
    system, cand, _, fitted = corners
    X, Y = fitted.train_inputs_, fitted.train_targets_
    noise = torch.linspace(1e-5, 1e-3, X.shape[0], dtype=DT).unsqueeze(-1).expand(-1, 2).contiguous()
    gp = tms.CorrectionGP(**LINEAR_PRIOR).fit(X, Y, noise=noise)
    plan = design.greedy(cand, 2, system=system, times=TIMES, gp=gp)
    new_x = system.select_inputs(plan.proxies).reshape(-1, 2)
    data_noise = noise[:, 0] + gp.noise_variance  # known noise plus the learned (here fixed) floor
    # a new sample is as noisy as the median earlier one (known part) plus the floor, not the floor alone
    sigma2 = gp.noise_variance + float(noise[:, 0].median())
    total = 0.5 * 2 * (_joint_logdet(gp, X, data_noise, new_x, sigma2) - new_x.shape[0] * math.log(sigma2))
    assert float(plan.gains.sum()) == pytest.approx(total, rel=1e-8)


def test_conditioning_on_the_corners_removes_them_from_the_top_picks(corners):
    system, cand, corner_idx, fitted = corners
    unconditioned = design.greedy(
        cand,
        4,
        system=system,
        times=TIMES,
        gp=fitted,
        condition=False,
        proxy=design.Proxy("known"),
    )
    assert sorted(unconditioned.indices.tolist()) == corner_idx  # what the prior picks (the report)
    conditioned = design.greedy(cand, 4, system=system, times=TIMES, gp=fitted)
    # the measured corners fall behind (the centre first); with noise variance 2.5 x the prior's, repeating a
    # measured trajectory still informs, so a corner may come back later
    assert not set(conditioned.indices[:3].tolist()) & set(corner_idx)
    assert float(conditioned.gains[0]) < float(unconditioned.gains[0])
    # an unfitted GP with the same hyperparameters picks like the unconditioned design
    prior = design.greedy(cand, 4, system=system, times=TIMES, gp=tms.CorrectionGP(**LINEAR_PRIOR))
    assert prior.indices.tolist() == unconditioned.indices.tolist()
    assert prior.diagnostics["conditioned"] == 0


def test_lazy_plain_and_naive_agree_when_conditioned(corners):
    system, cand, _, fitted = corners
    picks = {
        m: design.greedy(cand[::3], 6, system=system, times=TIMES, gp=fitted, method=m)
        for m in ("lazy", "plain", "naive")
    }
    assert picks["lazy"].indices.tolist() == picks["plain"].indices.tolist() == picks["naive"].indices.tolist()
    torch.testing.assert_close(picks["lazy"].gains, picks["naive"].gains, rtol=1e-7, atol=1e-10)
    screened = design.greedy(
        cand,
        6,
        system=system,
        times=TIMES,
        gp=fitted,
        engine=design.Engine(screen=True),
    )
    plain = design.greedy(cand, 6, system=system, times=TIMES, gp=fitted, method="plain")
    assert screened.indices.tolist() == plain.indices.tolist()


def test_condition_on_an_unfitted_gp_is_refused():
    system = tms.systems.paper_linear()
    with pytest.raises(
        tms.InputError, match="condition: expected a fitted gp to condition on its data, got an unfitted one"
    ):
        design.greedy(
            grid(system.domain, 3), 1, system=system, times=TIMES, gp=tms.CorrectionGP(**LINEAR_PRIOR), condition=True
        )


def test_corrected_proxies_follow_the_corrected_model(corners):
    system, cand, corner_idx, fitted = corners
    plan = design.greedy(cand, 3, system=system, times=TIMES, gp=fitted)
    assert plan.diagnostics["proxy"] == "corrected"
    rtol, atol = PROXY_TOLERANCES  # a design tolerance: proxies stand in for unknown trajectories
    expected = tms.CorrectedODE(system, fitted).predict(plan.points, TIMES, solver=tms.Solver(rtol=rtol, atol=atol))
    # the proxies were solved in the batch of all candidates, the prediction in a batch of 3: an adaptive batched solve
    # shares its steps (and its atol is in units of the batch's states), so they agree to the solver's tolerance
    torch.testing.assert_close(plan.proxies, expected, rtol=10 * rtol, atol=10 * atol)
    accurate = tms.CorrectedODE(system, fitted).predict(plan.points, TIMES)
    torch.testing.assert_close(plan.proxies, accurate, rtol=0, atol=1e-5)
    known = design.greedy(
        cand,
        3,
        system=system,
        times=TIMES,
        gp=fitted,
        proxy=design.Proxy("known"),
    )
    assert known.diagnostics["proxy"] == "known"
    torch.testing.assert_close(known.proxies, design.proxy_trajectories(system, known.points, TIMES))
    # closer to the truth than G alone, over all candidates, once data cover D (13 experiments across the grid,
    # sample noise 1e-3: at the paper's 1e-2, as large as F itself, 13 experiments barely move the mean)
    spread = tms.simulate(system, cand[::13], TIMES)
    samples = tms.correction_samples(
        spread, system, derivative="oracle", noise_std=1e-3, generator=torch.Generator().manual_seed(1)
    )
    truth = tms.simulate(system, cand, TIMES).states
    gp = tms.CorrectionGP(**{**LINEAR_PRIOR, "noise_variance": 1e-6}).fit(samples)
    corrected = tms.CorrectedODE(system, gp).predict(cand, TIMES)
    g_only = design.proxy_trajectories(system, cand, TIMES)
    assert tms.trajectory_rmse(corrected, truth) < 0.8 * tms.trajectory_rmse(g_only, truth)
    assert (
        design.greedy(cand, 1, system=system, times=TIMES, gp=tms.CorrectionGP(**LINEAR_PRIOR)).diagnostics["proxy"]
        == "known"
    )


def test_bad_proxy_names_and_an_unfitted_correction():
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 3)
    with pytest.raises(tms.InputError, match=r"Proxy.dynamics: expected one of \('known', 'corrected'\).*got 'true'"):
        design.greedy(
            cand,
            1,
            system=system,
            times=TIMES,
            gp=tms.CorrectionGP(**LINEAR_PRIOR),
            proxy=design.Proxy("true"),
        )
    with pytest.raises(tms.InputError, match="proxy='corrected': an unfitted gp"):
        design.greedy(
            cand,
            1,
            system=system,
            times=TIMES,
            gp=tms.CorrectionGP(**LINEAR_PRIOR),
            proxy=design.Proxy("corrected"),
        )


def test_low_rank_data_term_is_within_its_certified_error():
    """Many samples: the data term uses r < N pivots; every kernel entry stays within ``data_error`` of the exact."""
    from torchmisspec.design._common import GPKernel

    system = tms.systems.paper_gravity()
    times = torch.linspace(0, 3, 20, dtype=DT)
    cand = design.candidates.orbits(20, generator=torch.Generator().manual_seed(0))
    samples = tms.correction_samples(
        tms.simulate(system, cand, times),
        system,
        derivative="oracle",
        noise_std=1e-2,
        generator=torch.Generator().manual_seed(0),
    )
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-3, noise_variance=1e-4).fit(samples)
    kern = GPKernel(gp, input_dim=2)
    assert kern.data_rank < samples.num_samples  # the low-rank path is the one tested
    x = torch.rand(200, 2, dtype=DT, generator=torch.Generator().manual_seed(1)) * 6 - 3
    X = gp.train_inputs_
    C = gp.covariance(X) + 1e-4 * torch.eye(X.shape[0], dtype=DT)
    exact = gp.covariance(x) - gp.covariance(x, X) @ torch.linalg.solve(C, gp.covariance(X, x))
    err = float((kern(x) - exact).abs().max())
    assert err <= kern.data_error
    assert kern.data_error < 1e-4 * 1e-3  # certified to 1e-4 of the prior variance
    torch.testing.assert_close(kern.diag(x), exact.diagonal().clamp_min(0), rtol=0, atol=kern.data_error)


def test_data_term_stays_finite_at_round_off():
    """Data from a campaign whose pivoted data factor once got a zero diagonal entry at round-off (NaN gains)."""
    from pathlib import Path

    import numpy as np

    from torchmisspec.design._common import GPKernel

    table = torch.as_tensor(
        np.loadtxt(Path(__file__).parent / "data" / "pivot_roundoff.csv", delimiter=",", skiprows=2)
    )
    X, Y = table[:, :2], table[:, 2:]
    noise = 0.0001181655721146965
    gp = tms.CorrectionGP(lengthscale=1.2124344436602665, outputscale=0.00014628282013504575, noise_variance=noise)
    gp.fit(X, Y)
    kern = GPKernel(gp, input_dim=2)
    x = torch.rand(100, 2, dtype=DT, generator=torch.Generator().manual_seed(3)) * 4 - 2
    C = gp.covariance(X) + noise * torch.eye(X.shape[0], dtype=DT)
    exact = gp.covariance(x) - gp.covariance(x, X) @ torch.linalg.solve(C, gp.covariance(X, x))
    got = kern(x)
    assert bool(torch.isfinite(got).all())
    assert float((got - exact).abs().max()) <= kern.data_error


def test_proxy_check_for_both_proxies():
    """Theorem 1's quantities for the known and the corrected proxies: with a GP fitted on 16 experiments the
    corrected model's trajectories sit closer to the truth (smaller kernel discrepancy and gain gap)."""
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 13)
    samples = tms.correction_samples(
        tms.simulate(system, grid(system.domain, 4), TIMES),
        system,
        derivative="oracle",
        noise_std=NOISE_STD,
        generator=torch.Generator().manual_seed(0),
    )
    fitted = tms.CorrectionGP(**LINEAR_PRIOR).fit(samples)
    for idx in ([20, 84, 130], [0, 168, 12]):
        known, corrected = (
            design.proxy_check(idx, cand, system=system, times=TIMES, gp=fitted, proxy=p)
            for p in ("known", "corrected")
        )
        assert corrected.delta < 0.5 * known.delta
        assert corrected.gap < 0.3 * known.gap
    conditioned = design.proxy_check(
        idx, cand, system=system, times=TIMES, gp=fitted, proxy="corrected", condition=True
    )
    assert conditioned.proxy_gain < corrected.proxy_gain  # the data already explain part of it
    # the proxy gain of the corrected check is the criterion along the corrected model's trajectories
    rtol, atol = PROXY_TOLERANCES
    paths = tms.CorrectedODE(system, fitted).predict(cand[idx], TIMES, solver=tms.Solver(rtol=rtol, atol=atol))
    pts = system.select_inputs(paths).reshape(-1, 2)
    assert corrected.proxy_gain == pytest.approx(design.information_gain(pts, fitted, condition=False), rel=1e-10)
    with pytest.raises(tms.InputError, match="proxy: expected"):
        design.proxy_check(idx, cand, system=system, times=TIMES, gp=fitted, proxy="true")


def _per_output_gain(gp, data_noise, new_x, new_noise):
    """Brute force over outputs: sum_o (1/2) [logdet C_o(data + new) - logdet C_o(data) - M log s_o], with output o's
    own kernel, its own data noise ``data_noise[:, o]`` and new-sample noise ``new_noise[o]``."""
    X = gp.train_inputs_
    x = torch.cat([X, new_x])
    with torch.no_grad():
        K = gp.covar_module.forward(x, x)
    K = K if K.dim() == 3 else K.expand(data_noise.shape[1], -1, -1)
    total = 0.0
    for o in range(data_noise.shape[1]):
        s = float(new_noise[o])
        C = K[o] + torch.diag(torch.cat([data_noise[:, o], torch.full((new_x.shape[0],), s, dtype=DT)]))
        n = X.shape[0]
        Cd = K[o, :n, :n] + torch.diag(data_noise[:, o])
        total += 0.5 * float(torch.linalg.slogdet(C)[1] - torch.linalg.slogdet(Cd)[1] - new_x.shape[0] * math.log(s))
    return total


def test_per_output_kernels_condition_each_output_on_its_own_data(corners):
    """A per-output GP (what fit_correction may return) is designed with: each output's information is conditioned
    on that output's data under its own kernel and noise; the greedy's gains sum to the brute-force total."""
    system, cand, _, fitted = corners
    X, Y = fitted.train_inputs_, fitted.train_targets_.clone()
    Y[:, 1] *= 30.0  # the outputs differ in size, so their hyperparameters differ
    gp = tms.CorrectionGP(per_output=True).fit(X, Y)
    assert float((gp.lengthscale[0] - gp.lengthscale[1]).abs()) > 1e-3
    picks = {m: design.greedy(cand[::4], 3, system=system, times=TIMES, gp=gp, method=m) for m in ("lazy", "naive")}
    assert picks["lazy"].indices.tolist() == picks["naive"].indices.tolist()
    new_x = system.select_inputs(picks["lazy"].proxies).reshape(-1, 2)
    noise = gp.noise_variance.reshape(1, -1).expand(X.shape[0], -1)
    expected = _per_output_gain(gp, noise, new_x, gp.noise_variance)
    assert float(picks["lazy"].gains.sum()) == pytest.approx(expected, rel=1e-7)
    assert design.information_gain(new_x, gp) == pytest.approx(expected, rel=1e-7)
    gains = design.marginal_gains(picks["lazy"].indices, cand[::4], system=system, times=TIMES, gp=gp)
    torch.testing.assert_close(gains.sum(), picks["lazy"].gains.sum(), rtol=1e-7, atol=0.0)


def test_noise_that_differs_between_outputs_is_conditioned_per_output(corners):
    """A shared kernel fitted with known noise that differs between outputs (the default derivative='auto' samples)
    was refused; now each output is conditioned on its own noisy data, and a new sample of output o is as noisy as
    the median earlier one of that output plus the floor."""
    system, cand, _, fitted = corners
    X, Y = fitted.train_inputs_, fitted.train_targets_
    base = torch.linspace(1e-5, 1e-3, X.shape[0], dtype=DT)
    noise = torch.stack([base, 20 * base.flip(0)], dim=-1)
    gp = tms.CorrectionGP(**LINEAR_PRIOR).fit(X, Y, noise=noise)
    plan = design.greedy(cand, 2, system=system, times=TIMES, gp=gp)
    new_x = system.select_inputs(plan.proxies).reshape(-1, 2)
    future = gp.noise_variance + noise.median(dim=0).values
    expected = _per_output_gain(gp, noise + gp.noise_variance, new_x, future)
    assert float(plan.gains.sum()) == pytest.approx(expected, rel=1e-7)
    with pytest.raises(tms.InputError, match="criterion='domain' .* per-output noise"):
        design.greedy(cand, 2, system=system, times=TIMES, gp=gp, criterion="domain")


def test_corrected_proxies_isolate_the_candidates_that_blow_up():
    """Candidates from which G + the posterior mean cannot be integrated get G's proxy, the others the corrected
    model's (each as solved alone), and the warning counts them."""
    from torchmisspec.design._proxy import corrected_proxies, proxy_trajectories

    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(60, 2, generator=g, dtype=torch.float64) * 0.4
    gp = tms.CorrectionGP(kernel="polynomial", degree=3, outputscale=1.0, noise_variance=1e-8).fit(x, 3 * x**3)
    cands = torch.tensor(
        [[0.1, 0.1], [3.0, 3.0], [0.2, -0.1], [-4.0, 4.0], [0.3, 0.0], [5.0, 5.0]], dtype=torch.float64
    )
    times = torch.linspace(0, 6, 7, dtype=torch.float64)
    model = tms.CorrectedODE(system, gp)
    alone, blown = [], []
    for i in range(len(cands)):
        with warnings.catch_warnings():  # a forecast that stops early is flagged (issue 41), not raised
            warnings.simplefilter("ignore", tms.TorchMisspecWarning)
            try:
                path = model.predict(cands[i : i + 1], times, solver=tms.Solver(rtol=1e-6, atol=1e-8))[0]
                stopped = bool(model.incomplete.any())
            except tms.IntegrationError:
                stopped = True
        if stopped:
            blown.append(i)
            path = proxy_trajectories(system, cands[i : i + 1], times)[0]
        alone.append(path)
    assert blown, "the test needs candidates that blow up"
    with pytest.warns(tms.TorchMisspecWarning, match=f"blows up from {len(blown)} of 6 candidates"):
        proxies = corrected_proxies(system, gp, cands, times)
    torch.testing.assert_close(proxies, torch.stack(alone), rtol=1e-5, atol=1e-7)
    # in chunks of 2 (a design's proxies, proxy_paths): one warning, naming the candidates by their own index
    from torchmisspec.design import _proxy

    previous, _proxy.PROXY_CHUNK = _proxy.PROXY_CHUNK, 2
    try:
        with pytest.warns(
            tms.TorchMisspecWarning, match=re.escape(f"{len(blown)} of 6 candidates (e.g. {blown}:")
        ) as seen:
            chunked = _proxy.proxy_paths("corrected", system, gp, cands, times)
    finally:
        _proxy.PROXY_CHUNK = previous
    assert len([w for w in seen if "blows up from" in str(w.message)]) == 1
    torch.testing.assert_close(chunked, proxies, rtol=1e-5, atol=1e-7)
