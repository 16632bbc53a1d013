"""Issue 41, item 3: the defaults never crash on a trial step. A fit through the ODE treats a solve that fails as a
rejected step, a starting model that cannot be integrated is replaced by a smaller one that can (with a warning),
and a component that is never observed has its initial values estimated from a stated guess."""

import pytest
import torch

import torchmisspec as tms

DT = torch.float64


@pytest.fixture(scope="module")
def problem(fast_linear):
    """A linear system with a quadratic F; 4 noise-free experiments, T = 11."""
    system, traj = fast_linear(4)
    return system, traj


def _wild(system, traj, **kernel):
    """A correction that blows up within the data's span (1e4 times x^2)."""
    x = system.select_inputs(traj.states).reshape(-1, 2)
    return tms.CorrectionGP(noise_variance=1e-4, **kernel).fit(x, 1e4 * x.pow(2))


@pytest.mark.parametrize("relevance", [True, False])
def test_a_starting_correction_that_blows_up_is_shrunk_until_it_integrates(problem, one_thread, relevance):
    """Levenberg-Marquardt (relevance through the ODE) and L-BFGS both start from a smaller correction, with a
    warning, instead of raising (before: FittingError 'the starting correction cannot be integrated', or
    IntegrationError)."""
    system, traj = problem
    wild = _wild(system, traj, kernel="features", degree=2)
    with pytest.warns(
        tms.TorchMisspecWarning, match=r"the starting correction cannot be integrated .* the fit starts from"
    ):
        refined = tms.fit_trajectories(wild, system, traj, max_steps=50, max_iter=5, relevance=relevance)
    assert refined.is_fitted and bool(torch.isfinite(refined.train_targets_).all())
    pred = tms.CorrectedODE(system, refined).predict(traj.initial_conditions, traj.times)
    assert bool(torch.isfinite(pred).all())


def test_nothing_integrates_still_raises(problem):
    """Where even the known model alone (F = 0) cannot be integrated, there is nothing to fall back on."""
    system, traj = problem
    wild = _wild(system, traj, kernel="features", degree=2)
    with pytest.raises(tms.IntegrationError, match="the solver took more than 1 steps"):
        tms.fit_trajectories(wild, system, traj, max_steps=1, max_iter=2)


def predator_prey(y):
    """Lotka-Volterra: the prey (never measured) drives the predator (measured)."""
    prey, predator = y[..., 0], y[..., 1]
    return torch.stack([0.8 * prey - 0.5 * prey * predator, 0.4 * prey * predator - 0.6 * predator], dim=-1)


def test_a_component_never_observed_starts_from_the_data_scale_and_is_estimated(one_thread):
    """The lynx case: the prey is never observed in any experiment (before: InputError 'give each experiment's
    initial value of it in the first row', which a scientist with these data cannot give); its initial values start
    at the data's scale, said in one warning, and are estimated through the ODE from the predator it drives."""
    truth = tms.MisspecifiedSystem(predator_prey, 2, state_names=["prey", "predator"])
    t = torch.linspace(0, 6, 13, dtype=DT)
    y0 = torch.tensor([[1.5, 1.0], [1.0, 0.6]], dtype=DT)
    y = tms.simulate(truth, y0, t).states.clone()
    y[..., 0] = float("nan")
    data = tms.Trajectories(t, y, state_names=["prey", "predator"])
    system = tms.MisspecifiedSystem(predator_prey, 2, state_names=["prey", "predator"], correction_outputs=[1])
    with pytest.warns(tms.TorchMisspecWarning, match=r"component 'prey' is never observed in any experiment.*start"):
        gp = tms.fit_correction(data, system, progress=False)
    assert torch.allclose(gp.initial_states_[:, 0], y0[:, 0], rtol=0.05)  # recovered through the predator


