"""Issue 41, item 4: counts as measured. The Poisson observation model (quasi-Poisson: its dispersion fitted) against
its closed forms and moments, its draws of new counts (Poisson, or negative binomial when overdispersed), a fit of
simulated counts that recovers the parameters and the dispersion, the band of new counts covering new counts, the
saved model, the command line, and the automatic choice for whole numbers with zeros."""

import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.noise import Counts, Poisson, as_noise_model

DT = torch.float64


def test_the_residuals_are_anscombes_closed_form():
    obs, pred = torch.tensor([0.0, 10.0, 400.0], dtype=DT), torch.tensor([1.0, 12.0, 380.0], dtype=DT)
    expected = 2 * torch.sqrt(obs + 0.375) - 2 * torch.sqrt(pred + 0.375)
    torch.testing.assert_close(Poisson().residuals(obs, pred), expected)
    torch.testing.assert_close(Poisson().inverse(Poisson().transform(pred)), pred)
    scale = torch.tensor([100.0], dtype=DT)  # in the data's units: the same counts
    torch.testing.assert_close(Poisson().in_units(scale).transform(obs / scale), Poisson().transform(obs))


@pytest.mark.parametrize("mu", [5.0, 50.0, 500.0])
def test_the_transform_gives_poisson_counts_unit_variance(mu):
    """The reason for the transform: the residual scale of Poisson counts is 1 at any size (20,000 draws: the
    variance's standard error is about 0.01)."""
    counts = torch.poisson(torch.full((20000,), mu, dtype=DT), generator=torch.Generator().manual_seed(0))
    assert float(Poisson().transform(counts).var()) == pytest.approx(1.0, abs=0.06)


