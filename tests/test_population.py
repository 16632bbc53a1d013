"""Populations (issue 43): per-experiment parameters with a population distribution, against closed forms.

The reference model is linear in its parameter: dy/dt = theta, y(t) = y0 + theta t, measured with additive noise.
Given the population N(mu, omega^2) and the noise variance s^2, experiment i's posterior is conjugate Gaussian:
mode (sum_t t (y_it - y0) / s^2 + mu / omega^2) / (sum_t t^2 / s^2 + 1 / omega^2), variance the inverse of that
denominator. The EM update and the standard errors have closed forms too (module notes of
:mod:`torchmisspec.population.nlme`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.noise import Additive
from torchmisspec.population import LogNormal, Normal, Population
from torchmisspec.population._modes import Modes
from torchmisspec.population._subjects import subject_system, with_subject_inputs
from torchmisspec.population.fit import PopulationFit
from torchmisspec.population.model import PopulationValues, covariate_matrix
from torchmisspec.population.nlme import fit_nlme, m_step, make_layout
from torchmisspec.population.predict import predict_subject
from torchmisspec.population.uncertainty import intervals, standard_errors
from torchmisspec.systems._rows import per_row

DT = torch.float64


def slope(y, theta):
    return theta[0] * torch.ones_like(y)


def linear_system(prior=(1.0, 0.5)):
    return tms.MisspecifiedSystem(slope, 1, parameters={"c": prior}, state_names=["y"])


def linear_data(thetas, times, g, noise=0.1, y0=2.0):
    states = y0 + thetas[:, None, None] * times[None, :, None]
    states = states + noise * torch.randn(states.shape, generator=g, dtype=DT)
    states[:, 0] = y0  # the first row gives the initial state
    return tms.Trajectories(times, states, state_names=["y"])


def two_parameter(y, theta):
    return torch.stack([-theta[0] * y[..., 0], theta[0] * y[..., 0] / theta[1] - 0.1 * y[..., 1]], -1)


def branching(y, theta):  # Python control flow on a value: no broadcast or vmap
    rate = theta[0] if float(theta[0]) > 0 else -theta[0]
    return torch.stack([-rate * y[..., 0], rate * y[..., 0] / theta[1] - 0.1 * y[..., 1]], -1)


@pytest.mark.parametrize("known", [two_parameter, branching])
def test_each_row_gets_its_own_parameters(known):
    system = tms.MisspecifiedSystem(known, 2, parameters={"ka": (1.0, 0.5), "V": (0.5, 0.2)})
    g = torch.Generator().manual_seed(0)
    thetas = 0.5 + torch.rand(7, 2, generator=g, dtype=DT)
    y = torch.rand(7, 2, generator=g, dtype=DT)
    call = per_row(known, autonomous=True)
    out = call(torch.zeros(7, dtype=DT), y, y.new_zeros(7, 0), thetas)
    ref = torch.stack([system.at(thetas[i]).known_rhs(y[i : i + 1])[0] for i in range(7)])
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)


def test_subject_system_simulates_each_experiment_with_its_parameters():
    system = tms.MisspecifiedSystem(two_parameter, 2, parameters={"ka": (1.0, 0.5), "V": (0.5, 0.2)})
    thetas = torch.tensor([[0.8, 0.4], [1.5, 0.6], [1.1, 0.5]], dtype=DT)
    y0 = torch.tensor([[4.0, 0.0], [3.0, 0.0], [5.0, 0.1]], dtype=DT)
    times = torch.linspace(0, 5, 6, dtype=DT)
    sub = subject_system(system, [0, 1], system.theta)
    base = tms.Trajectories(times, y0[:, None].expand(3, 6, 2).clone())
    ctrl = with_subject_inputs(base, thetas, ["ka", "V"]).controls
    together = tms.simulate(sub, y0, times, controls=ctrl).states
    for i in range(3):
        alone = tms.simulate(system.at(thetas[i]), y0[i : i + 1], times).states[0]
        torch.testing.assert_close(together[i], alone, rtol=1e-8, atol=1e-10)


def _linear_fit(K=8, mu=1.0, omega=0.3, seed=0, dist=None):
    g = torch.Generator().manual_seed(seed)
    thetas = mu + omega * torch.randn(K, generator=g, dtype=DT)
    times = torch.linspace(0, 1, 6, dtype=DT)
    data = linear_data(thetas, times, g)
    population = Population(["c"], distribution=dist or Normal())
    return fit_nlme(linear_system(), data, population, Additive()), data, thetas


def _mean_square_at_the_modes(fit, data) -> float:
    """The residuals' mean square at the modes (what the fit weighs by) of the linear model."""
    t, y = data.times[1:], data.states[:, 1:, 0] - 2.0
    return float((fit.modes.eta[:, :1] * t - y).pow(2).mean())


def test_conditional_modes_are_the_conjugate_posterior():
    fit, data, _ = _linear_fit()
    s2 = _mean_square_at_the_modes(fit, data)
    mu, w2 = float(fit.values.mean[0]), float(fit.values.spread[0]) ** 2
    t = data.times[1:]
    y = data.states[:, 1:, 0] - 2.0
    precision = float((t * t).sum()) / s2 + 1 / w2
    mode = ((y * t).sum(1) / s2 + mu / w2) / precision
    torch.testing.assert_close(fit.modes.eta[:, 0], mode, rtol=2e-3, atol=1e-6)
    torch.testing.assert_close(
        fit.modes.covariance[:, 0, 0], torch.full((8,), 1 / precision, dtype=DT), rtol=2e-3, atol=0
    )


def test_the_noise_scale_counts_the_freedom_the_fitted_parameters_took():
    """The conjugate model's hat matrix: experiment i's trace is a / (a + 1 / omega^2), a = sum_t t^2 / s^2 (s^2
    the mean square the fit weighs by), so the scale is the residual sum of squares over N - K a / (a + 1/omega^2)."""
    fit, data, _ = _linear_fit()
    s2, w2 = _mean_square_at_the_modes(fit, data), float(fit.values.spread[0]) ** 2
    a = float(data.times[1:].pow(2).sum()) / s2
    n = data.states[:, 1:].numel()
    expected = s2 * n / (n - data.num_experiments * a / (a + 1 / w2))
    assert float(fit.modes.scale[0]) ** 2 == pytest.approx(expected, rel=1e-3)


def test_the_noise_scale_is_unbiased_where_the_mean_square_is_not():
    """Over 40 populations of 8 experiments x 5 measurements (noise 0.1): the mean of the scale's square is the
    noise variance within 3 standard errors; the mean square at the modes is not (the fitted parameters took about
    one measurement in five)."""
    scales, raw = [], []
    for seed in range(40):
        fit, data, _ = _linear_fit(seed=seed)
        scales.append(float(fit.modes.scale[0]) ** 2)
        raw.append(_mean_square_at_the_modes(fit, data))
    scales, raw = torch.tensor(scales, dtype=DT), torch.tensor(raw, dtype=DT)
    se = float(scales.std()) / math.sqrt(scales.numel())
    assert abs(float(scales.mean()) - 0.01) < 3 * se, (float(scales.mean()), se)
    assert float(raw.mean()) < 0.01 - 3 * float(raw.std()) / math.sqrt(raw.numel())


def test_em_settles_at_its_own_update():
    fit, _, _ = _linear_fit()
    assert fit.converged
    again = m_step(fit.values, fit.modes, fit.covariates, fit.values.spread * 1e-3)
    assert abs(float(again.mean[0] - fit.values.mean[0])) < 5e-3 * float(fit.values.spread[0])
    assert abs(math.log(float(again.spread[0] / fit.values.spread[0]))) < 5e-3


