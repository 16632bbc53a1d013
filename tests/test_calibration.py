"""Calibration of the predicted bands on held-out experiments (issue 10: ``torchmisspec.prediction.calibration``)."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.prediction.calibration import BISECTION_STEPS

DT = torch.float64


@pytest.fixture(scope="module")
def data():
    """paper 5.1's system, 6 experiments with oracle derivatives plus noise of std 1e-3."""
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(3)
    y0 = torch.rand(6, 2, generator=g, dtype=DT) * 2 - 1
    traj = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=DT))
    samples = tms.correction_samples(traj, system, derivative="oracle", noise_std=1e-3, generator=g)
    return system, traj, samples


def _model(data, **gp_kwargs):
    system, _, samples = data
    return tms.CorrectedODE(system, tms.CorrectionGP(**gp_kwargs).fit(samples))


def test_scaled_draws_are_the_mean_plus_scaled_deviations(data):
    gp = _model(data).gp
    x = torch.rand(40, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    mu = gp.predict_mean(x)
    one = gp.sample_functions(8, generator=torch.Generator().manual_seed(5))(x)
    for c in (0.3, 2.5):
        scaled = gp.sample_functions(8, generator=torch.Generator().manual_seed(5), scale=c)(x)
        torch.testing.assert_close(scaled - mu, c * (one - mu), rtol=1e-9, atol=1e-12)
    with pytest.raises(tms.InputError, match="scale"):
        gp.sample_functions(8, scale=0.0)


def _check_bisection(cal, level):
    """``scale`` is where the held-out coverage first reaches ``level``: it does there, and not at the largest scale
    tried below it (up to the bisection's precision)."""
    tried = dict(zip(cal.scales, cal.coverages, strict=True))
    assert tried[cal.scale] == cal.coverage >= level
    below = [c for c in cal.scales if c < cal.scale]
    if below:
        assert tried[max(below)] < level
        assert cal.scale / max(below) < 2 ** (12 / 2**BISECTION_STEPS) + 1e-9


def test_an_overconfident_gp_is_widened(data):
    system, traj, samples = data
    # the output scale fixed far below the correction's size: F is shrunk to ~0 and the bands are far too narrow
    model = _model(data, outputscale=1e-9)
    cal = model.calibrate(traj, samples, num_samples=16, generator=torch.Generator().manual_seed(1))
    assert isinstance(cal, tms.BandCalibration) and model.calibration_ is cal
    assert cal.coverage_at_one < 0.5 and cal.scale > 4 and cal.reached and cal.folds == 6 and cal.refit
    assert cal.num_points == 6 * 10 * 2  # every held-out time after the first, both components
    _check_bisection(cal, 0.9)
    assert "scale=" in str(cal)
    with pytest.raises(tms.InputError, match="level"):
        model.calibrate(traj, samples, level=2.0)
    assert model.calibration_ is cal  # a failed calibration loses nothing
    # later posteriors use the calibrated scale by default
    y0, times = traj.states[:2, 0], torch.linspace(0, 6, 7, dtype=DT)
    default = model.posterior(y0, times, num_samples=8, generator=torch.Generator().manual_seed(2))
    explicit = model.posterior(y0, times, num_samples=8, generator=torch.Generator().manual_seed(2), scale=cal.scale)
    assert torch.equal(default.samples, explicit.samples)
    own = model.posterior(y0, times, num_samples=8, generator=torch.Generator().manual_seed(2), scale=1.0)
    assert float(default.stddev[:, 1:].mean()) > 4 * float(own.stddev[:, 1:].mean())


def test_an_overcautious_gp_is_narrowed(data):
    system, traj, samples = data
    # an output scale far above the correction's size (F ~ 1e-2), a short lengthscale and a noise variance 10^4
    # times the samples': bands far too wide
    model = _model(data, outputscale=1.0, lengthscale=0.3, noise_variance=1e-2)
    cal = model.calibrate(
        traj, samples, num_samples=8, folds=3, refit=False, generator=torch.Generator().manual_seed(1)
    )
    assert cal.coverage_at_one == 1.0 and cal.scale < 0.5 and not cal.refit
    _check_bisection(cal, 0.9)


def test_state_noise_is_not_mistaken_for_missing_spread(data):
    system, traj, samples = data
    # noise of std 0.05 on every observed state but the first (where the held-out paths start)
    noise = 0.05 * torch.randn(traj.states.shape, dtype=DT, generator=torch.Generator().manual_seed(4))
    noise[:, 0] = 0.0
    noisy = tms.Trajectories(traj.times, traj.states + noise)
    model = _model(data)
    kw = dict(num_samples=16, folds=3, refit=False, generator=torch.Generator().manual_seed(1))
    ignored = model.calibrate(noisy, samples, state_noise=None, **kw)
    allowed = model.calibrate(noisy, samples, state_noise=0.05, **kw)
    estimated = model.calibrate(noisy, samples, **kw)  # default "auto": the noise the GP in time finds
    exact = model.calibrate(traj, samples, **kw)
    # ignoring the noise, the bands miss most noisy states and must be widened a lot to cover them; allowing for it,
    # the GP's own bands (plus the noise) already cover about as often as on exact states
    assert ignored.coverage_at_one < 0.5 < 0.85 < allowed.coverage_at_one
    assert abs(allowed.coverage_at_one - exact.coverage_at_one) < 0.1
    assert ignored.scale > 5 * allowed.scale
    assert abs(estimated.coverage_at_one - allowed.coverage_at_one) < 0.1 and estimated.scale < 2 * allowed.scale
    relative = model.calibrate(noisy, samples, state_noise="5%", **kw)  # noise proportional to |y| (<= 1 here)
    assert relative.coverage_at_one > ignored.coverage_at_one
    with pytest.raises(tms.InputError, match="'auto', a percentage such as '2%'"):
        model.calibrate(noisy, samples, state_noise="five percent", **kw)


def test_out_of_reach_is_warned_and_kept_finite(data):
    system, traj, samples = data
    # states observed with an offset far beyond anything the draws reach even at the widest scale
    shifted = tms.Trajectories(traj.times, traj.states + 1e3)
    model = _model(data)
    with pytest.warns(tms.TorchMisspecWarning, match="no scale up to"):
        cal = model.calibrate(
            shifted, samples, num_samples=4, folds=2, refit=False, generator=torch.Generator().manual_seed(1)
        )
    assert not cal.reached and cal.coverage < 0.9 and cal.scale <= 256


def test_bad_input(data):
    system, traj, samples = data
    model = _model(data)
    for level in (0.0, 1.0, 1.5, float("nan")):
        with pytest.raises(tms.InputError, match="level"):
            tms.calibrate_bands(model, traj, samples, level=level)
    with pytest.raises(tms.InputError, match="folds"):
        tms.calibrate_bands(model, traj, samples, folds=1)
    with pytest.raises(tms.InputError, match="num_samples"):
        tms.calibrate_bands(model, traj, samples, num_samples=0)
    with pytest.raises(tms.InputError, match="state_noise"):
        tms.calibrate_bands(model, traj, samples, state_noise=-1.0)
    with pytest.raises(tms.ShapeError, match="state_noise: expected a standard deviation or 2"):
        tms.calibrate_bands(model, traj, samples, state_noise=[0.1, 0.1, 0.1])
    with pytest.raises(tms.InputError, match="expected neither scale nor num_samples .calibrate_bands sets them"):
        tms.calibrate_bands(model, traj, samples, scale=2.0)
    with pytest.raises(
        tms.InputError,
        match=r"model: expected a CorrectedODE \(torchmisspec\.CorrectedODE\(system, gp\)\), got CorrectionGP",
    ):
        tms.calibrate_bands(model.gp, traj, samples)
    fewer = tms.Trajectories(traj.times, traj.states[:4])
    with pytest.raises(tms.InputError, match="samples: expected the correction samples of these 4 experiments"):
        tms.calibrate_bands(model, fewer, samples)
    y0, times = traj.states[:1, 0], torch.linspace(0, 1, 3, dtype=DT)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(tms.InputError, match="scale"):
            model.posterior(y0, times, num_samples=2, scale=bad)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        assert model.calibration_ is None  # nothing above calibrated the model


def test_the_calibration_is_kept_with_the_gp_saved_with_it_and_dropped_by_a_refit(data, tmp_path):
    """The calibration lives on the GP: a new CorrectedODE over it, a saved and loaded copy, and the CLI (which saves
    only the GP) all get the calibrated bands; an uncalibrated posterior warns; a refit drops the calibration."""
    system, traj, samples = data
    model = _model(data, outputscale=1e-9)
    y0, times = traj.states[:2, 0], torch.linspace(0, 6, 7, dtype=DT)
    with pytest.warns(tms.TorchMisspecWarning, match="not calibrated on held-out experiments"):
        model.posterior(y0, times, num_samples=4, generator=torch.Generator().manual_seed(2))
    model.gp.samples_ = samples  # as fit_correction records them: calibrate() then needs no samples
    cal = model.calibrate(traj, num_samples=8, generator=torch.Generator().manual_seed(1))
    assert model.gp.calibration_ is cal and tms.CorrectedODE(system, model.gp).calibration_ is cal
    loaded = tms.CorrectionGP.load(model.gp.save(tmp_path / "gp.pt"))
    assert loaded.calibration_ == cal
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)  # calibrated: no warning (paths stay in support)
        again = tms.CorrectedODE(system, loaded).posterior(
            y0, times, num_samples=8, generator=torch.Generator().manual_seed(2), support_threshold=1.0
        )
    first = model.posterior(y0, times, num_samples=8, generator=torch.Generator().manual_seed(2), support_threshold=1.0)
    torch.testing.assert_close(again.samples, first.samples, rtol=1e-7, atol=1e-10)
    model.gp.fit(samples)
    assert model.calibration_ is None
    del model.gp.samples_
    with pytest.raises(tms.InputError, match="samples: expected the correction samples"):
        model.calibrate(traj)


