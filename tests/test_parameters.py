"""Uncertain parameters of G: the closed-form posterior against brute force, and the fit on a damped oscillator."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.theta.closed_form import condition_with_parameters, parameter_posterior, posterior_given
from torchmisspec.parameters import ParameterPosterior, check_priors, parameter_basis

D = torch.float64


def _gp(X, Y):
    return tms.CorrectionGP(lengthscale=0.7, outputscale=0.5, noise_variance=0.01).fit(X, Y)


def _brute(gp, X, residuals, basis, outputs, prior_mean, prior_sd, other_var):
    """Everything stacked: r (over samples and components) ~ N(0, C + H S H^T), C the GP's block on the corrected
    components and other_var on the others; a hand-written Gaussian conditioning."""
    N, d, k = basis.shape
    comps = list(outputs) + [j for j in other_var]
    blocks = []
    K = gp.covar_module(X, X).to_dense().detach() + gp.noise_variance * torch.eye(N, dtype=D)
    for j in comps:
        blocks.append(K if j in outputs else other_var[j] * torch.eye(N, dtype=D))
    C = torch.block_diag(*blocks)
    H = torch.cat([basis[:, j, :] for j in comps])  # (N * c, k)
    r = torch.cat([residuals[:, j] for j in comps])
    S = torch.diag(prior_sd**2)
    total = C + H @ S @ H.T
    L = torch.linalg.cholesky(total)
    solve = torch.cholesky_solve(r[:, None], L)[:, 0]
    mean = prior_mean + S @ H.T @ solve
    cov = S - S @ H.T @ torch.cholesky_solve(H @ S, L)
    evidence = torch.distributions.MultivariateNormal(torch.zeros_like(r), scale_tril=L).log_prob(r)
    return mean, cov, evidence, total, r, H, K


@pytest.fixture
def problem():
    g = torch.Generator().manual_seed(3)
    N, d, k = 30, 3, 2
    X = torch.rand(N, 1, generator=g, dtype=D) * 4 - 2
    basis = torch.randn(N, d, k, generator=g, dtype=D)
    basis[:, 2, :] = 0  # a component G does not make depend on theta: ignored
    residuals = torch.randn(N, d, generator=g, dtype=D) * 0.3 + torch.sin(2 * X)
    priors = check_priors({"a": (0.5, 0.3), "b": (-1.0, 2.0)})
    return X, residuals, basis, priors


def test_closed_form_posterior_and_evidence_match_brute_force(problem):
    X, residuals, basis, priors = problem
    gp = _gp(X, residuals[:, [1]])
    delta = torch.tensor([0.1, -0.2], dtype=D)
    post = parameter_posterior(gp, residuals, basis, [1], priors, delta)
    other = {0: float(((residuals[:, 0] - basis[:, 0] @ delta) ** 2).sum()) / (X.shape[0] - 2)}
    mean, cov, evidence, *_ = _brute(gp, X, residuals, basis, [1], priors.mean, priors.scale, other)
    torch.testing.assert_close(post.mean, mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(post.covariance, cov, rtol=1e-8, atol=1e-12)
    assert post.log_evidence == pytest.approx(float(evidence), rel=1e-10)
    # no correction at all: the noise alone (the GP's noise on the corrected component)
    _, cov0, *_ = _brute(
        tms.CorrectionGP(lengthscale=0.7, outputscale=1e-300, noise_variance=0.01).fit(X, residuals[:, [1]]),
        X,
        residuals,
        basis,
        [1],
        priors.mean,
        priors.scale,
        other,
    )
    torch.testing.assert_close(post.sd_without_correction, cov0.diagonal().sqrt(), rtol=1e-6, atol=1e-12)


def test_f_posterior_with_theta_integrated_matches_brute_force(problem):
    """Conditioning F on r - H theta_bar gives the mean of F given r with theta integrated out, and the GP's
    covariance plus M A^-1 M^T (M: F's absorption of each basis, what the draws use) its covariance."""
    X, residuals, basis, priors = problem
    basis = basis[:, [1], :]  # F acts on the only component: every component is F's
    residuals = residuals[:, [1]]
    gp = _gp(X, residuals)
    declared = SimpleNamespace(parameters=priors, correction_outputs=[0])  # what the closed form reads of a system
    conditioned, _ = condition_with_parameters(gp, _samples(X, residuals, basis), declared)
    post = conditioned.parameters_
    mean, cov, _, total, r, H, K = _brute(gp, X, residuals, basis, [0], priors.mean, priors.scale, {})
    xs = torch.linspace(-2.5, 2.5, 7, dtype=D)[:, None]
    Ks = gp.covar_module(xs, X).to_dense().detach()
    L = torch.linalg.cholesky(total)
    f_mean = Ks @ torch.cholesky_solve(r[:, None], L)[:, 0]  # r: residuals at the prior mean
    f_cov = gp.covar_module(xs, xs).to_dense().detach() - Ks @ torch.cholesky_solve(Ks.T, L)
    torch.testing.assert_close(conditioned.predict_mean(xs)[:, 0], f_mean, rtol=1e-8, atol=1e-10)
    M = post.draw_terms(conditioned)(xs)[:, 0, :]  # (M, k)
    cov_draws = _gp_cov(conditioned, xs)
    torch.testing.assert_close(cov_draws + M @ post.covariance @ M.T, f_cov, rtol=1e-7, atol=1e-10)
    torch.testing.assert_close(post.mean, mean, rtol=1e-9, atol=1e-10)


def _gp_cov(gp, xs):
    out = gp.posterior().covariance(xs)
    return out.reshape(xs.shape[0], xs.shape[0], -1)[..., 0] if out.dim() == 3 else out


def _samples(X, residuals, basis):
    return tms.CorrectionSamples(
        inputs=X,
        targets=residuals.clone(),
        states=X,
        experiment=torch.zeros(X.shape[0], dtype=torch.long),
        residuals=residuals,
        basis=basis,
    )


def test_priors_and_linearity_are_checked():
    with pytest.raises(tms.InputError, match="value, scale"):
        check_priors({"a": 0.3})
    with pytest.raises(
        tms.InputError, match="scale .the prior standard deviation.: expected a positive finite number, got 0"
    ):
        check_priors({"a": (0.3, 0.0)})
    with pytest.raises(tms.InputError, match="non-empty mapping"):
        check_priors([("a", (0.3, 0.1))])
    y = torch.rand(10, 2, dtype=D)
    theta, scale = torch.tensor([1.0, 2.0], dtype=D), torch.tensor([0.1, 0.2], dtype=D)
    basis, linear = parameter_basis(lambda th: torch.stack([th[0] * y[:, 0], th[1] * y[:, 1] ** 2], -1), theta, scale)
    assert linear
    torch.testing.assert_close(basis[:, 0, 0], y[:, 0])
    torch.testing.assert_close(basis[:, 1, 1], y[:, 1] ** 2)
    # nonlinear in a, then in the pair (a, b) only: the Jacobian at theta, by hand
    basis, linear = parameter_basis(lambda th: torch.stack([th[0] ** 2 * y[:, 0], th[1] * y[:, 1]], -1), theta, scale)
    assert not linear
    torch.testing.assert_close(basis[:, 0, 0], 2 * theta[0] * y[:, 0])
    torch.testing.assert_close(basis[:, 1, 1], y[:, 1])
    basis, linear = parameter_basis(lambda th: torch.stack([th[0] * th[1] * y[:, 0], y[:, 1]], -1), theta, scale)
    assert not linear
    torch.testing.assert_close(basis[:, 0, :], torch.stack([theta[1] * y[:, 0], theta[0] * y[:, 0]], -1))


# ------------------------------------------------------------------------------- the fit on a damped oscillator
def _oscillator(c: float, absorb: bool):
    """x' = v, v' = -x - c v + F: F(x) a missing force (identifiable), or F(v) a drag that can absorb c v."""
    inputs = [1] if absorb else [0]

    def G(y, theta):
        return torch.stack([y[..., 1], -y[..., 0] - theta[0] * y[..., 1]], -1)

    def F(x):
        return -0.3 * x**3 if absorb else -0.5 * torch.sin(2 * x)

    truth = tms.MisspecifiedSystem(
        lambda y: G(y, torch.tensor([c], dtype=D)), 2, correction=F, correction_inputs=inputs, correction_outputs=[1]
    )
    system = tms.MisspecifiedSystem(
        G, 2, correction_inputs=inputs, correction_outputs=[1], parameters={"c": (1.3 * c, 0.5 * c)}
    )
    return truth, system


def _oscillator_time_constant(tau: float):
    """The damped oscillator with its damping given by a time constant: v' = -x - v / tau + F(x), nonlinear in tau."""

    def G(y, theta):
        return torch.stack([y[..., 1], -y[..., 0] - y[..., 1] / theta[0]], -1)

    def F(x):
        return -0.5 * torch.sin(2 * x)

    truth = tms.MisspecifiedSystem(
        lambda y: G(y, torch.tensor([tau], dtype=D)), 2, correction=F, correction_inputs=[0], correction_outputs=[1]
    )
    system = tms.MisspecifiedSystem(
        G, 2, correction_inputs=[0], correction_outputs=[1], parameters={"tau": (1.3 * tau, 0.5 * tau)}
    )
    return truth, system


def _data(truth, seed, K=8):
    g = torch.Generator().manual_seed(seed)
    y0 = torch.rand(K, 2, generator=g, dtype=D) * 4 - 2
    t = torch.linspace(0, 6, 25, dtype=D)
    clean = tms.simulate(truth, y0, t)
    return tms.Trajectories(t, clean.states + 0.01 * torch.randn(clean.states.shape, generator=g, dtype=D))


@pytest.mark.parametrize("nonlinear", [False, True], ids=["damping c (linear)", "time constant 1/c (nonlinear)"])
def test_damping_is_recovered_predicts_as_well_as_known_and_persists(tmp_path, nonlinear):
    """The damping as a rate c (G linear in it: the closed form) or as a time constant tau = 1 / c (nonlinear: the
    MAP and its Laplace posterior): recovered within 2 posterior sd, far inside the prior, identified without a
    warning; predictions near the truth, kept exactly by save/load; band draws carry theta's posterior."""
    truth, system = _oscillator_time_constant(1 / 0.3) if nonlinear else _oscillator(0.3, absorb=False)
    true = 1 / 0.3 if nonlinear else 0.3
    data = _data(truth, 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)  # identified: no warning
        gp = tms.fit_correction(data, system, progress=False)
    post = gp.parameters_
    assert post.linear is not nonlinear and post.identified == (True,)
    assert abs(float(post.mean[0]) - true) <= 2 * float(post.stddev[0])
    assert float(post.stddev[0]) < 0.1 * float(post.prior_scale[0])  # far inside the prior
    model = tms.CorrectedODE(system, gp)
    g = torch.Generator().manual_seed(9)
    y0 = torch.rand(10, 2, generator=g, dtype=D) * 4 - 2
    t = torch.linspace(0, 6, 25, dtype=D)
    ref = tms.simulate(truth, y0, t).states
    known_error = tms.trajectory_rmse(tms.simulate(system, y0, t, known_only=True).states, ref)
    assert tms.trajectory_rmse(model.predict(y0, t), ref) <= 0.1 * known_error
    gp.save(tmp_path / "m.pt")
    loaded = tms.CorrectionGP.load(tmp_path / "m.pt")
    assert loaded.parameters_.linear is post.linear
    torch.testing.assert_close(loaded.parameters_.covariance, post.covariance, rtol=0, atol=0)
    torch.testing.assert_close(tms.CorrectedODE(system, loaded).predict(y0, t), model.predict(y0, t))
    bands = model.posterior(y0[:3], t, num_samples=16, scale=1.0, generator=torch.Generator().manual_seed(1))
    assert bool(torch.isfinite(bands.samples).all())


def test_oscillator_damping_absorbed_by_a_drag_is_reported():
    truth, system = _oscillator(0.3, absorb=True)
    with pytest.warns(tms.TorchMisspecWarning, match=r"c: posterior sd .* F can absorb its effect"):
        gp = tms.fit_correction(_data(truth, 1), system, progress=False)
    post = gp.parameters_
    assert post.identified == (False,)
    assert float(post.sd_without_correction[0]) < 0.5 * float(post.prior_scale[0])
    assert "NOT identified" in post.summary()


# ------------------------------------------------------------------------------- G nonlinear in theta
def test_nonlinear_parameter_map_and_laplace_match_brute_force():
    """For a G nonlinear in theta and fixed hyperparameters, Gauss-Newton's mean is the maximum of
    log N(r(theta); 0, C) + log N(theta; m, s^2) found on a grid, and its variance the Laplace one, 1 / (1/s^2 +
    J^T C^-1 J) with J = dr/dtheta at the maximum by differences of the residuals themselves."""
    truth, system = _oscillator_time_constant(1 / 0.3)
    samples = tms.correction_samples(_data(truth, 3), system, derivative="gp")
    assert not samples.parameters_linear
    gp = tms.CorrectionGP(lengthscale=0.7, outputscale=0.3, noise_variance=1e-3).fit(samples.inputs, samples.targets)
    post, linearized = posterior_given(gp, samples, system)
    assert not post.linear
    dydt = samples.residuals + system.known_rhs(samples.states)
    m, s = float(system.parameters.mean[0]), float(system.parameters.scale[0])
    exact = gp.posterior()

    def log_density(tau: float) -> float:
        r = dydt - system.at([tau]).known_rhs(samples.states)
        return exact.with_targets(r[:, [1]]).log_marginal_likelihood - 0.5 * (tau - m) ** 2 / s**2

    grid = torch.linspace(m - 4 * s, m + 4 * s, 801, dtype=D)
    best = float(grid[int(torch.tensor([log_density(float(v)) for v in grid]).argmax())])
    fine = torch.linspace(best - 0.02 * s, best + 0.02 * s, 401, dtype=D)
    best = float(fine[int(torch.tensor([log_density(float(v)) for v in fine]).argmax())])
    assert float(post.mean[0]) == pytest.approx(best, abs=2e-4 * s)
    h = 1e-5 * s
    J = (system.at([best - h]).known_rhs(samples.states) - system.at([best + h]).known_rhs(samples.states))[:, 1] / (
        2 * h
    )  # dr/dtheta on the corrected component (the other does not depend on tau)
    info = float(J @ exact.with_targets(J[:, None]).weights[:, 0])
    assert float(post.covariance[0, 0]) == pytest.approx(1 / (1 / s**2 + info), rel=1e-3)
    # the samples come back linearised at the mean: their targets are r at it
    r = dydt - system.at(post.mean).known_rhs(samples.states)
    torch.testing.assert_close(linearized.targets, r[:, [1]])


def test_prior_only_model_and_refusals():
    truth, system = _oscillator(0.3, absorb=False)
    data = _data(truth, 2, K=4)
    plain = tms.fit_correction(data, system.at([0.39]), select="evidence", progress=False)  # theta fixed
    model = tms.CorrectedODE(system, plain)  # not fitted with theta: the prior, nothing absorbed
    assert isinstance(model.parameters_, ParameterPosterior)
    torch.testing.assert_close(model.parameters_.mean, system.parameters.mean)
    assert math.isnan(model.parameters_.log_evidence)
    # each draw of the bands is a draw of theta too: wider than with theta fixed at the same value
    y0, t = torch.tensor([[1.0, 0.5]], dtype=D), torch.linspace(0, 4, 9, dtype=D)
    kw = dict(num_samples=32, scale=1.0)
    spread = model.posterior(y0, t, generator=torch.Generator().manual_seed(0), **kw).stddev
    fixed = tms.CorrectedODE(system.at([0.39]), plain).posterior(
        y0, t, generator=torch.Generator().manual_seed(0), **kw
    )
    assert float(spread[0, -1].norm()) > 3 * float(fixed.stddev[0, -1].norm())
    # refine=True: F refined through the ODE at theta's mean, after theta's fit; theta's posterior kept
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        plain_fit = tms.fit_correction(data, system, progress=False)
        refined = tms.fit_correction(data, system, refine=True, progress=False)
    assert refined.refinement_ is not None and plain_fit.refinement_ is None
    torch.testing.assert_close(refined.parameters_.mean, plain_fit.parameters_.mean)
    assert not torch.equal(refined.train_targets_, plain_fit.train_targets_)
    # its calibration folds refine F the same way at their own theta, which they keep (not the prior)
    seen = []
    original = tms.prediction.calibration.fit_trajectories

    def spy(gp, system, *args, **kw):
        seen.append(system.parameters is None)
        return original(gp, system, *args, **kw)

    tms.prediction.calibration.fit_trajectories = spy
    try:
        tms.CorrectedODE(system, refined).calibrate(data, folds=2, progress=False)
    finally:
        tms.prediction.calibration.fit_trajectories = original
    assert seen and all(seen)  # each fold's F refined with theta fixed at the fold's estimate
    with pytest.raises(tms.InputError, match=r"system.at\(gp.parameters_.mean\)"):
        tms.fit_trajectories(refined, system, data)  # G would run at the prior mean: refused, with the fix
    with pytest.raises(tms.InputError, match="expected a system with uncertain parameters to fix, got one without"):
        truth.at([0.3])
    with pytest.raises(tms.ShapeError, match="one value per parameter"):
        system.at([0.3, 0.1])


OSCILLATOR_FILE = """
import torch
from torchmisspec import MisspecifiedSystem

def oscillator():
    # damping c known only roughly; a restoring force missing from dv/dt, a function of x
    return MisspecifiedSystem(
        lambda y, theta: torch.stack([y[..., 1], -y[..., 0] - theta[0] * y[..., 1]], -1), 2,
        state_names=["x", "v"], parameters={"c": (0.4, 0.2)}, correction_inputs=["x"], correction_outputs=[1],
        name="oscillator",
    )
"""


def test_a_lab_csv_of_a_system_with_an_uncertain_parameter_through_the_cli(tmp_path, capsys):
    """The scientist's loop on the command line with the defaults: a ragged, irregular, noisy CSV with named
    columns; the system file declares the parameter; fit prints its posterior, predict and design use it."""
    from torchmisspec.cli import main

    truth, _ = _oscillator(0.3, absorb=False)
    g = torch.Generator().manual_seed(4)
    rows = ["trial,seconds,x,v"]
    for k in range(8):
        n = int(torch.randint(15, 26, (1,), generator=g))
        t = torch.sort(torch.rand(n, generator=g, dtype=D) * 6).values
        t[0] = 0.0
        y = tms.simulate(truth, torch.rand(1, 2, generator=g, dtype=D) * 4 - 2, t).states[0]
        y = y + 0.01 * torch.randn(y.shape, generator=g, dtype=D)
        rows += [f"T{k},{float(t[i]):.4f},{float(y[i, 0]):.6g},{float(y[i, 1]):.6g}" for i in range(n)]
    (tmp_path / "lab.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "osc.py").write_text(OSCILLATOR_FILE)
    (tmp_path / "initial.csv").write_text("x,v\n1.5,-0.5\n-1.0,1.2\n")
    (tmp_path / "candidates.csv").write_text(
        "x,v\n" + "\n".join(f"{a},{b}" for a in (-2, 0, 2) for b in (-1, 1)) + "\n"
    )
    system = f"{tmp_path / 'osc.py'}:oscillator"
    model = str(tmp_path / "m.pt")
    fit = ["fit", "--data", str(tmp_path / "lab.csv"), "--system", system, "--experiment-column", "trial"]
    assert main([*fit, "--time-column", "seconds", "--out", model, "--no-calibrate", "--quiet"]) == 0
    out = capsys.readouterr().out
    line = next(s for s in out.splitlines() if s.strip().startswith("c = "))
    mean, sd = float(line.split()[2]), float(line.split()[4])
    # recovered to a tenth of the prior's sd (whether its own sd covers the error is the study's measure)
    assert abs(mean - 0.3) < 0.02 and sd < 0.05 and "NOT identified" not in line
    choice = next(s for s in out.splitlines() if s.startswith("cross-validation"))  # both known-model scores
    assert (
        "at the parameters fitted with the correction" in choice and "with its own parameters fitted (F = 0)" in choice
    )
    assert tms.CorrectionGP.load(model).parameters_.names == ("c",)
    pred = tmp_path / "pred.csv"
    predict = ["predict", "--model", model, "--system", system, "--initial", str(tmp_path / "initial.csv")]
    assert main([*predict, "--times", "0:6:13", "--out", str(pred), "--quiet"]) == 0
    assert len(pred.read_text().splitlines()) == 1 + 2 * 13
    design = ["design", "--model", model, "--system", system, "--candidates", str(tmp_path / "candidates.csv")]
    assert main([*design, "--times", "0:6:13", "--budget", "2", "--out", str(tmp_path / "next.csv"), "--quiet"]) == 0
    assert len((tmp_path / "next.csv").read_text().splitlines()) == 3


def test_a_campaign_refuses_uncertain_parameters_without_their_estimate_with_the_fix():
    _, system = _oscillator(0.3, absorb=False)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=0.1, noise_variance=1e-4)
    with pytest.raises(tms.InputError, match=r"start the campaign from fit_correction.*Campaign\(system.at\(theta\)"):
        tms.design.Campaign(system, torch.rand(5, 2, dtype=D), torch.linspace(0, 1, 5, dtype=D), gp)
    assert tms.parameters.ParameterPosterior is ParameterPosterior


def test_sd_with_a_larger_correction_matches_brute_force(problem):
    """``sd_larger_correction`` (issue 42, item 3): theta's posterior sd with F's prior variance LARGER_CORRECTION
    times the fitted one or what 2 prior sd of a parameter make to G, whichever is larger, against the hand-written
    Gaussian conditioning with that K; near the prior's where F can
    stand in for the parameter (a basis that is a smooth function of F's input alone), well inside it where the
    basis also moves a component F does not act on."""
    from torchmisspec.parameters import LARGER_CORRECTION

    X, residuals, basis, priors = problem
    gp = _gp(X, residuals[:, [1]])
    post = parameter_posterior(gp, residuals, basis, [1], priors)
    other = {0: float((residuals[:, 0] ** 2).sum()) / (X.shape[0] - 2)}
    K = gp.covar_module(X, X).to_dense().detach()
    H1, H0 = basis[:, 1, :], basis[:, 0, :]
    size = K.diagonal().mean()
    a = max(LARGER_CORRECTION * size, 4 * float((priors.scale**2 * H1.pow(2).mean(0)).max()))
    C = a * K / size + gp.noise_variance * torch.eye(X.shape[0], dtype=D)
    info = H1.T @ torch.linalg.solve(C, H1) + H0.T @ H0 / other[0]
    want = torch.linalg.inv(torch.diag(priors.scale**-2) + info).diagonal().sqrt()
    torch.testing.assert_close(post.sd_larger_correction, want, rtol=1e-6, atol=1e-12)
    smooth = torch.cat([X, 0.5 * X**2], dim=1).unsqueeze(1)  # (N, 1, 2): functions of F's input
    alone = parameter_posterior(gp, residuals[:, [1]], smooth, [0], priors)
    assert bool((alone.sd_larger_correction > 0.5 * priors.scale).all()) and alone.identified == (False, False)


def _posterior(mean, sd, larger):
    one = torch.ones(1, dtype=D)
    return ParameterPosterior(
        names=("half_life",),
        prior_mean=20.0 * one,
        prior_scale=5.0 * one,
        mean=mean * one,
        covariance=(sd**2) * one[:, None],
        sd_without_correction=0.5 * one,
        log_evidence=0.0,
        basis_targets=torch.zeros(3, 1, 1, dtype=D),
        sd_larger_correction=None if larger is None else larger * one,
    )


def test_an_absorbable_parameter_is_not_identified_whatever_its_width():
    """Issue 42, item 3: a half-life that F can stand in for, estimated 9 +- 2.3 against a prior of 20 +- 5 (the
    Laplace width of a parameter entering as 1 / theta shrinks as it drifts low; with F = 0 returned, the parameter
    takes up the missing term), is reported not identified, and the message says where the estimate went; the same
    width for a parameter F cannot absorb is identified."""
    drifted = _posterior(9.0, 2.3, 4.5)
    assert drifted.identified == (False,)
    (problem,) = drifted.problems()
    assert "estimate 9 +- 2.3, 2.2 prior sd from its prior 20 +- 5" in problem
    assert "larger would leave it at 0.90 of the prior's sd" in problem and "not evidence" in problem
    assert _posterior(19.0, 2.3, 4.5).identified == (False,)  # near its prior too: the data cannot say where it is
    assert _posterior(9.0, 2.3, 2.4).identified == (True,)  # a larger F could not stand in for it: the data moved it
    assert _posterior(9.0, 2.3, None).identified == (True,)  # not computed (a record from before): width alone
    wide = _posterior(12.0, 4.0, 4.5)
    assert wide.identified == (False,) and "posterior sd 0.80 of the prior's (estimate 12 +- 4" in wide.problems()[0]


def test_what_a_correction_could_absorb_stays_on_record():
    """``absorbing``: the known model alone returned (F = 0 absorbs nothing) keeps what the candidates' F could
    absorb, so a parameter that took up the missing term is not reported identified."""
    known = _posterior(11.6, 0.6, 0.6)
    assert known.identified == (True,)
    kept = known.absorbing(_posterior(12.0, 2.0, 4.0))
    assert kept.identified == (False,) and float(kept.sd_larger_correction) == pytest.approx(4.0)
    assert known.absorbing(None) is known and known.absorbing(_posterior(12.0, 2.0, None)) is known
    got = _posterior(11.6, 0.6, None).absorbing(_posterior(12.0, 2.0, 3.0)).sd_larger_correction
    assert float(got) == pytest.approx(3.0)


def test_sd_larger_correction_round_trips_through_the_record():
    post = _posterior(9.0, 2.3, 4.5)
    back = ParameterPosterior.from_dict(
        post.to_dict(), "m.pt", num_samples=3, output_dim=1, like=torch.zeros(1, dtype=D)
    )
    torch.testing.assert_close(back.sd_larger_correction, post.sd_larger_correction)
    old = {key: v for key, v in post.to_dict().items() if key != "sd_larger_correction"}
    assert (
        ParameterPosterior.from_dict(old, "m.pt", num_samples=3, output_dim=1, like=torch.zeros(1)).sd_larger_correction
        is None
    )
    with pytest.raises(tms.InputError, match="'sd_larger_correction'"):
        ParameterPosterior.from_dict(
            {**post.to_dict(), "sd_larger_correction": torch.ones(2)},
            "m.pt",
            num_samples=3,
            output_dim=1,
            like=torch.zeros(1),
        )