def _modes(eta, var):
    K, kv = eta.shape
    cov = torch.diag_embed(var)
    return Modes(eta, cov, torch.zeros(0, dtype=DT), torch.zeros(K, 1, dtype=DT), torch.ones(1), torch.zeros(1), 0)


def test_m_step_is_the_linear_gaussian_update():
    g = torch.Generator().manual_seed(1)
    eta, var = torch.randn(10, 2, generator=g, dtype=DT), torch.rand(10, 2, generator=g, dtype=DT) * 0.1
    X = torch.randn(10, 1, generator=g, dtype=DT)
    acts = torch.tensor([[True], [False]])
    values = PopulationValues(
        torch.zeros(2, dtype=DT), torch.ones(2, dtype=DT), torch.zeros(2, 1, dtype=DT), X.mean(0), acts
    )
    new = m_step(values, _modes(eta, var), X, torch.full((2,), 1e-6, dtype=DT))
    D = torch.cat([torch.ones(10, 1, dtype=DT), X - X.mean(0)], -1)
    coef = torch.linalg.lstsq(D, eta[:, :1]).solution[:, 0]
    torch.testing.assert_close(new.mean[0], coef[0])
    torch.testing.assert_close(new.effects[0, 0], coef[1])
    torch.testing.assert_close(new.spread[0], ((eta[:, 0] - D @ coef).pow(2) + var[:, 0]).sum().div(10 - 2).sqrt())
    torch.testing.assert_close(new.mean[1], eta[:, 1].mean())
    assert float(new.effects[1, 0]) == 0.0
    centred = eta[:, 1] - eta[:, 1].mean()
    torch.testing.assert_close(new.spread[1], (centred.pow(2) + var[:, 1]).sum().div(10 - 1).sqrt())


def test_standard_errors_of_exactly_known_experiments():
    """tau = 0: SE(mu) = omega / sqrt(K), SE(omega) = omega / sqrt(2 (K - 1)) (the sample mean and REML's spread)."""
    K, omega = 16, 0.4
    eta = torch.randn(K, 1, generator=torch.Generator().manual_seed(2), dtype=DT)
    values = PopulationValues(eta.mean(0), torch.tensor([omega], dtype=DT), torch.zeros(1, 0, dtype=DT),
                              torch.zeros(0, dtype=DT), torch.zeros(1, 0, dtype=torch.bool))  # fmt: skip
    se_mean, se_spread, _ = standard_errors(
        values, _modes(eta, torch.zeros(K, 1, dtype=DT)), torch.zeros(K, 0, dtype=DT)
    )
    assert float(se_mean[0]) == pytest.approx(omega / math.sqrt(K), rel=1e-9)
    assert float(se_spread[0]) == pytest.approx(omega / math.sqrt(2 * (K - 1)), rel=1e-9)


def _known_values(eta: torch.Tensor, X: torch.Tensor, acts: torch.Tensor):
    """The M step's values from experiments known exactly (no Laplace variance) and their modes."""
    K, kv = eta.shape
    start = PopulationValues(torch.zeros(kv, dtype=DT), torch.ones(kv, dtype=DT),
                             torch.zeros(kv, X.shape[-1], dtype=DT), X.mean(0), acts)  # fmt: skip
    modes = _modes(eta, torch.zeros(K, kv, dtype=DT))
    return m_step(start, modes, X, torch.full((kv,), 1e-9, dtype=DT)), modes


def test_intervals_of_exactly_known_experiments_are_the_textbook_ones():
    """tau = 0: the typical value's interval is the one-sample t interval, the spread's the chi-square interval of a
    normal sample's variance, and a covariate's effect the least-squares t interval (scipy's quantiles)."""
    from scipy import stats

    K = 9
    g = torch.Generator().manual_seed(7)
    eta = torch.randn(K, 2, generator=g, dtype=DT)
    X = torch.randn(K, 1, generator=g, dtype=DT)
    values, modes = _known_values(eta, X, torch.tensor([[False], [True]]))
    out = intervals(values, modes, X, 0.9)
    e = eta[:, 0].numpy()
    lo, hi = stats.t.interval(0.9, K - 1, loc=e.mean(), scale=stats.sem(e))
    torch.testing.assert_close(out.mean[0], torch.tensor([lo, hi], dtype=DT))
    s2 = e.var(ddof=1)
    expected = [((K - 1) * s2 / stats.chi2.ppf(q, K - 1)) ** 0.5 for q in (0.95, 0.05)]
    torch.testing.assert_close(out.spread[0], torch.tensor(expected, dtype=DT))
    D = torch.cat([torch.ones(K, 1, dtype=DT), X - X.mean(0)], -1).numpy()
    coef, res, *_ = np.linalg.lstsq(D, eta[:, 1].numpy(), rcond=None)
    sd = np.sqrt(res[0] / (K - 2) * np.linalg.inv(D.T @ D)[1, 1])
    t = stats.t.ppf(0.95, K - 2)
    torch.testing.assert_close(out.effects[1, 0], torch.tensor([coef[1] - t * sd, coef[1] + t * sd], dtype=DT))
    assert bool(out.effects[0, 0].isnan().all())  # not estimated


def test_a_new_subject_s_prior_is_the_textbook_prediction_interval():
    """Experiments known exactly: the new subject's normal prior has the central 95 % interval of the prediction
    interval of a new observation: a normal sample's (t with K - 1 degrees of freedom, scale s sqrt(1 + 1/K)), and a
    regression's at the new covariate (t with K - 2, scale s sqrt(1 + d (D^T D)^-1 d)), by numpy and scipy."""
    from scipy import stats

    from torchmisspec.population.uncertainty import new_subject_prior

    K = 7
    g = torch.Generator().manual_seed(11)
    eta = torch.randn(K, 2, generator=g, dtype=DT)
    X = torch.randn(K, 1, generator=g, dtype=DT)
    values, modes = _known_values(eta, X, torch.tensor([[False], [True]]))
    x = torch.tensor([[1.7]], dtype=DT)
    typical, spread = new_subject_prior(values, modes, X, x)
    half = stats.norm.ppf(0.975) * spread.numpy()
    e = eta[:, 0].numpy()
    assert half[0] == pytest.approx(stats.t.ppf(0.975, K - 1) * e.std(ddof=1) * math.sqrt(1 + 1 / K), rel=1e-9)
    D = torch.cat([torch.ones(K, 1, dtype=DT), X - X.mean(0)], -1).numpy()
    coef, res, *_ = np.linalg.lstsq(D, eta[:, 1].numpy(), rcond=None)
    d = np.array([1.0, 1.7 - float(X.mean())])
    s = math.sqrt(res[0] / (K - 2))
    assert float(typical[0, 1]) == pytest.approx(d @ coef, rel=1e-9)
    assert half[1] == pytest.approx(stats.t.ppf(0.975, K - 2) * s * math.sqrt(1 + d @ np.linalg.inv(D.T @ D) @ d))


def test_intervals_cover_at_their_level():
    """2,000 populations of 8 experiments known exactly: the 95 % intervals of mu and omega cover the truth
    95 % +- 1.5 % of the time (their binomial spread is 0.5 %)."""
    g = torch.Generator().manual_seed(8)
    X, acts = torch.zeros(8, 0, dtype=DT), torch.zeros(1, 0, dtype=torch.bool)
    hits = torch.zeros(2)
    for _ in range(2000):
        eta = 0.5 + 0.3 * torch.randn(8, 1, generator=g, dtype=DT)
        values, modes = _known_values(eta, X, acts)
        out = intervals(values, modes, X)
        hits[0] += float((out.mean[0, 0] <= 0.5) & (0.5 <= out.mean[0, 1]))
        hits[1] += float((out.spread[0, 0] <= 0.3) & (0.3 <= out.spread[0, 1]))
    assert ((hits / 2000 - 0.95).abs() < 0.015).all(), hits / 2000