def test_the_guess_of_a_component_never_observed_is_the_data_scale():
    """Without a system (CorrectedODE.initial_states, calibrate) the guess is made and said; with one, a component
    that drives no measured component is still refused (nothing could estimate it; test_partial has that case)."""
    from torchmisspec.learning.refinement import partial

    t = torch.linspace(0, 1, 5, dtype=DT)
    y = torch.stack([torch.full((5,), float("nan"), dtype=DT), torch.linspace(-2.0, 4.0, 5, dtype=DT)], -1)[None]
    data = tms.Trajectories(t, y, state_names=["prey", "predator"])
    with pytest.warns(tms.TorchMisspecWarning, match=r"'prey' is never observed .* start at 2 \(the mean magnitude"):
        guess = partial.initial_guess(data)
    assert guess.tolist() == [[2.0, -2.0]]  # |-2|, |-0.5|, |1|, |2.5|, |4|
    lonely = tms.MisspecifiedSystem(lambda z: -z, 2, state_names=["prey", "predator"])  # prey drives nothing
    with pytest.raises(
        tms.InputError, match=r"'prey' is never observed .* drives no measured component through the known model"
    ):
        partial.initial_guess(data, lonely)


def test_the_refined_feature_model_is_the_fitted_one_with_fewer_samples_than_terms(one_thread, monkeypatch):
    """Relevance through the ODE on 6 samples of a degree-3 feature kernel in 2 states (10 terms): the pseudo-targets
    at the 6 samples alone could not carry the fitted coefficients (on the influenza data, 12 days and 20 terms, the
    model returned differed from the fitted one by 1e4 and its paths blew up); inputs are added until they can, so
    the returned model's paths fit the data at least as well as the start's."""
    truth = tms.MisspecifiedSystem(predator_prey, 2)
    t = torch.linspace(0, 5, 6, dtype=DT)
    data = tms.simulate(truth, torch.tensor([[1.5, 1.0]], dtype=DT), t)
    system = tms.MisspecifiedSystem(lambda y: 0.9 * predator_prey(y), 2)
    samples = tms.correction_samples(data, system, derivative="central")
    gp = tms.CorrectionGP(kernel="features", degree=3, per_output=True).fit(samples)
    # the relevance rounds' own model (its sparse rival, torchmisspec.learning.refinement._term_price, has fewer terms
    # than samples)
    monkeypatch.setattr(tms.learning.refinement.trajectory_fit, "_sparser", lambda refined, *args: refined)
    refined = tms.fit_trajectories(gp, system, data, max_iter=10)

    def misfit(model, y0):
        return float(tms.trajectory_rmse(tms.CorrectedODE(system, model).predict(y0, t), data.states))

    # before: the returned model's paths stalled (IntegrationError); measured now 2.5e-5 against 0.13
    assert misfit(refined, refined.initial_states_) <= misfit(gp, data.initial_conditions)
    assert refined.train_inputs_.shape[0] > samples.inputs.shape[0]  # inputs added to carry the 10 terms


def test_a_refinement_that_cannot_be_integrated_keeps_the_chosen_model(one_thread, monkeypatch):
    """The lynx data, origin 1908: the partly measured fit's last step (the chosen model refined through the ODE)
    could not be integrated even from G alone, and the IntegrationError ended the default fit; the chosen model is
    kept unrefined, with a warning."""
    truth = tms.MisspecifiedSystem(predator_prey, 2, state_names=["prey", "predator"])
    t = torch.linspace(0, 6, 13, dtype=DT)
    y = tms.simulate(truth, torch.tensor([[1.5, 1.0], [1.0, 0.6]], dtype=DT), t).states.clone()
    y[..., 0] = float("nan")
    data = tms.Trajectories(t, y, state_names=["prey", "predator"])
    system = tms.MisspecifiedSystem(predator_prey, 2, state_names=["prey", "predator"], correction_outputs=[1])
    from torchmisspec.learning.refinement import partial

    def fails(*args, **kwargs):
        raise tms.IntegrationError("fit_trajectories: the solver stalled (made to fail)")

    monkeypatch.setattr(partial, "fit_trajectories", fails)
    with pytest.warns(tms.TorchMisspecWarning, match="refinement of the chosen model through the ODE failed.*kept"):
        # a model of the user's (the default one would be the known model alone here: the data are G's own)
        gp = tms.fit_correction(data, system, progress=False, refine=True, gp=tms.CorrectionGP(lengthscale=1.0))
    assert gp.initial_states_.shape == (2, 2) and bool(torch.isfinite(gp.initial_states_).all())