def test_the_folds_numerical_warnings_are_summarised_once_with_what_calibrate_can_do(data):
    """A fold refit that warns (here: the feature weights stop at a tiny max_iter) gave the user a message asking to
    'raise max_iter', an argument calibrate does not take; now one warning says the folds use the model's settings."""
    system, traj, samples = data
    gp = tms.CorrectionGP(kernel="features", degree=3, max_iter=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.NumericalWarning)
        gp.fit(samples)
    with pytest.warns(
        tms.NumericalWarning, match=r"calibrate_bands: the refit of the GP on \d+ fold\(s\) warned"
    ) as rec:
        tms.CorrectedODE(system, gp).calibrate(traj, samples, num_samples=4, folds=3, progress=False)
    assert sum("max_iter=1" in str(w.message) for w in rec) == 1
    assert not any(str(w.message).startswith("the feature weights") for w in rec)


@pytest.mark.filterwarnings("ignore::torchmisspec.TorchMisspecWarning")  # tiny folds of exact states: not the point
def test_a_model_refined_through_the_ode_has_each_fold_refined_the_same_way(data, tmp_path, monkeypatch):
    """fit_correction refines the feature kernel through the ODE; the folds used to be fitted to the samples alone, a
    worse model whose held-out errors made the bands cover 0.98 of the true states in the end-to-end study. The
    refinement's settings are recorded on the model, saved with it, and repeated on every fold's experiments."""
    import torchmisspec.prediction.calibration as calibration

    system, traj, samples = data
    gp = tms.CorrectionGP(kernel="features", degree=2).fit(samples)
    assert gp.refinement_ is None
    refined = tms.fit_trajectories(gp, system, traj, max_iter=7, state_noise=1e-6)
    assert refined.refinement_["max_iter"] == 7 and refined.refinement_["state_noise"] == 1e-6
    assert refined.refinement_["relevance"] is True and gp.refinement_ is None
    loaded = tms.CorrectionGP.load(refined.save(tmp_path / "gp.pt"))
    assert loaded.refinement_ == refined.refinement_
    calls = []
    real = calibration.fit_trajectories

    def counting(fold_gp, fold_system, fold_traj, **settings):
        calls.append((fold_traj.num_experiments, settings))
        return real(fold_gp, fold_system, fold_traj, **settings)

    monkeypatch.setattr(calibration, "fit_trajectories", counting)
    loaded.samples_ = samples
    model = tms.CorrectedODE(system, loaded)
    model.calibrate(traj, num_samples=4, folds=3, progress=False, generator=torch.Generator().manual_seed(0))
    assert [n for n, _ in calls] == [4, 4, 4] and all(s == refined.refinement_ for _, s in calls)
    calls.clear()
    model.calibrate(traj, num_samples=4, folds=2, refit=False, progress=False)
    assert [n for n, _ in calls] == [3, 3] and all(s["relevance"] is False for _, s in calls)
    calls.clear()
    tms.CorrectedODE(system, gp).calibrate(traj, samples, num_samples=4, folds=2, progress=False)
    assert calls == []  # a model not refined: neither are its folds
    refined.fit(samples)
    assert refined.refinement_ is None  # a refit is no longer the refined model