@pytest.mark.parametrize("level", [0.0, 1.0, 95, "0.95", True])
def test_intervals_reject_a_level_outside_0_1(level):
    values, modes = _known_values(torch.zeros(4, 1, dtype=DT), torch.zeros(4, 0, dtype=DT),
                                  torch.zeros(1, 0, dtype=torch.bool))  # fmt: skip
    with pytest.raises(tms.InputError, match="level: expected a confidence level"):
        intervals(values, modes, torch.zeros(4, 0, dtype=DT), level)


def test_population_recovered_within_its_standard_errors():
    fit, _, thetas = _linear_fit(K=60, mu=1.0, omega=0.3, seed=3)
    mean_se, spread_se, _ = fit.standard_errors
    assert abs(float(fit.values.mean[0]) - 1.0) < 3 * float(mean_se[0])
    assert abs(float(fit.values.spread[0]) - 0.3) < 3 * float(spread_se[0])
    assert float(mean_se[0]) == pytest.approx(0.3 / math.sqrt(60), rel=0.3)


def test_lognormal_population_of_a_positive_parameter():
    fit, _, thetas = _linear_fit(K=40, mu=1.0, omega=0.2, seed=4, dist=LogNormal())
    assert float(fit.values.mean[0].exp()) == pytest.approx(1.0, abs=3 * float(fit.standard_errors[0][0]) + 0.05)
    assert bool((fit.thetas[:, 0] > 0).all())


def test_a_pooled_start_outside_the_support_falls_back_to_the_priors(monkeypatch):
    """One set of parameters for every experiment can fit a log-normal parameter negative (R's BodyWeight without rat
    09: k and A): EM then starts at the priors instead of a NaN log."""
    from types import SimpleNamespace

    from torchmisspec.population import nlme

    g = torch.Generator().manual_seed(4)
    data = linear_data(1.0 + 0.2 * torch.randn(10, generator=g, dtype=DT), torch.linspace(0, 1, 5, dtype=DT), g)
    system, population = linear_system(prior=(1.5, 0.5)), Population(["c"], distribution=LogNormal())
    layout = make_layout(system, population)
    X = torch.zeros(10, 0, dtype=DT)
    pooled = SimpleNamespace(theta=torch.tensor([-0.3], dtype=DT), initial_states=data.initial_conditions)
    monkeypatch.setattr(nlme, "_known_fit_or_none", lambda *args: pooled)
    values, _, _ = nlme.starting_values(system, layout, population, X, data, Additive())
    assert float(values.mean[0]) == pytest.approx(math.log(1.5))
    pooled.theta = torch.tensor([0.9], dtype=DT)  # inside the support: the pooled fit stands
    values, _, _ = nlme.starting_values(system, layout, population, X, data, Additive())
    assert float(values.mean[0]) == pytest.approx(math.log(0.9))
    fit = fit_nlme(system, data, population, Additive(), progress=False)
    assert bool(torch.isfinite(fit.values.mean).all()) and bool((fit.thetas > 0).all())


def test_covariate_effect_is_recovered():
    g = torch.Generator().manual_seed(5)
    K = 40
    weight = 60 + 20 * torch.rand(K, generator=g, dtype=DT)
    thetas = 1.0 + 0.02 * (weight - 70) + 0.1 * torch.randn(K, generator=g, dtype=DT)
    data = linear_data(thetas, torch.linspace(0, 1, 6, dtype=DT), g)
    population = Population(["c"], distribution=Normal(), covariates={"c": ["weight"]})
    fit = fit_nlme(linear_system(), data, population, Additive(), covariates={"weight": weight})
    effect, se = float(fit.values.effects[0, 0]), float(fit.standard_errors[2][0, 0])
    assert abs(effect - 0.02) < 3 * se
    assert float(fit.values.spread[0]) < 0.2  # the covariate explains the rest of the spread


def test_a_group_covariate_is_centred_at_its_reference_group():
    """A 0/1 covariate (a diet against the reference diet) is centred at 0: the typical value is the reference
    group's, not that of a group at the covariate's mean, which does not exist; other covariates at their mean."""
    from torchmisspec.population.model import covariate_centre

    X = torch.tensor([[0.0, 1.5], [1.0, 2.5], [1.0, 3.5]], dtype=DT)
    torch.testing.assert_close(covariate_centre(X), torch.tensor([0.0, 2.5], dtype=DT))
    g = torch.Generator().manual_seed(8)
    K = 30
    group = (torch.arange(K) % 3 == 0).to(DT)  # a third of them on the other diet
    thetas = 1.0 + 0.5 * group + 0.05 * torch.randn(K, generator=g, dtype=DT)
    data = linear_data(thetas, torch.linspace(0, 1, 6, dtype=DT), g)
    population = Population(["c"], distribution=Normal(), covariates={"c": ["diet2"]})
    fit = fit_nlme(linear_system(), data, population, Additive(), covariates={"diet2": group})
    se = fit.standard_errors
    assert float(fit.values.centre[0]) == 0.0
    assert abs(float(fit.values.mean[0]) - float(thetas[group == 0].mean())) < 3 * float(se[0][0])
    assert abs(float(fit.values.effects[0, 0]) - 0.5) < 3 * float(se[2][0, 0])


def _classical(fit, system, population):
    sub = subject_system(system, fit.layout.vary, system.theta)
    return PopulationFit(system, population, Additive(), fit, fit, None, sub)


def test_new_subject_from_the_population_and_from_its_measurements():
    system, population = linear_system(), Population(["c"], distribution=Normal())
    fit, data, _ = _linear_fit(K=30, seed=6)
    pop = _classical(fit, system, population)
    times = torch.linspace(0, 1, 6, dtype=DT)
    g = torch.Generator().manual_seed(7)
    alone = predict_subject(pop, torch.tensor([2.0], dtype=DT), times, num_samples=4000, generator=g)
    typical, spread = fit.new_subject_prior(torch.zeros(1, 0, dtype=DT))  # the textbook one: its own test
    mu, omega = float(typical[0, 0]), float(spread[0])
    assert omega > float(fit.values.spread[0])  # the population's values are estimates
    lo, hi = alone.posterior.interval(0.9)
    z = 1.6448536269514722
    torch.testing.assert_close(hi[0, :, 0], 2.0 + times * (mu + z * omega), rtol=0.03, atol=1e-9)
    torch.testing.assert_close(lo[0, :, 0], 2.0 + times * (mu - z * omega), rtol=0.03, atol=1e-9)
    first = tms.Trajectories(times[:3], torch.tensor([[[2.0], [2.5], [3.0]]], dtype=DT), state_names=["y"])
    updated = predict_subject(pop, None, times, first=first, num_samples=8, generator=g)
    s2, t = float(fit.modes.scale[0]) ** 2, times[1:3]
    mu, omega = float(fit.values.mean[0]), float(fit.values.spread[0])  # the fit to measurements: point estimates
    precision = float((t * t).sum()) / s2 + 1 / omega**2
    mode = (float((t * torch.tensor([0.5, 1.0], dtype=DT)).sum()) / s2 + mu / omega**2) / precision
    assert float(updated.theta[0]) == pytest.approx(mode, rel=5e-3)
    assert float(updated.eta_covariance[0, 0]) == pytest.approx(1 / precision, rel=5e-3)
    # the path runs from the first measurement's time: times that start later are the same path's, not a shifted one
    late = tms.Trajectories(times[2:4], torch.tensor([[[3.0], [3.5]]], dtype=DT), state_names=["y"])
    whole = predict_subject(pop, None, times[2:], first=late, num_samples=2, generator=g).posterior.mean_path[0]
    later = predict_subject(pop, None, times[4:], first=late, num_samples=2, generator=g).posterior.mean_path[0]
    torch.testing.assert_close(later, whole[2:])
    c = float(predict_subject(pop, None, times[2:], first=late, num_samples=2, generator=g).theta[0])
    torch.testing.assert_close(later[:, 0], float(whole[0, 0]) + c * (times[4:] - times[2]))
    with pytest.raises(tms.InputError, match=r"times: expected times from the subject's first measurement at t = 0.4"):
        predict_subject(pop, None, times, first=late, num_samples=2)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: Population([]), "non-empty list"),
        (lambda: Population("ka"), "non-empty list"),
        (lambda: Population(["ka", "ka"]), "distinct"),
        (lambda: Population(["ka"], distribution="lognormal"), "Normal"),
        (lambda: Population(["ka"], covariates={"V": ["weight"]}), "keys among the varying"),
    ],
)
def test_bad_declarations_are_refused(build, match):
    with pytest.raises(tms.InputError, match=match):
        build()


