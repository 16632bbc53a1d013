"""Issue 41, do no harm: the known model with its parameters fitted (F = 0) is a candidate of the default fit and is
returned when no correction predicts held-out experiments better; experiments too short for a derivative estimator
give no samples instead of ending the fit."""

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.choice.cross_validation import _held_out_errors
from torchmisspec.learning.fit import KNOWN_MODEL_OUTPUTSCALE, known_model_template, time_pieces

DT = torch.float64
R_TRUE, K_TRUE = 0.5, 10.0


def logistic(y, theta):
    r, k = theta[0], theta[1]
    return r * y * (1 - y / k)


def _growth(n=6, T=9, noise=0.02, seed=0):
    """Logistic growth of ``n`` cultures from the true (r, K), 2 % multiplicative noise: G is exact."""
    truth = tms.MisspecifiedSystem(lambda y: logistic(y, torch.tensor([R_TRUE, K_TRUE], dtype=y.dtype)), 1, name="t")
    g = torch.Generator().manual_seed(seed)
    y0 = 0.5 + torch.rand(n, 1, generator=g, dtype=DT)
    times = torch.linspace(0.0, 10.0, T, dtype=DT)
    clean = tms.simulate(truth, y0, times).states
    noisy = clean * (1 + noise * torch.randn(clean.shape, generator=g, dtype=DT))
    return tms.Trajectories(times, noisy, state_names=["x"])


def logistic_at_truth():
    """The same G without uncertain parameters: the known model's score is the cross-validation's baseline."""
    theta = torch.tensor([R_TRUE, K_TRUE], dtype=DT)
    return tms.MisspecifiedSystem(lambda y: logistic(y, theta), 1, name="logistic at the truth", state_names=["x"])


def _system():
    return tms.MisspecifiedSystem(
        logistic, 1, name="logistic", state_names=["x"], parameters={"r": (0.3, 0.2), "K": (14.0, 6.0)}
    )


def test_the_known_model_is_returned_when_it_is_right_with_its_parameters_fitted():
    data = _growth()
    with pytest.warns(tms.TorchMisspecWarning, match="returning the known model with its parameters fitted, F = 0"):
        gp = tms.fit_correction(data, _system(), progress=False)
    assert gp.known_model_ is True
    r, k = gp.parameters_.mean.tolist()
    assert r == pytest.approx(R_TRUE, rel=0.05) and k == pytest.approx(K_TRUE, rel=0.05)
    # F = 0: the corrected model's prediction is G's at the fitted parameters
    model = tms.CorrectedODE(_system(), gp)
    y0, times = torch.tensor([[0.7]], dtype=DT), torch.linspace(0, 20, 11, dtype=DT)  # beyond the data's span
    pred = model.predict(y0, times)
    known = tms.simulate(_system().at(gp.parameters_.mean), y0, times).states
    torch.testing.assert_close(pred, known, rtol=1e-6, atol=1e-8)
    # the record says what the known model scored with its own parameters, independently recomputed here
    cv = gp.cross_validation_
    own = _held_out_errors(_system().at(gp.parameters_.mean), data, noise=gp.noise_).sum()
    assert cv.known_fitted == pytest.approx(float(own), rel=1e-9) and cv.known_fitted <= cv.baseline
    assert tms.fit_correction(data, logistic_at_truth(), progress=False).cross_validation_.known_fitted is None


def test_the_known_model_template_is_zero_to_its_precision():
    data = _growth()
    samples = tms.correction_samples(data, tms.MisspecifiedSystem(lambda y: 0 * y, 1, name="zero"))
    gp = known_model_template(samples).fit(samples)
    x = torch.linspace(0, 12, 7, dtype=DT)[:, None]
    mean = gp.predict_mean(x)
    assert float(mean.abs().max()) <= 1e-9 * float(samples.targets.abs().max())
    assert gp.outputscale == pytest.approx(KNOWN_MODEL_OUTPUTSCALE * float(samples.targets.pow(2).mean()))


def test_a_correction_that_helps_is_kept():
    """G misses a decay term that matters: the known model loses on held-out experiments and is not returned."""
    truth = tms.MisspecifiedSystem(lambda y: -0.1 * y, 1, correction=lambda y: -0.5 * y**2 / (1 + y), name="t")
    times = torch.linspace(0, 5, 11, dtype=DT)
    data = tms.simulate(truth, torch.linspace(0.5, 3.0, 6, dtype=DT)[:, None], times)
    system = tms.MisspecifiedSystem(lambda y: -0.1 * y, 1, name="decay")
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)
        warnings.filterwarnings("ignore", message="fit_correction: noise 'relative'")  # the default's message
        gp = tms.fit_correction(data, system, progress=False)
    assert gp.known_model_ is False