def test_a_corrupt_refinement_record_is_refused_by_name(data, tmp_path):
    system, traj, samples = data
    refined = tms.fit_trajectories(tms.CorrectionGP(kernel="features").fit(samples), system, traj, max_iter=3)
    blob = torch.load(refined.save(tmp_path / "gp.pt"), weights_only=True)
    blob["refinement"] = {"shooting": "single", "max_iter": "many"}
    torch.save(blob, tmp_path / "bad.pt")
    with pytest.raises(tms.InputError, match="'refinement' to be the settings of fit_trajectories"):
        tms.CorrectionGP.load(tmp_path / "bad.pt")


def test_where_the_noise_alone_covers_the_held_out_data_the_bands_are_left_as_the_model_gives_them():
    """Even the narrowest scale covering: with measurement noise that covers the held-out data by itself (the model's
    spread at scale 0), the scale says nothing and stays 1 (R's Indometh: narrowed to the floor, the forecast bands
    were 16 times narrower than the model's); without noise, or where the noise alone does not cover, the floor is
    kept. Both warn."""
    from torchmisspec.prediction.calibration import _at_the_floor

    def coverage(c):  # noise alone: 0.95 of the points; the model's spread adds to it
        return min(1.0, 0.95 + 0.05 * c)

    with pytest.warns(tms.TorchMisspecWarning, match="the measurement noise alone covers 0.9"):
        assert _at_the_floor(coverage, 0.9, True, 0.0625, 0.953, 1.0) == (1.0, 1.0)
    with pytest.warns(tms.TorchMisspecWarning, match="even the narrowest scale tried"):
        assert _at_the_floor(coverage, 0.9, False, 0.0625, 0.953, 1.0) == (0.0625, 0.953)
    with pytest.warns(tms.TorchMisspecWarning, match="even the narrowest scale tried"):
        assert _at_the_floor(lambda c: 0.5 + c, 0.9, True, 0.0625, 0.9, 1.0) == (0.0625, 0.9)
