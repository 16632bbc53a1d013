"""Issue 41, the classical answer inside the package: the known model alone (F = 0) fitted through the ODE to what was
measured (torchmisspec.learning.refinement._known_fit), checked against scipy's least squares on the same objective, and
the held-out later times on which partly measured data keep a correction only when it forecasts them better."""

import math
import warnings

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.refinement._known_fit import fit_known_model, forecast_check, forecast_score, time_split
from torchmisspec.noise import Additive, Relative

DT = torch.float64
TRUE = (0.8, 0.3)  # infection-like conversion rate and loss rate of a two-state chain


def chain(y, theta):
    """dA/dt = -a A, dB/dt = a A - b B: A not measured, B measured."""
    a, b = theta[0], theta[1]
    return torch.stack([-a * y[..., 0], a * y[..., 0] - b * y[..., 1]], dim=-1)


def _system(scale=(0.5, 0.5)):
    return tms.MisspecifiedSystem(
        chain, 2, name="chain", state_names=["A", "B"], parameters={"a": (0.5, scale[0]), "b": (0.5, scale[1])}
    )


def _data(noise=0.0, multiplicative=False, seed=0, a0=4.0, n=16):
    truth = tms.MisspecifiedSystem(lambda y: chain(y, torch.tensor(TRUE, dtype=y.dtype)), 2, name="truth")
    times = torch.linspace(0.0, 8.0, n, dtype=DT)
    clean = tms.simulate(truth, torch.tensor([[a0, 0.1]], dtype=DT), times).states
    g = torch.Generator().manual_seed(seed)
    eps = torch.randn(clean.shape, generator=g, dtype=DT)
    noisy = clean * torch.exp(noise * eps) if multiplicative else clean + noise * eps
    noisy[:, 1:, 0] = math.nan  # A given at t = 0 only (the dose), B measured throughout
    noisy[:, 0, 0] = math.nan  # ... or not at all: its initial value is then fitted
    return tms.Trajectories(times, noisy, state_names=["A", "B"])


def _scipy_fit(data, transform):
    """The same fit by scipy: theta and A(0) by least squares on transform(B), tight solves, no prior."""
    from scipy.optimize import least_squares

    times, y = data.experiments()[0]
    b = y[:, 1].numpy()

    def residuals(x):
        sim = tms.simulate(_system().at(torch.tensor(x[:2])), torch.tensor([[x[2], b[0]]]), times).states[0]
        return transform(sim[:, 1].numpy()) - transform(b)

    return least_squares(residuals, np.array([0.5, 0.5, 2.0]), x_scale=1.0, xtol=1e-12, ftol=1e-12).x


def _fit(data, noise, scale=(50.0, 50.0)):
    start = data.initial_conditions.clone()
    start[:, 0] = 2.0
    free = torch.tensor([[True, False]])
    return fit_known_model(_system(scale), data.with_initial_states(start), free, noise)


@pytest.mark.parametrize("noise, transform", [(Additive(), lambda v: v), (Relative(), np.log)])
def test_the_known_models_fit_matches_scipy_least_squares(noise, transform):
    """An unmeasured initial state and two parameters, noisy data, a prior 100 times wider than the estimates (its
    penalty negligible): the same minimum as scipy's least squares on the noise model's residuals."""
    data = _data(noise=0.05, multiplicative=isinstance(noise, Relative))
    fit = _fit(data, noise)
    a, b, a0 = _scipy_fit(data, transform)
    assert fit.theta.tolist() == pytest.approx([a, b], rel=2e-3)
    assert float(fit.initial_states[0, 0]) == pytest.approx(a0, rel=2e-3)
    assert float(fit.initial_states[0, 1]) == float(data.initial_conditions[0, 1])  # given: kept
    assert fit.covariance.shape == (2, 2) and bool((fit.covariance.diagonal() > 0).all())
    # the initial state's uncertainty widens theta's (marginalised, not held fixed)
    assert bool((fit.covariance.diagonal() >= fit.fixed.diagonal() * (1 - 1e-9)).all())
    assert math.isnan(float(fit.scale[0])) and float(fit.scale[1]) > 0  # A is never measured