def test_declaration_checked_against_the_system():
    with pytest.raises(tms.InputError, match="expected names among"):
        Population(["k"]).indices(linear_system())
    with pytest.raises(tms.InputError, match="positive prior value"):
        Population(["c"]).indices(linear_system(prior=(-1.0, 0.5)))
    population = Population(["c"], covariates={"c": ["weight"]})
    with pytest.raises(tms.InputError, match="expected values of"):
        covariate_matrix(population, {}, 3)
    with pytest.raises(tms.ShapeError, match="expected 3 values"):
        covariate_matrix(population, {"weight": [1.0, 2.0]}, 3)
    with pytest.raises(tms.InputError, match="finite"):
        covariate_matrix(population, {"weight": [1.0, math.nan, 2.0]}, 3)


def test_layout_orders_varying_then_shared():
    system = tms.MisspecifiedSystem(two_parameter, 2, parameters={"ka": (1.0, 0.5), "V": (0.5, 0.2)})
    layout = make_layout(system, Population(["V"]))
    assert layout.vary == [1] and layout.shared == [0] and layout.names == ["V", "ka"]
    theta = layout.theta(torch.log(torch.tensor([[0.4]], dtype=DT)), torch.tensor([1.3], dtype=DT))
    torch.testing.assert_close(theta, torch.tensor([[1.3, 0.4]], dtype=DT))


# ---- the next subject's design -------------------------------------------------------------------------------------
def test_design_first_pick_is_the_brute_force_best_time():
    """dy/dt = c: the sensitivity of y(t) to c is t, so one sample's information is log(1 + t^2 omega^2 / s^2) / 2
    (D-optimality), and the posterior variance it leaves, in units of the spread, 1 / (1 + t^2 omega^2 / s^2) (the
    expected error): the last time wins under both, and the scores are those numbers."""
    from torchmisspec.population.design import Determinant, SubjectParameters, design_subject

    system, population = linear_system(), Population(["c"], distribution=Normal())
    fit, _, _ = _linear_fit(K=20, seed=8)
    pop = _classical(fit, system, population)
    grid = torch.tensor([0.0, 0.2, 0.5, 0.9, 0.7], dtype=DT).sort().values
    s2, w2 = float(fit.modes.scale[0]) ** 2, float(fit.values.spread[0]) ** 2
    design = design_subject(pop, grid, 1, initial_states=[2.0], target=SubjectParameters(draws=3))
    assert design.times.tolist() == [0.9]
    assert design.score == pytest.approx(1 - 1 / (1 + 0.81 * w2 / s2), rel=1e-5)
    assert design.description.startswith(f"expected to remove {design.score:.0%} of the variance its parameters have")
    target = SubjectParameters(draws=3, criterion=Determinant())
    design = design_subject(pop, grid, 1, initial_states=[2.0], target=target)
    assert design.times.tolist() == [0.9]
    assert design.score == pytest.approx(0.5 * math.log1p(0.81 * w2 / s2), rel=1e-5)
    assert design.description == f"expected information about its parameters {design.score:.3g} nats"
    with pytest.raises(tms.InputError, match="ExpectedError"):
        SubjectParameters(criterion="D")


def driven_slope(t, y, u, theta):  # dy/dt = c u(t)
    return theta[0] * u


def test_design_under_the_subject_s_input_profile_is_the_brute_force_best_time():
    """dy/dt = c u(t) with u = 1 on [0, 0.5) and -1 after: the sensitivity of y(t) to c is U(t) = min(t, 1 - t),
    largest at 0.5 (0.5; at 0.9, 0.1), so one sample there removes 1 - 1 / (1 + 0.25 omega^2 / s^2) of the
    parameter's variance; without the profile (dy/dt = c) the last time won (the test above). A system with inputs
    without a profile, or a profile of two experiments, is refused."""
    from torchmisspec.population.design import SubjectParameters, design_subject

    driven = tms.MisspecifiedSystem(
        driven_slope, 1, num_controls=1, time_dependent=True, parameters={"c": (1.0, 0.5)}, state_names=["y"]
    )
    population = Population(["c"], distribution=Normal())
    g = torch.Generator().manual_seed(8)
    profile = tms.Controls(torch.tensor([0.0, 0.5], dtype=DT), torch.tensor([[[1.0], [-1.0]]], dtype=DT))
    times = torch.linspace(0, 1, 6, dtype=DT)
    thetas = 1.0 + 0.3 * torch.randn(20, generator=g, dtype=DT)
    states = 2.0 + thetas[:, None, None] * torch.minimum(times, 1 - times)[None, :, None]
    states[:, 1:] += 0.1 * torch.randn(states[:, 1:].shape, generator=g, dtype=DT)
    data = tms.Trajectories(times, states, state_names=["y"], controls=profile.repeat(20))
    fit = fit_nlme(driven, data, population, Additive())
    pop = _classical(fit, driven, population)
    grid = torch.tensor([0.0, 0.2, 0.5, 0.7, 0.9], dtype=DT)
    s2, w2 = float(fit.modes.scale[0]) ** 2, float(fit.values.spread[0]) ** 2
    design = design_subject(pop, grid, 1, initial_states=[2.0], target=SubjectParameters(draws=3), controls=profile)
    assert design.times.tolist() == [0.5]
    assert design.score == pytest.approx(1 - 1 / (1 + 0.25 * w2 / s2), rel=1e-5)
    with pytest.raises(tms.InputError, match="expected the subject's input profile"):
        design_subject(pop, grid, 1, initial_states=[2.0])
    with pytest.raises(tms.InputError, match="got 2 profiles"):
        design_subject(pop, grid, 1, initial_states=[2.0], controls=profile[[0, 0]])


def test_design_greedy_matches_brute_force_on_a_tiny_problem():
    """Two varying parameters (a rate and a volume), the information in units of the spread (prior the identity):
    the greedy pair's expected log-determinant is within (1 - 1/e) of the best pair's, found by trying them all, and
    equal to it here; under the expected error, its first pick is the best single time, and its score that of the
    pair it returns (the fraction of the prior's variance removed)."""
    import itertools

    from torchmisspec.population.design import Determinant, ExpectedError, _greedy_parameters

    g = torch.Generator().manual_seed(9)
    J = torch.randn(4, 6, 1, 2, generator=g, dtype=DT)
    weights = torch.tensor([4.0], dtype=DT)
    allowed = torch.ones(6, dtype=torch.bool)

    def info(times):
        return torch.eye(2, dtype=DT) + sum(torch.einsum("soa,o,sob->sab", J[:, t], weights, J[:, t]) for t in times)

    chosen, score = _greedy_parameters(J, weights, Determinant(), 2, allowed)

    def value(pair):
        return 0.5 * float(torch.linalg.slogdet(info(pair)).logabsdet.mean())

    best = max(itertools.combinations(range(6), 2), key=value)
    assert score == pytest.approx(value(chosen), rel=1e-10)
    assert score >= (1 - 1 / math.e) * value(best)

    def removed(times):
        return 1 - float(torch.linalg.inv(info(times)).diagonal(dim1=-2, dim2=-1).sum(-1).mean()) / 2

    chosen, score = _greedy_parameters(J, weights, ExpectedError(), 2, allowed)
    assert score == pytest.approx(removed(chosen), rel=1e-10)
    first, _ = _greedy_parameters(J, weights, ExpectedError(), 1, allowed)
    assert first == [max(range(6), key=lambda t: removed([t]))]
    assert score <= max(removed(pair) for pair in itertools.combinations(range(6), 2)) + 1e-12


