"""dy/dt estimated in the noise model's space (torchmisspec.learning.samples._noise_space): the chain rule against
a hand computation, closed-form slopes, rows the model cannot hold, and why (per-sample noise that follows the
state's size under relative errors)."""

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.samples._noise_space import slope
from torchmisspec.learning.samples._stencils import finite_difference
from torchmisspec.noise import Additive, Counts, Poisson, Relative

DT = torch.float64


def _decay(rate=0.3):
    return tms.MisspecifiedSystem(lambda y: -rate * y, 1, name="decay", state_names=["conc"])


def _data(noise_sd=0.0, first_zero=False, seed=0):
    """Two experiments of y = y0 exp(-0.5 t) (the known model says 0.3: F = -0.2 y), log-normal noise."""
    t = torch.linspace(0.0, 10.0, 21, dtype=DT)
    y = torch.stack([100.0 * torch.exp(-0.5 * t), 40.0 * torch.exp(-0.5 * t)])[..., None]
    gen = torch.Generator().manual_seed(seed)
    y = y * torch.exp(noise_sd * torch.randn(y.shape, generator=gen, dtype=DT))
    if first_zero:
        y[:, 0] = 0.0
    return tms.Trajectories(t, y, state_names=["conc"])


@pytest.mark.parametrize(
    "noise, closed",
    [
        (Relative(), lambda y: y),
        (Counts(), lambda y: 1.0 + y),
        (Poisson(), lambda y: torch.sqrt(y + 0.375)),
        (Additive(), lambda y: torch.ones_like(y)),
    ],
)
def test_the_slope_of_each_noise_model_s_inverse_is_its_closed_form(noise, closed):
    y = torch.tensor([0.5, 3.0, 120.0], dtype=DT)
    assert torch.allclose(slope(noise, noise.transform(y)), closed(y), rtol=1e-10)


def test_central_differences_in_log_space_are_the_chain_rule_by_hand():
    """Under relative noise the stencil runs on log y and dy/dt = y d(log y)/dt: the samples' targets are that minus
    G, computed here by hand from the package's own stencil on log y."""
    data = _data()
    system = _decay()
    samples = tms.correction_samples(data, system, derivative="central", order=2, noise=Relative())
    by_hand = finite_difference(data.states.log(), data.times, order=2) * data.states
    expected = (by_hand - (-0.3 * data.states)).reshape(-1, 1)
    assert torch.allclose(samples.targets, expected, rtol=1e-10, atol=1e-12)
    assert samples.noise is None  # an explicit stencil: no per-sample noise
    assert "in the relative noise's space" in samples.derivative


def test_exact_exponential_data_give_exact_samples_in_log_space_not_as_measured():
    """log y is linear in t: second-order differences of it are exact, so F = -0.2 y to rounding; on y itself the
    same stencil is off by a few percent where the grid is coarse."""
    data, system = _data(), _decay()
    truth = (-0.2 * data.states).reshape(-1, 1)
    in_log = tms.correction_samples(data, system, derivative="central", noise=Relative())
    as_measured = tms.correction_samples(data, system, derivative="central")
    assert float((in_log.targets - truth).abs().max()) < 1e-9 * float(truth.abs().max())
    assert float((as_measured.targets - truth).abs().max()) > 1e-3 * float(truth.abs().max())


def test_the_gp_in_time_s_noise_follows_the_state_s_size_under_relative_errors():
    """With 5 % log-normal noise on a decay over two decades, the GP in time run on log y gives each sample a
    standard deviation roughly proportional to its state (its ratio to y spans less than a factor 10 over the two
    decades), where run on y itself the smallest states' derivatives are far more uncertain than the states' size
    allows (more than their own derivative)."""
    data, system = _data(noise_sd=0.05), _decay()
    relative = tms.correction_samples(data, system, derivative="gp", noise=Relative())
    additive = tms.correction_samples(data, system, derivative="gp")
    y = relative.states[:, 0]
    per_size = relative.noise[:, 0].sqrt() / y
    assert float(per_size.max() / per_size.min()) < 10.0
    small = y < 1.0
    assert bool(small.any())
    truth = 0.5 * y[small]  # |dy/dt|
    assert float((additive.noise[small, 0].sqrt() / truth).median()) > 1.0
    assert float((relative.noise[small, 0].sqrt() / truth).median()) < 0.5


