"""Issue 41, noise as measured: the noise models' residuals (closed forms), the automatic choice and its message,
their checks, and what they change in fit_correction (scale-free model choice and parameter fit)."""

import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.noise import Additive, CountNoise, Counts, Poisson, Relative, as_noise_model

DT = torch.float64


def _data(values):
    v = torch.tensor(values, dtype=DT)
    return tms.Trajectories(torch.arange(v.shape[0], dtype=DT), v[None, :, None])


def test_residuals_are_the_closed_forms():
    obs, pred = torch.tensor([2.0, 10.0, float("nan")], dtype=DT), torch.tensor([1.0, 20.0, 3.0], dtype=DT)
    torch.testing.assert_close(Additive().residuals(obs, pred)[:2], torch.tensor([1.0, -10.0], dtype=DT))
    torch.testing.assert_close(
        Relative().residuals(obs, pred)[:2], torch.tensor([math.log(2), math.log(0.5)], dtype=DT)
    )
    torch.testing.assert_close(
        Counts().residuals(obs, pred)[:2], torch.tensor([math.log(3 / 2), math.log(11 / 21)], dtype=DT)
    )
    assert torch.isnan(Relative().residuals(obs, pred)[2])
    # a prediction at or below 0 is far off in logs, never NaN
    assert float(Relative().residuals(torch.tensor([1.0], dtype=DT), torch.tensor([-1.0], dtype=DT))) > 700


def test_counts_in_the_datas_units_are_the_same_counts():
    y, scale = torch.tensor([[0.0, 30.0], [120.0, 7.0]], dtype=DT), torch.tensor([100.0, 10.0], dtype=DT)
    torch.testing.assert_close(Counts().in_units(scale).transform(y / scale), Counts().transform(y))
    assert Relative().in_units(scale) == Relative()


def test_auto_is_relative_for_positive_states_spanning_a_factor_and_says_so():
    with pytest.warns(tms.TorchMisspecWarning, match="noise 'relative'.*pass noise='additive'"):
        assert as_noise_model("auto", _data([3.0, 9.0, 30.0]), announce="fit_correction") == Relative()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert as_noise_model("auto", _data([3.0, 4.0, 5.0]), announce="fit_correction") == Additive()  # 1.7x
        assert as_noise_model("auto", _data([-1.0, -2.0, 4.0, 5.0]), announce="fit_correction") == Additive()


def test_a_value_below_zero_that_rules_out_relative_noise_is_named():
    """A blank-corrected assay's negative concentration among values spanning decades: additive, and said so (a
    user's trial on nlme's Remifentanil got no word of it)."""
    decay = [100.0 * 0.7**i for i in range(25)]  # 100 down to 0.02
    with pytest.warns(tms.TorchMisspecWarning, match="noise 'additive': 1 measured value.*lowest -0.02.*empty"):
        assert as_noise_model("auto", _data([*decay, -0.02]), announce="fit_correction") == Additive()
    with warnings.catch_warnings():  # a signal that crosses zero: additive without a word
        warnings.simplefilter("error")
        wave = [math.sin(0.5 * i) + 0.01 for i in range(40)]
        assert as_noise_model("auto", _data(wave), announce="fit_correction") == Additive()


def test_a_starting_value_that_is_not_measured_does_not_decide():
    """Influenza: R = 0 is given on day 0 only (not measured), I is measured and positive: relative noise."""
    states = torch.full((1, 6, 2), float("nan"), dtype=DT)
    states[0, :, 0] = torch.tensor([1.0, 3.0, 25.0, 75.0, 228.0, 296.0], dtype=DT)
    states[0, 0, 1] = 0.0
    data = tms.Trajectories(torch.arange(6, dtype=DT), states)
    assert as_noise_model("auto", data) == Relative() and as_noise_model("relative", data) == Relative()


