"""fit_trajectories: multiple shooting under the GP prior lowers the misfit and recovers F better than the
derivative-based fit it starts from."""

import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.refinement.trajectory_fit import shooting_misfit

DT = torch.float64


@pytest.fixture(scope="module")
def problem(fast_linear):
    """A faster linear system than the paper's with a larger quadratic F; 8 noise-free experiments, T = 11."""
    system, traj = fast_linear(8)
    samples = tms.correction_samples(traj, system, derivative="central", order=2)  # biased at this spacing
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=0.1, noise_variance=1e-4).fit(samples.inputs, samples.targets)
    return system, traj, gp


def test_misfit_falls_and_the_correction_improves(problem, one_thread):
    system, traj, gp = problem
    before = (shooting_misfit(gp, system, traj), tms.correction_error(gp, system))
    refined = tms.fit_trajectories(gp, system, traj)
    after = (shooting_misfit(refined, system, traj), tms.correction_error(refined, system))
    assert after[0] < 0.5 * before[0]  # measured: 4.5e-4 -> 1.1e-4
    assert after[1] < 0.8 * before[1]  # measured: 0.051 -> 0.030 (integrated error of F_hat over D)
    # hyperparameters are fixed, the input GP is untouched, the result predicts with CorrectedODE
    assert (refined.lengthscale, refined.outputscale, refined.noise_variance) == pytest.approx((1.0, 0.1, 1e-4))
    assert shooting_misfit(gp, system, traj) == before[0]
    assert 1 <= refined.n_iterations_ <= refined.n_evaluations_
    assert refined.n_rhs_evaluations_ >= 6 * refined.n_evaluations_  # dopri5: at least one step per solve
    pred = tms.CorrectedODE(system, refined).predict(traj.initial_conditions, traj.times)
    assert tms.trajectory_rmse(pred, traj.states) < tms.trajectory_rmse(
        tms.CorrectedODE(system, gp).predict(traj.initial_conditions, traj.times), traj.states
    )


def test_a_starting_correction_that_blows_up_is_replaced_or_refused(problem):
    """A start that cannot be integrated is shrunk towards the known model alone (issue 41, item 3: a fit through
    the ODE never ends on a failed solve); only where even G alone cannot be integrated is there nothing to fall
    back on (a budget of 1 step)."""
    system, traj, _ = problem
    x = system.select_inputs(traj.states).reshape(-1, 2)
    wild = tms.CorrectionGP(lengthscale=1.0, outputscale=1e6, noise_variance=1e-4).fit(x, 1e4 * x.pow(2))
    for shooting in ("single", "multiple"):
        with pytest.warns(tms.TorchMisspecWarning, match="the starting correction cannot be integrated"):
            refined = tms.fit_trajectories(wild, system, traj, max_steps=20, shooting=shooting, max_iter=3)
        assert bool(torch.isfinite(refined.train_targets_).all())
        with pytest.raises(tms.IntegrationError, match="nor any smaller one down to the known model alone"):
            tms.fit_trajectories(wild, system, traj, max_steps=1, shooting=shooting)


def test_a_trial_step_that_blows_up_keeps_the_best_iterate(problem):
    """The start integrates (200 steps are enough), a line-search trial does not: the fit stops with a warning and
    returns the best correction found instead of failing."""
    system, traj, _ = problem
    x = system.select_inputs(traj.states).reshape(-1, 2)
    wild = tms.CorrectionGP(lengthscale=1.0, outputscale=1e6, noise_variance=1e-4).fit(x, 1e4 * x.pow(2))
    with pytest.warns(tms.TorchMisspecWarning, match=r"a trial step of the optimiser made the corrected ODE blow up"):
        refined = tms.fit_trajectories(wild, system, traj, max_steps=200)
    assert refined.is_fitted and bool(torch.isfinite(refined.train_targets_).all())


def test_bad_input(problem):
    system, traj, gp = problem
    with pytest.raises(tms.NotFittedError, match="expected a fitted CorrectionGP"):
        tms.fit_trajectories(tms.CorrectionGP(), system, traj)
    with pytest.raises(tms.InputError, match="trajectories: expected a torchmisspec Trajectories object, got Tensor"):
        tms.fit_trajectories(gp, system, traj.states)
    with pytest.raises(tms.InputError, match="at least 2 times per experiment"):
        tms.fit_trajectories(gp, system, tms.Trajectories(traj.times[:1], traj.states[:, :1]))
    with pytest.raises(tms.InputError, match="state_noise: expected a positive finite number"):
        tms.fit_trajectories(gp, system, traj, state_noise=-1.0)


def test_known_per_sample_noise_stays_part_of_the_prior(problem, one_thread):
    system, traj, _ = problem
    samples = tms.correction_samples(traj, system, derivative="gp")  # carries the GP-in-time variances
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=0.1, noise_variance=1e-6).fit(samples)
    refined = tms.fit_trajectories(gp, system, traj, max_iter=5)
    torch.testing.assert_close(refined.train_noise_, gp.train_noise_, rtol=0, atol=0)
    assert shooting_misfit(refined, system, traj) <= shooting_misfit(gp, system, traj)


def test_batched_jacobian_columns_equal_one_solve_per_column():
    """The Gauss-Newton Jacobian of the feature coefficients: every perturbed model in one batched solve (ragged
    experiments included) gives the columns of one solve per perturbation, to solver tolerance."""
    from torchmisspec.gp._features import FeatureKernel
    from torchmisspec.learning.refinement import _jacobian as tm
    from torchmisspec.learning.refinement import trajectory_fit as tf

    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(0)
    y0 = torch.rand(3, 2, generator=g, dtype=torch.float64) * 2 - 1
    full = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=torch.float64))
    ragged = tms.Trajectories(
        [full.times[: 11 - 2 * k] for k in range(3)], [full.states[k, : 11 - 2 * k] for k in range(3)]
    )
    residuals, _, offsets = tf._shooting(ragged, "single", dict(rtol=1e-10, atol=1e-12, what="test"), system)
    features = FeatureKernel(2, 2).to(torch.float64).features
    p = features(y0).shape[1]
    beta = 0.01 * torch.randn(p, 2, generator=g, dtype=torch.float64)
    active = torch.rand(p, 2, generator=g) > 0.3

    def make_field(b):
        return lambda y, t=None, u=None: system.known_rhs(y) + features(y) @ b  # rhs(y, t, u)

    def make_fields(bs):
        def field(y, t=None, u=None):
            f = features(y).reshape(bs.shape[0], -1, p)
            return system.known_rhs(y) + torch.einsum("mkp,mpo->mko", f, bs).reshape(y.shape[0], -1)

        return field

    sd = torch.full((2,), 1e-2, dtype=torch.float64)
    off = 0.1 * torch.randn(offsets.shape, generator=g, dtype=torch.float64)
    one = tm._coefficient_columns(residuals, make_field, beta, active, off, sd)
    batched = tm._coefficient_columns(residuals, make_field, beta, active, off, sd, make_fields)
    assert one.shape == batched.shape == (ragged.num_samples * 2, int(active.sum()))
    torch.testing.assert_close(batched, one, rtol=1e-5, atol=1e-6 * float(one.abs().max()))
    # the offsets' and parameters' columns: tests/test_trial_budget.py (the joint Jacobian)