def test_a_zero_the_relative_model_cannot_hold_gives_no_sample_and_the_others_stay():
    """A 0 written at each experiment's start (a lab's infusion start) is no relative measurement: those rows give no
    sample, and every other row gives the one it gives without them."""
    data, system = _data(first_zero=True), _decay()
    samples = tms.correction_samples(data, system, derivative="central", noise=Relative())
    assert samples.targets.shape[0] == data.num_samples - 2
    assert bool((samples.states > 0).all())
    rest = tms.Trajectories([data.times[1:]] * 2, [data.states[k, 1:] for k in range(2)], state_names=["conc"])
    alone = tms.correction_samples(rest, system, derivative="central", noise=Relative())
    assert torch.allclose(samples.targets, alone.targets, rtol=1e-12)


def test_auto_s_stencils_carry_their_self_checked_error_as_sample_noise_in_a_noise_space():
    """derivative="auto" in a noise model's space: every sample's variance is its estimator's mean-square error on
    the self-check's copy (one size in that space), so on y it scales with y^2 (relative errors)."""
    data, system = _data(noise_sd=0.05), _decay()
    samples = tms.correction_samples(data, system, noise=Relative())
    assert samples.noise is not None and bool(torch.isfinite(samples.noise).all())
    ratio = samples.noise[:, 0] / samples.states[:, 0].pow(2)
    if "gp" not in samples.derivative:  # a stencil: exactly one size in log space
        assert torch.allclose(ratio, ratio[0].expand_as(ratio), rtol=1e-9)


def test_a_noise_that_is_not_a_model_is_refused_with_the_fix():
    with pytest.raises(tms.InputError, match=r"noise: expected a torchmisspec.noise.NoiseModel .* got str.*Relative"):
        tms.correction_samples(_data(), _decay(), noise="relative")


def test_fit_correction_in_the_noise_space_learns_f_at_small_states_too():
    """A decay over two decades with 5 % log-normal noise, G missing 0.2 y, fitted with ``in_noise_space=True``:
    F's posterior at y = 0.5 (where the missing elimination is 0.1) is pinned within a fraction of it, which one
    noise size for every derivative sample does not give (the learned floor then sets F's spread where the states
    are smallest: 0.14 measured without it). One experiment's default leaves it off (the Samples stage says why)."""
    data, system = _data(noise_sd=0.05), _decay()
    gp = tms.fit_correction(data, system, noise="relative", in_noise_space=True, progress=False)
    assert not gp.known_model_ and "in the relative noise's space" in gp.derivative_
    assert gp.pipeline_.samples.in_noise_space
    default = tms.fit_correction(data, system, noise="relative", progress=False)
    assert "noise's space" not in default.derivative_
    post = gp.predict(torch.tensor([[0.5], [5.0]], dtype=DT))
    mean, sd = post.mean[:, 0], post.variance[:, 0].sqrt()
    assert math.isclose(float(mean[0]), -0.1, abs_tol=0.05), (mean, sd)
    assert float(sd[0]) < 0.1, (mean, sd)


def test_in_noise_space_must_be_a_flag_and_the_stage_called_alone_needs_the_noise_model():
    with pytest.raises(tms.InputError, match=r"in_noise_space: expected True or False, got 'yes'"):
        tms.learning.Samples(in_noise_space="yes")
    stage, data, system = tms.learning.Samples(derivative="central", in_noise_space=True), _data(), _decay()
    with pytest.raises(tms.InputError, match=r"True\) estimates dy/dt in a noise model.s space, got none"):
        stage(data, system)
    direct = tms.correction_samples(data, system, derivative="central", noise=Relative())
    assert torch.equal(stage(data, system, noise=Relative()).targets, direct.targets)