def test_design_with_f_error_is_the_brute_force_sandwich():
    """F's draws moving what is measured: the expected error covariance is M^-1 + M^-1 B M^-1, B the covariance over
    draws of sum_t J_t^T W_t dz_t (written out here draw by draw); the greedy first pick is the brute-force best
    single time under it, its score that time's, and a time whose draws scatter widely loses to one with the same
    sensitivity whose draws agree (without the draws, the first of the two would win the tie)."""
    from torchmisspec.population.design import ExpectedError, _greedy_parameters

    g = torch.Generator().manual_seed(11)
    S, F, T = 3, 6, 5
    J = torch.randn(S, T, 1, 2, generator=g, dtype=DT)
    dz = 0.5 * torch.randn(S, F, T, 1, generator=g, dtype=DT)
    weights = torch.tensor([4.0], dtype=DT)
    allowed = torch.ones(T, dtype=torch.bool)

    def error(t):
        total = 0.0
        for s in range(S):
            Mi = torch.linalg.inv(torch.eye(2, dtype=DT) + 4.0 * torch.outer(J[s, t, 0], J[s, t, 0]))
            pushes = [4.0 * J[s, t, 0] * dz[s, f, t, 0] for f in range(F)]
            B = sum(torch.outer(v, v) for v in pushes) / F
            total += float(torch.trace(Mi + Mi @ B @ Mi))
        return total / S

    first, score = _greedy_parameters(J, weights, ExpectedError(), 1, allowed, dz)
    assert first == [min(range(T), key=error)]
    assert score == pytest.approx(1 - error(first[0]) / 2, rel=1e-10)
    J[:, 1] = J[:, 0]  # times 0 and 1 alike, but F's draws scatter at 0 and agree at 1
    dz[:, :, 0], dz[:, :, 1] = 3.0 * torch.randn(S, F, 1, generator=g, dtype=DT), 0.0
    only = torch.zeros(T, dtype=torch.bool)
    only[:2] = True
    assert _greedy_parameters(J, weights, ExpectedError(), 1, only)[0] == [0]
    assert _greedy_parameters(J, weights, ExpectedError(), 1, only, dz)[0] == [1]


def test_design_refuses_a_budget_beyond_the_candidates():
    from torchmisspec.population.design import design_subject

    fit, _, _ = _linear_fit(K=6, seed=10)
    pop = _classical(fit, linear_system(), Population(["c"], distribution=Normal()))
    with pytest.raises(tms.InputError, match="at most the 2 candidate times"):
        design_subject(pop, [0.0, 0.5, 1.0], 3, initial_states=[2.0])


# ---- covariates read from a lab's table ------------------------------------------------------------------------------
def test_covariates_read_one_value_per_experiment_in_the_loaders_order(tmp_path):
    from torchmisspec.data import experiment_labels, read_covariates

    path = tmp_path / "lab.csv"
    path.write_text("subject,time,y,weight\n10,0,1,70\n2,0,1,55\n2,1,2,55\n10,1,2,\n")
    assert experiment_labels(path, "subject") == ["2", "10"]
    values = read_covariates(path, ["weight"], experiment_column="subject")
    torch.testing.assert_close(values["weight"], torch.tensor([55.0, 70.0], dtype=DT))
    path.write_text("subject,time,y,weight\n1,0,1,70\n1,1,2,71\n")
    with pytest.raises(tms.InputError, match="one value of covariate 'weight' per experiment"):
        read_covariates(path, ["weight"], experiment_column="subject")
    with pytest.raises(tms.InputError, match="expected covariate column"):
        read_covariates(path, ["age"], experiment_column="subject")
    path.write_text("subject,time,y,weight\n1,0,1,heavy\n")
    with pytest.raises(tms.InputError, match="finite number"):
        read_covariates(path, ["weight"], experiment_column="subject")


def test_design_for_the_correction_is_refused_without_one():
    from torchmisspec.population.design import Correction, design_subject

    fit, _, _ = _linear_fit(K=6, seed=11)
    pop = _classical(fit, linear_system(), Population(["c"], distribution=Normal()))
    with pytest.raises(tms.InputError, match="kept F = 0"):
        design_subject(pop, [0.0, 0.5, 1.0], 1, initial_states=[2.0], target=Correction())
    with pytest.raises(tms.InputError, match="SubjectParameters"):
        design_subject(pop, [0.0, 0.5, 1.0], 1, initial_states=[2.0], target="parameters")


def test_fit_population_refuses_one_experiment_and_a_bad_declaration():
    from torchmisspec.population import fit_population

    _, data, _ = _linear_fit(K=3, seed=12)
    with pytest.raises(tms.InputError, match="at least 2 experiments"):
        fit_population(data[[0]], linear_system(), Population(["c"]), progress=False)
    with pytest.raises(tms.InputError, match="Population"):
        fit_population(data, linear_system(), ["c"], progress=False)


def test_the_integrated_system_gives_each_experiment_its_own_parameters_and_the_population_as_prior():
    from torchmisspec.population._integrated import integrated_modes, integrated_system, with_experiment_index

    system = tms.MisspecifiedSystem(two_parameter, 2, parameters={"ka": (1.0, 0.5), "V": (0.5, 0.2)})
    thetas = torch.tensor([[0.8, 0.4], [1.5, 0.6], [1.1, 0.5], [0.9, 0.45]], dtype=DT)
    y0 = torch.tensor([[4.0, 0.0], [3.0, 0.0], [5.0, 0.0], [4.5, 0.0]], dtype=DT)
    times = torch.linspace(0, 5, 8, dtype=DT)
    base = tms.Trajectories(times, y0[:, None].expand(4, 8, 2).clone())
    ctrl = with_subject_inputs(base, thetas, ["ka", "V"]).controls
    states = tms.simulate(subject_system(system, [0, 1], system.theta), y0, times, controls=ctrl).states
    data = tms.Trajectories(times, states, state_names=["gut", "conc"])
    fit = fit_nlme(system, data, Population(["ka", "V"]), Additive())
    joint = integrated_system(system, fit)
    typical = fit.values.typical(fit.covariates)
    torch.testing.assert_close(joint.parameters.mean.reshape(4, 2), typical)  # each prior: the population's
    assert torch.allclose(joint.parameters.scale.reshape(4, 2), fit.values.spread.clamp_min(1e-3).expand(4, 2))
    eta = torch.log(thetas).reshape(-1)  # log-normal: eta = log(theta)
    indexed = with_experiment_index(data, system)
    y = torch.rand(4, 2, generator=torch.Generator().manual_seed(1), dtype=DT)
    u = indexed.controls.values[:, 0]  # (K, 1): each experiment's index
    got = joint.at(eta).known_rhs(y, torch.zeros(4, dtype=DT), u)
    want = torch.stack([system.at(thetas[i]).known_rhs(y[i : i + 1])[0] for i in range(4)])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)

    class Posterior:  # what integrated_modes reads from a fit on the integrated system
        mean = eta

    class Fitted:
        parameters_ = Posterior()

    modes = integrated_modes(Fitted(), fit)
    torch.testing.assert_close(fit.layout.theta(modes.eta, modes.shared), thetas)