def test_a_zero_first_row_does_not_rule_out_relative_noise():
    """Theophylline: the concentration is 0 before the dose (each subject's first row, where every prediction
    starts), then positive and spanning a factor of 20: relative noise, as the classical answer takes it (the auto
    choice was additive). A 0 after the first row still rules it out."""
    assert as_noise_model("auto", _data([0.0, 10.0, 6.0, 0.5])) == Relative()
    assert as_noise_model("relative", _data([0.0, 10.0, 6.0, 0.5])) == Relative()
    assert as_noise_model("auto", _data([1.0, 10.0, 0.0, 0.5])) == Additive()


def test_bad_noise_is_refused_with_the_fix():
    with pytest.raises(tms.InputError, match="expected positive measurements for relative.*noise='counts'"):
        as_noise_model("relative", _data([1.0, 0.0, 2.0]))
    with pytest.raises(tms.InputError, match="expected counts \\(0 or more\\)"):
        as_noise_model("counts", _data([-1.0, 1.0, 2.0]))
    with pytest.raises(
        tms.InputError, match="noise: expected 'auto', one of \\['additive', 'relative', 'counts', 'poisson'\\]"
    ):
        as_noise_model("gaussian", _data([1.0, 2.0, 3.0]))


def logistic(y, theta):
    return theta[0] * y * (1 - y / theta[1])


def _growth(scale: float, seed: int = 0):
    """Logistic growth from 0.2 to near K = 10 (a factor of 50), 5 % multiplicative noise, in units ``scale``."""
    truth = tms.MisspecifiedSystem(lambda y: logistic(y, torch.tensor([0.6, 10.0], dtype=y.dtype)), 1, name="t")
    g = torch.Generator().manual_seed(seed)
    y0 = 0.2 + 0.3 * torch.rand(5, 1, generator=g, dtype=DT)
    clean = tms.simulate(truth, y0, torch.linspace(0, 12, 13, dtype=DT)).states
    noisy = clean * torch.exp(0.05 * torch.randn(clean.shape, generator=g, dtype=DT))
    return tms.Trajectories(torch.linspace(0, 12, 13, dtype=DT), scale * noisy)


def _system(scale: float):
    return tms.MisspecifiedSystem(lambda y, th: logistic(y, th), 1, name="logistic",
                                  parameters={"r": (0.4, 0.3), "K": (8.0 * scale, 5.0 * scale)})  # fmt: skip


def test_relative_noise_fits_the_parameters_alike_in_any_units_and_is_recorded():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        fits = [tms.fit_correction(_growth(c), _system(c), progress=False) for c in (1.0, 1e3)]
    for gp in fits:
        assert gp.noise_ == Relative()
    r1, k1 = fits[0].parameters_.mean.tolist()
    r2, k2 = fits[1].parameters_.mean.tolist()
    assert r1 == pytest.approx(r2, rel=1e-3) and k1 * 1e3 == pytest.approx(k2, rel=1e-3)
    assert r1 == pytest.approx(0.6, rel=0.1) and k1 == pytest.approx(10.0, rel=0.1)