def test_exact_data_give_the_truth():
    """Noiseless data from the truth: the fit lands on it (theta and the unmeasured initial state)."""
    data = _data()
    fit = _fit(data, Additive())
    assert fit.theta.tolist() == pytest.approx(list(TRUE), rel=1e-4)
    assert float(fit.initial_states[0, 0]) == pytest.approx(4.0, rel=1e-4)


def test_the_time_split_keeps_two_thirds_of_each_long_enough_experiment():
    data = _data(n=9)
    early, keep = time_split(data)
    assert keep.tolist() == [6] and early.lengths == (6,)
    assert time_split(_data(n=5)) is None  # too short to hold anything out


def test_the_forecast_score_is_zero_for_the_truth_and_infinite_when_it_cannot_be_integrated():
    data = _data()
    _, keep = time_split(data)
    truth = _system().at(torch.tensor(TRUE, dtype=DT))
    y0 = torch.tensor([[4.0, 0.1]], dtype=DT)
    scale = torch.ones(2, dtype=DT)
    assert forecast_score(truth, truth.known_rhs, data, y0, keep, Additive(), scale) < 1e-8
    wrong = _system().at(torch.tensor([0.5, 0.5], dtype=DT))
    assert forecast_score(wrong, wrong.known_rhs, data, y0, keep, Additive(), scale) > 1e-2

    def blows_up(y, t=None, u=None):
        return y.pow(3)

    assert forecast_score(truth, blows_up, data, 10 * y0, keep, Additive(), scale) == math.inf


def test_partly_measured_data_from_the_known_model_return_it_with_its_parameters_and_initial_state():
    """The chain with A never measured, 5 % multiplicative noise, G exact: the default fit keeps no correction (do no
    harm), and returns the known model with theta and A(0) as its own fit finds them, usable beyond the data."""
    data = _data(noise=0.05, multiplicative=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = tms.fit_correction(data, _system(), progress=False)
    assert gp.known_model_ is True
    assert any("forecasts the last third within its own uncertainty" in str(w.message) for w in caught)
    assert gp.parameters_.mean.tolist() == pytest.approx(list(TRUE), rel=0.1)
    assert float(gp.initial_states_[0, 0]) == pytest.approx(4.0, rel=0.1)
    model = tms.CorrectedODE(_system(), gp)
    times = torch.linspace(0.0, 16.0, 9, dtype=DT)  # twice the data's span
    pred = model.predict(gp.initial_states_, times)
    known = tms.simulate(_system().at(gp.parameters_.mean), gp.initial_states_, times).states
    torch.testing.assert_close(pred, known, rtol=1e-5, atol=1e-7)


def test_a_system_with_its_parameters_fixed_is_fitted_on_data_far_from_one():
    """A system fixed by ``at(theta)`` calls G with theta still: the fit in the data's units (counts in the
    thousands) must call it so too (it raised TypeError inside G's scaled copy)."""
    data = _data(noise=0.02)
    big = tms.Trajectories(data.time_grid, data.states * 1000.0, state_names=["A", "B"])
    fixed = _system().at(torch.tensor(TRUE, dtype=DT))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = tms.fit_correction(big, fixed, progress=False)
    assert float(gp.initial_states_[0, 0]) == pytest.approx(4000.0, rel=0.1)


def test_the_incomplete_beta_function_matches_scipy():
    from scipy.special import betainc as reference
    from scipy.stats import f

    from torchmisspec.learning.refinement._known_fit import betainc, f_survival

    for a in (0.5, 1.0, 2.5, 7.0, 30.0):
        for b in (0.5, 1.0, 3.0, 12.0):
            for x in (1e-4, 0.1, 0.5, 0.9, 0.999):
                assert betainc(a, b, x) == pytest.approx(float(reference(a, b, x)), abs=1e-12)
    assert f_survival(2.0, 3, 7) == pytest.approx(float(f.sf(2.0, 3, 7)), rel=1e-10)


def _check(data, noise=None):
    noise = Additive() if noise is None else noise
    early, keep = time_split(data)
    start = early.initial_conditions.clone()
    start[:, 0] = 2.0
    fit = fit_known_model(_system(), early.with_initial_states(start), torch.tensor([[True, False]]), noise)
    return forecast_check(_system(), fit, data, keep, noise)


def test_the_forecast_check_passes_the_right_model_and_fails_a_wrong_one():
    """Under the known model (20 noise realizations) the p-values are spread as a test's should be (few below 0.05:
    measured 4 of 40 at 0.05 with the F distribution, 11 of 40 with the chi-square that ignores the estimated noise);
    with a constant inflow into B, over a span long enough for A to run out (B then settles at the inflow's level,
    which no (a, b, A(0)) can mimic), the check fails in every realization."""
    p_right = torch.tensor([_check(_data(noise=0.05, seed=seed))[0] for seed in range(20)])
    assert float((p_right < 0.05).double().mean()) <= 0.2 and 0.3 <= float(p_right.mean()) <= 0.7

    def inflow(y):
        return chain(y, torch.tensor(TRUE, dtype=y.dtype)) + torch.tensor([0.0, 0.3], dtype=y.dtype)

    times = torch.linspace(0.0, 16.0, 16, dtype=DT)
    clean = tms.simulate(tms.MisspecifiedSystem(inflow, 2), torch.tensor([[4.0, 0.1]], dtype=DT), times).states
    for seed in range(5):
        noisy = clean + 0.05 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(seed), dtype=DT)
        noisy[:, :, 0] = math.nan
        p_wrong, ratio = _check(tms.Trajectories(times, noisy, state_names=["A", "B"]))
        assert p_wrong < 0.01 and ratio > 3