def _sloped_population(missing: bool, K=8, seed=0):
    """dy/dt = c_i (+ F(y) = -0.8 y where ``missing``): every experiment its own c ~ N(1, 0.3^2), 13 times."""
    g = torch.Generator().manual_seed(seed)
    truth = tms.MisspecifiedSystem(
        slope, 1, parameters={"c": (1.0, 0.5)}, state_names=["y"], correction=(lambda y: -0.8 * y) if missing else None
    )
    thetas = 1.0 + 0.3 * torch.randn(K, 1, generator=g, dtype=DT)
    times = torch.linspace(0, 3, 13, dtype=DT)
    y0 = 0.5 + 2 * torch.rand(K, 1, generator=g, dtype=DT)
    base = tms.Trajectories(times, y0[:, None].expand(K, 13, 1).clone(), state_names=["y"])
    controls = with_subject_inputs(base, thetas, ["c"]).controls
    states = tms.simulate(subject_system(truth, [0], truth.theta), y0, times, controls=controls).states.clone()
    states[:, 1:] += 0.02 * torch.randn(K, 12, 1, generator=g, dtype=DT)
    return tms.Trajectories(times, states, state_names=["y"])


def test_a_missing_term_every_experiment_shares_is_learned_and_none_is_refused():
    from torchmisspec.population import fit_population

    population = Population(["c"], distribution=Normal())
    fit = fit_population(_sloped_population(True), linear_system(), population, noise="additive", progress=False)
    assert not fit.known_model
    x = torch.tensor([[0.5], [3.0]], dtype=DT)  # F = -0.8 y up to a constant, which the typical c takes
    f = fit.gp.predict_mean(x).flatten()
    assert -1.2 < float(f[1] - f[0]) / 2.5 < -0.5
    # F's own uncertainty is counted in the typical value's standard error (_f_uncertainty)
    plain = standard_errors(fit.nlme.values, fit.nlme.modes, fit.nlme.covariates)
    assert fit.nlme.shifts is not None and float(fit.nlme.standard_errors[0][0]) > float(plain[0][0])
    # the next subject's design counts F's draws: none at its start, more the longer F acts, and a larger error
    from torchmisspec.population.design import F_DRAWS, _correction_deviations, design_subject

    grid, eta = torch.linspace(0, 3, 7, dtype=DT), fit.nlme.values.mean.expand(4, 1)
    moved = _correction_deviations(fit, torch.tensor([1.0], dtype=DT), grid, eta, torch.Generator().manual_seed(0))
    assert moved.shape == (4, F_DRAWS, 7, 1) and float(moved[:, :, 0].abs().max()) == 0.0
    spread = moved.std(1).mean(0)[:, 0]
    assert float(spread[-1]) > float(spread[1]) > 0
    design = design_subject(fit, grid, 2, initial_states=[1.0], generator=torch.Generator().manual_seed(1))
    assert 0 < design.score < 1 and design.times.numel() == 2
    from torchmisspec.population.design import Correction

    for_f = design_subject(fit, grid, 6, initial_states=[1.0], target=Correction())
    assert for_f.times.tolist() == grid[1:].tolist()  # every time but the known start
    with pytest.warns(tms.TorchMisspecWarning, match="not fitted significantly better"):
        none = fit_population(_sloped_population(False), linear_system(), population, noise="additive", progress=False)
    assert none.known_model and none.nlme is none.classical


def test_a_population_learns_f_from_derivatives_in_its_noise_model_s_space(monkeypatch):
    """fit_population's default pipeline estimates dy/dt in the noise model's space (Samples(in_noise_space=True),
    one experiment's default leaves it off); a pipeline given is used as given, its noise model the fit's."""
    from torchmisspec.population import fit as population_fit

    seen = []
    monkeypatch.setattr(population_fit, "_learn", lambda system, data, pop, noise, pipeline, *rest: seen.append(
        pipeline) or [])  # fmt: skip
    population = Population(["c"], distribution=Normal())
    with pytest.warns(tms.TorchMisspecWarning, match="returning the classical answer"):
        population_fit.fit_population(_sloped_population(True), linear_system(), population, noise="additive",
                                      progress=False)  # fmt: skip
        given = tms.Pipeline(samples=tms.learning.Samples(derivative="central"))
        population_fit.fit_population(_sloped_population(True), linear_system(), population, pipeline=given,
                                      noise="additive", progress=False)  # fmt: skip
    assert seen[0].samples.in_noise_space and not tms.Pipeline().samples.in_noise_space
    assert not seen[1].samples.in_noise_space and seen[1].samples.derivative == "central"
    assert seen[1].noise == tms.noise.Additive()


def test_the_integrated_fit_s_f_is_a_candidate_where_f_s_own_fit_keeps_none(monkeypatch):
    """Where F's own fit at fixed parameters keeps F = 0, the F of the fit that learns every experiment's parameters
    with it is still offered, and do no harm keeps it on data with a shared missing term."""
    from types import SimpleNamespace

    from torchmisspec.population import fit as fit_module

    real, seen = fit_module._without_warnings, []

    def own_fit_keeps_none(fit, data, system, **kwargs):
        seen.append(system.parameters is not None)
        if system.parameters is not None:  # the integrated system: every experiment's parameters uncertain
            return real(fit, data, system, **kwargs)
        return SimpleNamespace(known_model_=True)

    monkeypatch.setattr(fit_module, "_without_warnings", own_fit_keeps_none)
    population = Population(["c"], distribution=Normal())
    fit = fit_module.fit_population(
        _sloped_population(True), linear_system(), population, noise="additive", progress=False
    )
    assert seen == [True, False]
    assert not fit.known_model and fit.gp.parameters_ is not None  # the integrated fit's F, its etas recorded
    with_f, without = fit.held_out  # what do no harm compared, in the summary
    assert with_f < without and f"misfit {with_f:.3g} with F conditioned without them, {without:.3g}" in fit.summary()
    x = torch.tensor([[0.5], [3.0]], dtype=DT)
    f = fit.gp.predict_mean(x).flatten()
    assert -1.2 < float(f[1] - f[0]) / 2.5 < -0.5
    # F's own uncertainty is counted in the typical value's standard error (_f_uncertainty)
    plain = standard_errors(fit.nlme.values, fit.nlme.modes, fit.nlme.covariates)
    assert fit.nlme.shifts is not None and float(fit.nlme.standard_errors[0][0]) > float(plain[0][0])
    # where that widens an interval more than WIDENED times, the summary says why, and gives the interval without it
    for widened, said in ((1.0, True), (1e9, False)):
        monkeypatch.setattr(fit_module, "WIDENED", widened)
        lo, hi = (float(v) for v in dataclasses.replace(fit.nlme, shifts=None).intervals(0.95).mean[0])
        line = "the typical values' intervals count F's own uncertainty"
        assert (line in fit.summary()) is said and (f"without it: c [{lo:.4g}, {hi:.4g}]" in fit.summary()) is said