def test_an_experiment_of_two_times_gives_no_samples_and_is_kept_by_the_fit():
    """ChickWeight has a chick weighed twice: the default estimator needs 3 times, and the fit raised InputError
    ("at least 3 samples per trajectory"). Its two rows are measured (not partly measured data)."""
    full = _growth(n=4)
    t, y = full.experiments()[2]
    experiments = [e for e in full.experiments()]
    experiments[2] = (t[:2], y[:2])
    data = tms.Trajectories([e[0] for e in experiments], [e[1] for e in experiments], state_names=["x"])
    assert not data.is_partial and bool(data.measured.all())
    with pytest.warns(tms.TorchMisspecWarning, match=r"1 experiment\(s\) \(\[2\]\) have fewer than 3 times"):
        samples = tms.correction_samples(data, _system())
    assert 2 not in samples.experiment.tolist()
    assert sorted(set(samples.experiment.tolist())) == [0, 1, 3]
    # the experiments' own samples are those of the data without the short one, experiment by experiment
    alone = tms.correction_samples(data[[0, 1, 3]], _system())
    torch.testing.assert_close(samples.targets, alone.targets)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = tms.fit_correction(data, _system(), progress=False)
    assert torch.isfinite(gp.parameters_.mean).all()


def test_only_short_experiments_are_refused_with_the_fix():
    data = tms.Trajectories(torch.tensor([0.0, 1.0], dtype=DT), torch.tensor([[[1.0], [1.2]]], dtype=DT))
    with pytest.raises(tms.InputError, match=r"derivative='auto': expected at least 3 samples per trajectory, got T=2"):
        tms.correction_samples(data, _system())


def test_a_component_seen_once_is_still_not_measured():
    """The rule's other side: a dose known only at time 0 (theophylline's gut) stays not measured."""
    times = torch.linspace(0, 4, 5, dtype=DT)
    states = torch.stack([torch.full((5,), float("nan"), dtype=DT), torch.linspace(1, 2, 5, dtype=DT)], -1)
    states[0, 0] = 3.0
    data = tms.Trajectories(times, states[None])
    assert data.measured.tolist() == [[False, True]]


def test_one_trajectory_is_scored_on_its_pieces_in_time():
    """One experiment (hare-lynx, influenza): no second experiment to hold out, so the candidates and the known
    model are scored on pieces of the trajectory cut in time, each forecast from its first state."""
    data = _growth(n=1, T=16)
    pieces = time_pieces(data)
    assert pieces.lengths == (5, 6, 5)
    torch.testing.assert_close(torch.cat([t for t, _ in pieces.experiments()]), data.times)
    with pytest.warns(tms.TorchMisspecWarning, match="returning the known model with its parameters fitted"):
        gp = tms.fit_correction(data, _system(), progress=False)
    assert gp.cross_validation_.folds == 3 and gp.known_model_
    assert time_pieces(_growth(n=1, T=9)) is None and time_pieces(_growth(n=2)) is None


def test_the_derivative_estimator_used_is_recorded():
    """Issue 41 item 6: the estimator derivative='auto' chose is on the samples and on the fitted model."""
    data = _growth()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        auto = tms.correction_samples(data, _system())
        assert tms.correction_samples(data, _system(), derivative="central", order=4).derivative == "central order=4"
        gp = tms.fit_correction(data, _system(), progress=False)
    assert auto.derivative.split()[0] in ("central", "gp", "smooth") and gp.derivative_ == auto.derivative
    assert auto.subset(torch.tensor([0, 1])).derivative == auto.derivative


def test_a_recentred_system_gives_the_residuals_at_theta_and_keeps_its_priors():
    """The second look's samples: G's parameters still uncertain, G evaluated and linearised at another theta."""
    data, system = _growth(), _system()
    theta = torch.tensor([0.5, 11.0], dtype=DT)
    moved = system.recentred(theta)
    assert moved.parameters is system.parameters and torch.equal(moved.theta, theta)
    samples = tms.correction_samples(data, moved, derivative="central")
    plain = tms.correction_samples(data, system.at(theta), derivative="central")
    torch.testing.assert_close(samples.targets, plain.targets)
    assert samples.basis is not None and plain.basis is None
    with pytest.raises(tms.InputError, match=r"recentred\(theta\): expected a system with uncertain parameters"):
        system.at(theta).recentred(theta)
    with pytest.raises(tms.ShapeError, match=r"theta: expected shape \(2,\)"):
        system.recentred(torch.zeros(3, dtype=DT))