@pytest.mark.parametrize("phi", [1.0, 4.0])
def test_new_counts_have_the_mean_and_the_dispersion_asked(phi):
    """Drawn at the mean mu with scale sqrt(phi): whole numbers of mean mu and variance phi mu (Poisson at phi = 1,
    negative binomial above), the same for the same generator; NaN stays NaN (a draw stopped outside its region)."""
    mu = torch.full((40000, 1), 30.0, dtype=DT)
    mu[0, 0] = math.nan
    scale = torch.tensor([math.sqrt(phi)], dtype=DT)
    draws = Poisson().measure(mu, scale, generator=torch.Generator().manual_seed(1))
    again = Poisson().measure(mu, scale, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(draws, again, equal_nan=True)
    assert math.isnan(float(draws[0, 0]))
    seen = draws[1:, 0]
    assert bool((seen == seen.round()).all()) and bool((seen >= 0).all())
    assert float(seen.mean()) == pytest.approx(30.0, rel=0.02)
    assert float(seen.var()) == pytest.approx(30.0 * phi, rel=0.05)


def logistic(y, theta):
    return theta[0] * y * (1 - y / theta[1])


TRUE = (0.6, 500.0)


def _colonies(phi: float, seed: int, K: int = 6):
    """Logistic growth of counts from about 10 to near 500, each time a new count of mean the true path and
    variance phi times it."""
    truth = tms.MisspecifiedSystem(lambda y: logistic(y, torch.tensor(TRUE, dtype=y.dtype)), 1, name="truth")
    g = torch.Generator().manual_seed(seed)
    y0 = 8.0 + 6.0 * torch.rand(K, 1, generator=g, dtype=DT)
    times = torch.linspace(0, 12, 13, dtype=DT)
    clean = tms.simulate(truth, y0, times).states
    noisy = Poisson().measure(clean, torch.tensor([math.sqrt(phi)], dtype=DT), generator=g)
    noisy[:, 0] = y0.round()
    return tms.Trajectories(times, noisy), clean


def _system():
    return tms.MisspecifiedSystem(logistic, 1, name="logistic", parameters={"r": (0.4, 0.3), "K": (400.0, 300.0)})


@pytest.mark.parametrize("phi", [1.0, 4.0])
def test_a_fit_of_counts_recovers_the_parameters_and_the_dispersion(phi):
    """The known model is right: the fit with noise='poisson' finds r and K and reports the residual scale
    sqrt(phi) (72 residuals: its standard error is about 9 %)."""
    data, _ = _colonies(phi, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, _system(), noise="poisson", progress=False)
    assert gp.noise_ == Poisson()
    r, k = gp.parameters_.mean.tolist()
    assert r == pytest.approx(TRUE[0], rel=0.1) and k == pytest.approx(TRUE[1], rel=0.05)
    assert float(gp.noise_scale_[0]) == pytest.approx(math.sqrt(phi), rel=0.3)


@pytest.mark.slow
def test_the_band_of_new_counts_covers_new_counts():
    """Fitted on 6 colonies, a new colony predicted from its first count: the 90 % band of new measurements
    (posterior draws, then new counts drawn around each) covers new counts of the true path 0.8-0.97 of the time
    (12 times x 50 replicate counts)."""
    data, _ = _colonies(1.0, seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, _system(), noise="poisson", progress=False)
    new, clean = _colonies(1.0, seed=11, K=1)
    model = tms.CorrectedODE(_system(), gp)
    post = model.posterior(new.states[:, 0], new.times, num_samples=64, generator=torch.Generator().manual_seed(0))
    lower, upper = post.measured(gp.noise_, gp.noise_scale_, generator=torch.Generator().manual_seed(1)).interval(0.9)
    g = torch.Generator().manual_seed(2)
    replicates = torch.poisson(clean[0, 1:, 0].expand(50, -1).contiguous(), generator=g)
    inside = (replicates >= lower[0, 1:, 0]) & (replicates <= upper[0, 1:, 0])
    assert 0.8 <= float(inside.double().mean()) <= 0.97


def test_a_saved_model_keeps_its_poisson_noise(tmp_path):
    data, _ = _colonies(1.0, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, _system(), noise="poisson", progress=False)
    gp.save(tmp_path / "m.pt")
    back = tms.CorrectionGP.load(tmp_path / "m.pt")
    assert back.noise_ == Poisson() and repr(back.noise_) == repr(gp.noise_)
    torch.testing.assert_close(back.noise_scale_, gp.noise_scale_)


def test_the_command_line_fits_counts_as_poisson(tmp_path, capsys):
    from torchmisspec.cli import main

    data, _ = _colonies(1.0, seed=2)
    rows = ["experiment,time,colonies"]
    for k, (t, y) in enumerate(data.experiments()):
        rows += [f"{k},{float(a):g},{float(b):g}" for a, b in zip(t, y[:, 0], strict=True)]
    (tmp_path / "counts.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "model.py").write_text(
        "import torch\n"
        "from torchmisspec import MisspecifiedSystem\n\n"
        "def g(y, theta):\n"
        "    return theta[0] * y * (1 - y / theta[1])\n\n"
        "SYSTEM = MisspecifiedSystem(g, 1, name='colonies', state_names=['colonies'],\n"
        "                            parameters={'r': (0.4, 0.3), 'K': (400.0, 300.0)})\n"
    )
    argv = ["fit", "--data", str(tmp_path / "counts.csv"), "--system", f"{tmp_path / 'model.py'}:SYSTEM"]
    code = main([*argv, "--noise", "poisson", "--out", str(tmp_path / "m.pt"), "--quiet", "--no-calibrate"])
    out = capsys.readouterr().out
    assert code == 0 and "noise 'poisson'" in out
    assert tms.CorrectionGP.load(tmp_path / "m.pt").noise_ == Poisson()


def test_auto_takes_whole_numbers_with_zeros_as_counts_and_says_so():
    values = torch.tensor([5.0, 12.0, 0.0, 3.0, 40.0], dtype=DT)
    data = tms.Trajectories(torch.arange(5, dtype=DT), values[None, :, None])
    with pytest.warns(tms.TorchMisspecWarning, match="noise 'counts'.*whole numbers.*noise='poisson'"):
        assert as_noise_model("auto", data, announce="fit_correction") == Counts()
    fractional = tms.Trajectories(torch.arange(5, dtype=DT), (values + 0.5)[None, :, None])
    assert as_noise_model("auto", fractional).name == "relative"  # positive, spanning a factor of 5


def test_a_component_without_noise_gets_none():
    """Scale 0 (the bands give it to a component never measured) leaves the states as they are."""
    y = torch.tensor([[12.3, 40.0]], dtype=DT).expand(1000, 2)
    draws = Poisson().measure(y, torch.tensor([0.0, 1.0], dtype=DT), generator=torch.Generator().manual_seed(0))
    assert bool((draws[:, 0] == 12.3).all()) and float(draws[:, 1].std()) > 3


@pytest.mark.parametrize("noise", ["counts", "poisson"])
def test_counts_of_a_partly_measured_outbreak_in_the_hundreds_are_fitted(noise):
    """Influenza days 0-10 (S = 762 given on day 0 only, I measured): the count models fit it in the data's units
    (a count's unit per component met the flattened residuals of the known model's fit and raised a shape error),
    near the relative model's beta 1.58 and gamma 0.43; the known model's bands say nothing about F's support."""
    from torchmisspec import datasets

    t, y = datasets.load("influenza").trajectories.experiments()[0]
    train = tms.Trajectories(t[:11], y[:11][None], state_names=["S", "I", "R"])
    system = datasets.load("influenza").system
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(train, system, noise=noise, progress=False)
    assert gp.noise_.name == noise and gp.known_model_
    beta, gamma = gp.parameters_.mean.tolist()
    assert beta == pytest.approx(1.58, abs=0.1) and gamma == pytest.approx(0.43, abs=0.05)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tms.CorrectedODE(system, gp).posterior(y[:1], t, num_samples=16, scale=1.0)
    assert not [w for w in caught if "support" in str(w.message)]