def test_the_noise_scale_is_the_measurement_noise_when_the_model_is_right():
    """5 % log-normal noise on logistic growth that G (its parameters fitted) describes exactly: the recorded scale
    of the residuals in log space is the noise's 0.05 (64 residuals: standard error about 0.0045)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(_growth(1.0, seed=3), _system(1.0), progress=False)
    assert gp.noise_scale_.shape == (1,)
    assert float(gp.noise_scale_[0]) == pytest.approx(0.05, abs=0.015)


def _still(y: float, S: int = 4000, d: int = 1):
    from torchmisspec.prediction._bands import TrajectoryPosterior

    samples = torch.full((S, 1, 3, d), y, dtype=DT)
    return TrajectoryPosterior(
        times=torch.arange(3, dtype=DT)[None], samples=samples, mean_path=samples[0], support=torch.zeros(1, 3),
        extrapolating=torch.zeros(1, dtype=torch.bool), threshold=0.7,
    )  # fmt: skip


@pytest.mark.parametrize("noise", [Additive(), Relative(), Counts()])
def test_the_band_of_new_measurements_is_the_noise_around_a_certain_path(noise):
    """All draws on one path (no uncertainty in F): the 90 % band of new measurements is the noise's own 5-95 %
    quantiles around it, z = -/+1.645 in the noise model's space (4,000 draws: the 5 % quantile's standard error is
    0.033 in z)."""
    scale = torch.tensor([0.1], dtype=DT)
    measured = _still(50.0).measured(noise, scale, generator=torch.Generator().manual_seed(0))
    lower, upper = measured.interval(0.9)
    centre = noise.transform(torch.tensor(50.0, dtype=DT))
    z_lo, z_hi = (((noise.transform(b) - centre) / scale).mean().item() for b in (lower, upper))
    assert z_lo == pytest.approx(-1.6449, abs=0.1) and z_hi == pytest.approx(1.6449, abs=0.1)


def test_the_band_of_new_measurements_refuses_what_it_cannot_use():
    with pytest.raises(tms.InputError, match="expected a torchmisspec.noise.NoiseModel"):
        _still(1.0).measured("relative", torch.tensor([0.1], dtype=DT))
    with pytest.raises(tms.InputError, match=r"scale: expected \(1,\) standard deviations >= 0"):
        _still(1.0).measured(Relative(), torch.tensor([-0.1], dtype=DT))
    # a component never measured (NaN scale) gets no noise
    none = _still(2.0, S=10, d=2).measured(Relative(), torch.tensor([0.1, math.nan], dtype=DT))
    assert bool((none.samples[..., 1] == 2.0).all()) and not bool((none.samples[..., 0] == 2.0).all())


COUNTED = (Counts(torch.tensor([1.0, 100.0], dtype=DT)), Poisson(torch.tensor([1.0, 0.1], dtype=DT)))


@pytest.mark.parametrize("noise", [Relative(), Additive(), *COUNTED])
def test_the_fit_records_travel_with_the_saved_model(tmp_path, noise):
    """noise_, noise_scale_, known_model_ and dispersion_ (the band of new measurements, and the do-no-harm flag)
    are saved and read back; a record the file cannot hold is refused naming the file."""
    X = torch.linspace(0, 1, 8, dtype=DT).reshape(-1, 1)
    gp = tms.CorrectionGP(lengthscale=0.5).fit(X, torch.sin(X))
    gp.noise_, gp.noise_scale_ = noise, torch.tensor([0.1, float("nan")], dtype=DT)
    gp.known_model_, gp.dispersion_ = True, 2.5
    loaded = tms.CorrectionGP.load(gp.save(tmp_path / "m.pt"))
    assert loaded.noise_ == noise and repr(loaded.noise_) == repr(noise)
    assert torch.equal(loaded.noise_scale_.isnan(), gp.noise_scale_.isnan()) and float(loaded.noise_scale_[0]) == 0.1
    assert loaded.known_model_ is True and loaded.dispersion_ == 2.5
    if isinstance(noise, CountNoise):
        assert torch.equal(torch.as_tensor(loaded.noise_.unit), noise.unit.to(torch.float64))
    blob = torch.load(tmp_path / "m.pt", weights_only=True)
    blob["fit_record"]["noise"] = "gaussian"
    torch.save(blob, tmp_path / "bad.pt")
    with pytest.raises(tms.InputError, match="bad.pt: expected 'fit_record' with 'noise' one of"):
        tms.CorrectionGP.load(tmp_path / "bad.pt")


def test_relative_noise_resolves_each_states_smallest_measured_value():
    """The smallest positive measured value per state (a state never measured, or measured only at or below 0: NaN);
    errors of one size need no floor."""
    states = torch.tensor([[[4.0, 0.0], [1e-3, math.nan], [2e-7, 0.5]], [[3.0, 0.0], [0.2, 0.1], [math.nan, 0.7]]])
    data = tms.Trajectories(torch.tensor([0.0, 1.0, 2.0]), states.double())
    assert Relative().resolution(data).tolist() == pytest.approx([2e-7, 0.1])
    unmeasured = states.double().clone()
    unmeasured[:, :, 1] = math.nan
    assert math.isnan(float(Relative().resolution(tms.Trajectories(torch.tensor([0.0, 1.0, 2.0]), unmeasured))[1]))
    assert Additive().resolution(data) is None