def test_the_population_is_refitted_under_the_integrated_f_only_where_it_helps_held_out_experiments(monkeypatch):
    """The integrated start's F is judged on held-out experiments first (do no harm's rule): refused there, the
    population is never refitted under it (on nlme's Remifentanil that EM took a minute a round for an F refused in
    the end), the rounds' F follows, and the summary says a refused misfit in words, not as inf."""
    from torchmisspec.population import fit as fit_module

    real_judge, real_mean = fit_module.best_on_unseen_experiments, fit_module.mean_correction
    judged, corrected = [], []

    def judge(fits, classical, data):
        judged.append([getattr(f.gp, "parameters_", None) is not None for f in fits])
        if len(judged) == 1:  # the integrated start's F, before its EM: refused, its folds stopped early
            return fits[0], False, math.inf, 10.0
        return real_judge(fits, classical, data)

    def mean(system, gp):
        corrected.append(getattr(gp, "parameters_", None) is not None)
        return real_mean(system, gp)

    monkeypatch.setattr(fit_module, "best_on_unseen_experiments", judge)
    monkeypatch.setattr(fit_module, "mean_correction", mean)
    population = Population(["c"], distribution=Normal())
    fit = fit_module.fit_population(
        _sloped_population(True), linear_system(), population, noise="additive", progress=False
    )
    assert judged[0] == [True]  # the integrated F alone, before any EM under it
    assert corrected and not any(corrected)  # no EM under it: only the rounds' F
    assert all(not any(j) for j in judged[1:])  # and it is no candidate at the end
    assert fit.gp is None or getattr(fit.gp, "parameters_", None) is None
    assert fit_module._misfits(math.inf, 10.0) == (
        "misfit above 10 (its folds stopped once past it) with F conditioned without them, 10 with F = 0"
    )


def test_a_subject_s_paths_below_zero_are_named_where_its_measurements_are_positive():
    """Drawn paths below 0 of a state measured positive (relative or count noise) are said, with how many and from
    when; under additive noise (a state that may cross 0) nothing is said."""
    from types import SimpleNamespace

    from torchmisspec.noise import Relative
    from torchmisspec.population.predict import warn_below_zero

    times = torch.tensor([0.0, 1.0, 2.0], dtype=DT)
    samples = torch.tensor([[1.0, 0.5, 0.1], [1.0, 0.2, -0.1], [1.0, 0.3, float("nan")]], dtype=DT)[:, None, :, None]
    fit = SimpleNamespace(noise=Relative(), system=SimpleNamespace(state_names=["conc"]))
    with pytest.warns(tms.TorchMisspecWarning, match=r"noise 'relative'\): conc in 1 of 3 from t = 2\."):
        warn_below_zero(fit, times, samples)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_below_zero(SimpleNamespace(noise=Additive(), system=fit.system), times, samples)
        warn_below_zero(fit, times, samples.abs())


def test_a_mean_path_outside_its_drawn_paths_is_named():
    """The path at F's mean below 39 of 40 drawn paths (more than 97.5 %) is outside their central 95 %: said, with
    the state and the first such time; inside them, or where every path is at it to the solver's precision (the
    subject's own first state), nothing is said."""
    from types import SimpleNamespace

    from torchmisspec.population.predict import warn_mean_outside

    times = torch.tensor([0.0, 1.0, 2.0], dtype=DT)
    fit = SimpleNamespace(system=SimpleNamespace(state_names=["conc"]))
    mean = torch.tensor([[[1.0], [0.5], [0.2]]], dtype=DT)
    held = torch.tensor([1.0, 0.6, 1.5], dtype=DT)[None, None, :, None] + torch.linspace(0, 0.1, 40, dtype=DT)[
        :, None, None, None
    ]  # fmt: skip
    held[:, 0, 0] = torch.linspace(0.9, 1.1, 40, dtype=DT)[:, None]  # around the mean at the start
    with pytest.warns(
        tms.TorchMisspecWarning, match=r"outside the central 95 % of its paths drawn with F \(conc from t = 1\)"
    ):
        warn_mean_outside(fit, times, mean, held)
    with pytest.warns(tms.TorchMisspecWarning, match=r"paths drawn over its parameters under F's mean \(conc from"):
        warn_mean_outside(fit, times, mean, held, with_f=False)  # a calibration that chose F's mean
    around = mean[None] + torch.linspace(-0.1, 0.1, 40, dtype=DT)[:, None, None, None]
    around[:, 0, 0] = mean[0, 0] * (1 + 1e-9)  # every path at the mean (the subject's own first state): not outside
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_mean_outside(fit, times, mean, around)


def test_a_candidate_s_folds_stop_once_past_the_classical_total(monkeypatch):
    """A candidate whose folds so far miss by more than the classical answer's total cannot be kept: each is given
    that total (or a better candidate's, if lower) as where to stop."""
    from types import SimpleNamespace

    from torchmisspec.population import _held_out

    K = 6
    classical = SimpleNamespace(
        modes=SimpleNamespace(scale=torch.ones(1, dtype=DT), initial_states=None), layout=None, thetas=None
    )
    known = torch.full((K,), 10.0, dtype=DT)
    totals, stops = {"worse": known * 1.2, "better": known * 0.5}, []

    def scores(fit, trajectories, scale, stop=math.inf):
        stops.append(stop)
        return totals[fit.name]

    monkeypatch.setattr(_held_out, "_scores", lambda *args: known)
    monkeypatch.setattr(_held_out, "_held_out_scores", scores)
    data = linear_data(torch.ones(K, dtype=DT), torch.linspace(0, 1, 4, dtype=DT), torch.Generator())
    fits = [SimpleNamespace(name=n, noise=Additive()) for n in ("worse", "better", "worse")]
    _held_out.best_on_unseen_experiments(fits, classical, data)
    assert stops == [60.0, 60.0, 30.0]


def test_the_candidate_kept_is_the_one_that_fits_held_out_experiments_best(monkeypatch):
    """Of several candidates the lowest held-out misfit is chosen, and the rule against F = 0 judges that one."""
    from types import SimpleNamespace

    from torchmisspec.population import _held_out

    K = 6
    classical = SimpleNamespace(
        modes=SimpleNamespace(scale=torch.ones(1, dtype=DT), initial_states=None), layout=None, thetas=None
    )
    known = torch.full((K,), 10.0, dtype=DT)
    rivals = {
        "worse": known * 1.2,
        "better": known * 0.5,
        "close": known * torch.tensor([0.9, 1.1, 0.95, 1.05, 1.0, 0.98], dtype=DT),
    }
    monkeypatch.setattr(_held_out, "_scores", lambda *args: known)
    monkeypatch.setattr(_held_out, "_held_out_scores", lambda fit, *args: rivals[fit.name])
    fits = [SimpleNamespace(name=n, noise=Additive()) for n in rivals]
    data = linear_data(torch.ones(K, dtype=DT), torch.linspace(0, 1, 4, dtype=DT), torch.Generator())
    best, kept, with_f, without = _held_out.best_on_unseen_experiments(fits, classical, data)
    assert best.name == "better" and kept and with_f == pytest.approx(30.0) and without == pytest.approx(60.0)
    best, kept, _, _ = _held_out.best_on_unseen_experiments(fits[::2], classical, data)
    assert best.name == "close" and not kept  # 0.3 % lower in all, mixed by experiment


def test_the_population_residuals_are_solved_once_for_every_design_and_new_subject(monkeypatch):
    """The residual scale by time (the design's weights, a new subject's) comes from one solve of the population's
    experiments, kept on the fit: a second design and a new subject's fit do not solve them again, and the scale is
    the same."""
    from torchmisspec.population import _misfit
    from torchmisspec.population.design import design_subject, misfit_scale
    from torchmisspec.population.predict import subject_parameters

    fit, data, _ = _linear_fit(K=6, seed=11)
    pop = dataclasses.replace(_classical(fit, linear_system(), Population(["c"], distribution=Normal())), data=data)
    calls = [0]
    real = _misfit._paths

    def counted(*args, **kwargs):
        calls[0] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(_misfit, "_paths", counted)
    grid = torch.tensor([0.0, 0.5, 1.0], dtype=DT)
    first = misfit_scale(pop, grid)
    design_subject(pop, grid, 1, initial_states=[2.0])
    subject_parameters(pop, data[0], torch.zeros(1, 0, dtype=DT))
    assert calls[0] == 1
    torch.testing.assert_close(misfit_scale(pop, grid), first)