SYSTEM_FILE = """
import torch
import torchmisspec as tms


def chain(y, theta):
    a, b = theta[0], theta[1]
    return torch.stack([-a * y[..., 0], a * y[..., 0] - b * y[..., 1]], dim=-1)


system = tms.MisspecifiedSystem(
    chain, 2, name="chain", state_names=["A", "B"], parameters={"a": (0.5, 50.0), "b": (0.5, 50.0)}
)
"""


def test_the_cli_says_the_known_model_was_kept_and_why(tmp_path, capsys):
    """A lab's CSV of one partly measured trajectory (A empty, B measured), the system built at the top of its file:
    the CLI keeps the known model, says so in one line, and the warning says how the held-out data tested it."""
    from torchmisspec.cli import main

    data = _data(noise=0.05, multiplicative=True)
    t, y = data.experiments()[0]
    rows = ["hour,A,B"] + [f"{float(ti):g},,{float(yi[1]):.6g}" for ti, yi in zip(t, y, strict=True)]
    (tmp_path / "lab.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (tmp_path / "chain_system.py").write_text(SYSTEM_FILE, encoding="utf-8")
    args = ["fit", "--data", str(tmp_path / "lab.csv"), "--system", f"{tmp_path / 'chain_system.py'}:system"]
    code = main([*args, "--time-column", "hour", "--out", str(tmp_path / "m.pt"), "--quiet"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "kept the known model alone (F = 0, its parameters fitted): the held-out data do not support" in out.out
    assert "forecasts the last third within its own uncertainty" in out.err
    assert "a = " in out.out and "b = " in out.out


@pytest.mark.parametrize("seed", range(6))
def test_the_paired_test_of_gains_is_scipys_one_sided_t_test(seed):
    """significant_gain (cross-validation's warning, and the partly measured rival's test with several experiments)
    is the one-sided paired t test at the 2.5 % level on the log ratios (scipy's ttest_1samp)."""
    from scipy.stats import ttest_1samp

    from torchmisspec.learning.choice.cross_validation import significant_gain

    g = torch.Generator().manual_seed(seed)
    gains = (0.3 * seed / 5 + 0.4 * torch.randn(8, generator=g, dtype=torch.float64)).tolist()
    p = ttest_1samp(gains, 0.0, alternative="greater").pvalue
    if abs(p - 0.025) > 1e-3:  # the Cornish-Fisher quantile is within 1e-3 of the exact one
        assert significant_gain(gains) == (p < 0.025)
    assert significant_gain([*gains[:2], math.inf]) and not significant_gain([1.0]) and not significant_gain([])


def test_the_rivals_gains_per_experiment():
    from torchmisspec.learning.choice._partial_choice import _gains

    known = torch.tensor([4.0, 0.0, 2.0, math.inf, 1.0], dtype=torch.float64)
    rival = torch.tensor([1.0, 3.0, math.inf, 5.0, 0.0], dtype=torch.float64)
    assert _gains(known, rival) == [math.log(4.0), -math.inf, math.inf, math.inf]  # nothing held out: skipped


@pytest.mark.parametrize("seed", range(6))
def test_better_in_every_experiment_is_scipys_variance_ratio_test_in_each(seed):
    """The rival is kept over few experiments when, in every experiment with held-out values, the ratio of the two
    models' sums of squares passes the one-sided F(n, n) test at the 2.5 % level (scipy's f.sf)."""
    from scipy.stats import f

    from torchmisspec.learning.choice._partial_choice import better_in_every_experiment

    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(2, 9, (3,), generator=g)
    rival = torch.rand(3, generator=g, dtype=torch.float64)
    known = rival * torch.exp(4.0 * torch.rand(3, generator=g, dtype=torch.float64))
    p = [float(f.sf(k / r, n, n)) for k, r, n in zip(known.tolist(), rival.tolist(), counts.tolist(), strict=True)]
    assert better_in_every_experiment(known, rival, counts) == all(q < 0.025 for q in p)


def test_better_in_every_experiment_at_its_edges():
    from torchmisspec.learning.choice._partial_choice import better_in_every_experiment

    two = torch.tensor([2, 2])
    # F(2, 2): P(X > x) = 1 / (1 + x), so a ratio above 39 is significant at 2.5 %
    assert better_in_every_experiment(torch.tensor([40.0, 80.0]), torch.tensor([1.0, 1.0]), two)
    assert not better_in_every_experiment(torch.tensor([38.0, 80.0]), torch.tensor([1.0, 1.0]), two)
    # worse, or not integrable, in one experiment: refused; the known model not integrable: the rival better there
    assert not better_in_every_experiment(torch.tensor([80.0, 1.0]), torch.tensor([1.0, 2.0]), two)
    assert not better_in_every_experiment(torch.tensor([80.0, 80.0]), torch.tensor([1.0, math.inf]), two)
    assert better_in_every_experiment(torch.tensor([math.inf, 80.0]), torch.tensor([1.0, 1.0]), two)
    # an experiment with nothing held out is skipped; with none at all there is no evidence
    assert better_in_every_experiment(torch.tensor([40.0, 0.0]), torch.tensor([1.0, 1.0]), torch.tensor([2, 0]))
    assert not better_in_every_experiment(torch.tensor([0.0, 0.0]), torch.tensor([1.0, 1.0]), torch.tensor([0, 0]))
    # the known model perfect where values are held out: the rival is not better there
    assert not better_in_every_experiment(torch.tensor([40.0, 0.0]), torch.tensor([1.0, 1.0]), two)
    assert not better_in_every_experiment(torch.tensor([40.0, 0.0]), torch.tensor([1.0, 0.0]), two)


def test_relative_noise_fits_a_state_measured_far_below_its_start():
    """A measured down to 1e-11 of its start (a = 2.5 over 10 time units), exact data compared in logarithms: the
    fit solves to the smallest value measured, lands on the truth and finds no noise (before, the absolute tolerance
    set by A's start made its late logarithms solver error: a 0.7 % off, A's noise scale 3 in logarithms)."""
    rate = torch.tensor([2.5, 0.3], dtype=DT)
    truth = tms.MisspecifiedSystem(lambda y: chain(y, rate.to(y)), 2, name="truth")
    times = torch.linspace(0.0, 10.0, 21, dtype=DT)
    clean = tms.simulate(truth, torch.tensor([[4.5, 0.1]], dtype=DT), times).states
    assert float(clean[0, -1, 0]) < 1e-10 * 4.5
    fit = fit_known_model(_system(), tms.Trajectories(times, clean), torch.tensor([[False, False]]), Relative())
    assert fit.theta.tolist() == pytest.approx(rate.tolist(), rel=1e-4)
    assert float(fit.scale.max()) < 1e-3