def test_a_subject_s_diverging_f_draws_are_named_in_its_terms():
    """The solver's warning names the rows it integrates "initial conditions"; a new subject's rows are parameter
    draws: one warning in those terms instead, counting the draws that left."""
    import warnings
    from types import SimpleNamespace

    from torchmisspec.population.predict import F_DRAWS, _with_f_draws

    S, T = 3, 5
    samples = torch.zeros(F_DRAWS, S, T, 1, dtype=DT)
    samples[1, 2, 3:] = math.nan  # one draw of F under the third parameter draw left the region

    def posterior(y0, times, **kwargs):
        tms_warn = tms.TorchMisspecWarning("CorrectedODE.posterior: 1 of 12 sampled paths left the region (...)")
        warnings.warn(tms_warn, stacklevel=1)
        return SimpleNamespace(samples=samples)

    fit = SimpleNamespace(corrected=SimpleNamespace(posterior=posterior))
    y0 = torch.zeros(S, 1, dtype=DT)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = _with_f_draws(fit, y0, torch.linspace(0, 1, T, dtype=DT), None, None)
    messages = [str(w.message) for w in caught]
    assert out.shape == (F_DRAWS * S, 1, T, 1) and int(out.isnan().any(-1).any(-1).sum()) == 1
    assert len(messages) == 1 and messages[0].startswith(
        "predict_subject: 1 of 12 draws of the subject's path (3 draws"
    )


def test_the_population_s_moves_under_shifted_data_are_a_refit_s():
    """F's uncertainty in the population's values (``_f_uncertainty``): where every experiment's measurements move
    by ``eps_i t`` (what a slope error does), the linear model's modes move by the same amount less their pull to
    the typical value, and EM's fixed point carries it whole into the typical value. The first-order move of the
    typical value is a refit's on the moved data (brute force), and a common shift moves
    the typical value by exactly itself."""
    from torchmisspec.population._f_uncertainty import population_moves

    fit, data, _ = _linear_fit(K=8)
    g = torch.Generator().manual_seed(5)
    K, times = data.num_experiments, data.time_grid
    eps = torch.stack([torch.full((K,), 0.02, dtype=DT), 0.03 * torch.randn(K, generator=g, dtype=DT)])  # (F, K)
    deviations = (eps[:, :, None] * times)[..., None]  # (F, K, T, 1): the first row is given, not a residual
    moves = population_moves(fit, linear_system(), data, Additive(), deviations)
    assert moves.fixed[0].shape == (2, 1)
    assert float(moves.fixed[0][0, 0]) == pytest.approx(0.02, rel=1e-6)
    for f in range(2):
        moved = dataclasses.replace(data, states=data.states + deviations[f])
        refit = fit_nlme(linear_system(), moved, Population(["c"], distribution=Normal()), Additive(), start=fit)
        change = float(refit.values.mean[0] - fit.values.mean[0])
        assert float(moves.fixed[0][f, 0]) == pytest.approx(change, rel=2e-2, abs=1e-4)


def test_f_s_uncertainty_widens_the_population_s_standard_errors_and_intervals():
    """With the draws' moves counted, a typical value's variance is the Fisher information's plus theirs, and its
    interval wider; the spread's is the information's (``uncertainty``'s notes)."""
    from torchmisspec.population._f_uncertainty import Shifts

    fit, _, _ = _linear_fit(K=8)
    g = torch.Generator().manual_seed(1)
    shifts = Shifts([0.05 * torch.randn(64, 1, generator=g, dtype=DT)])
    plain, counted = fit.standard_errors, fit.with_shifts(shifts).standard_errors
    extra = float(shifts.fixed[0].var())
    assert float(counted[0][0]) ** 2 == pytest.approx(float(plain[0][0]) ** 2 + extra, rel=1e-9)
    assert float(counted[1][0]) == float(plain[1][0])
    narrow, wide = fit.intervals(0.95), fit.with_shifts(shifts).intervals(0.95)
    assert float(wide.mean[0, 0]) < float(narrow.mean[0, 0]) and float(wide.mean[0, 1]) > float(narrow.mean[0, 1])
    assert wide.spread.tolist() == narrow.spread.tolist()
    assert fit.with_shifts(None) is fit


def test_many_new_subjects_at_once_match_the_closed_form_posterior_of_each():
    """``subjects_parameters`` fits several new subjects in one batch, each measured at its own times: on the linear
    model each is the conjugate normal posterior of c, the prior the population's, each sample weighed by the
    population's misfit scale at that subject's own times (computed here from ``misfit_scale`` per subject), and
    equal to its own ``subject_parameters``: the subjects do not interact."""
    from torchmisspec.population.design import misfit_scale
    from torchmisspec.population.predict import subject_parameters, subjects_parameters

    fit, data, _ = _linear_fit(K=8, seed=12)
    pop = dataclasses.replace(_classical(fit, linear_system(), Population(["c"], distribution=Normal())), data=data)
    t, y = data.times, data.states[0, :, 0]
    picks = torch.tensor([[0, 1, 2], [0, 3, 5], [0, 1, 5], [0, 4, 5]])
    measured = tms.Trajectories(t[picks], y[picks][..., None], state_names=["y"])
    X = torch.zeros(1, 0, dtype=DT)
    eta, cov, y0 = subjects_parameters(pop, measured, X)
    assert eta.shape == (4, 1) and cov.shape == (4, 1, 1) and y0.shape == (4, 1)
    mu, omega = float(fit.values.typical(X)[0, 0]), float(fit.values.spread[0])
    for k, idx in enumerate(picks):
        tk, yk = t[idx][1:], y[idx][1:] - 2.0
        w = misfit_scale(pop, t[idx])[1:, 0].pow(-2)
        precision = 1 / omega**2 + (w * tk**2).sum()
        mean = (mu / omega**2 + (w * tk * yk).sum()) / precision
        torch.testing.assert_close(eta[k, 0], mean, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(cov[k, 0, 0], 1 / precision, rtol=1e-4, atol=1e-9)
        one = subject_parameters(pop, measured[k], X)
        torch.testing.assert_close(eta[k], one[0], rtol=1e-5, atol=1e-7)
    with pytest.raises(tms.InputError, match="measured: expected Trajectories"):
        subjects_parameters(pop, y, X)


def test_a_subject_s_paths_beyond_f_s_training_range_are_named():
    """A new subject's drawn paths that leave the states F was learned on (its training inputs) get one warning
    naming the state, the first time more than 5 % of the draws are outside, and F's range; draws inside it, or a
    share at 5 %, get none; a control F reads is not checked."""
    import warnings
    from types import SimpleNamespace

    from torchmisspec.population.predict import warn_beyond_f

    system = SimpleNamespace(correction_inputs=(1, 2), state_names=("gut", "conc"))
    X = torch.tensor([[0.5, 0.0], [4.0, 9.0]], dtype=DT)  # F learned on conc 0.5-4 (and a control 0-9)
    fit = SimpleNamespace(corrected=SimpleNamespace(system=system), gp=SimpleNamespace(train_inputs_=X))
    times = torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=DT)
    samples = torch.full((40, 1, 4, 2), 2.0, dtype=DT)
    samples[:2, 0, 2:, 1] = 0.01  # 2 of 40 draws (5 %) below from t = 2: not more than 5 %
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_beyond_f(fit, times, samples)
    samples[2, 0, 3, 1] = float("nan")  # a draw that left the region counts as not seen
    samples[3:6, 0, 3, 1] = 1e-300
    with pytest.warns(tms.TorchMisspecWarning, match=r"conc from t = 3 \(F learned on 0.5 to 4\)") as record:
        warn_beyond_f(fit, times, samples)
    assert len(record) == 1 and "gut" not in str(record[0].message)
