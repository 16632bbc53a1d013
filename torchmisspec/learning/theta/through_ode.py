"""theta's posterior refined through the ODE: Gauss-Newton on the observed states, with a Laplace posterior.

The closed form of :mod:`torchmisspec.learning.theta.closed_form` treats the derivative samples' errors as independent
noise. They are not: a finite-difference or smoothing estimator errs alike at neighbouring times (and most where an
input jumps), so a parameter fitted to derivative samples can be biased by several of its own standard deviations. The
states themselves carry independent measurement noise. This step takes the closed form's answer as the start and fits
theta to the observed trajectories, with F following theta as the closed form says it does:

    F_theta(x) = F_0(x) - sum_k (theta - theta_0)_k m_k(x)      (F's posterior mean given r - H (theta - m)),

so the corrected model at theta is G(y; theta_0) + F_0(x) + sum_k (theta - theta_0)_k (g_k(y) - m_k(x)): exactly the
right-hand side of a posterior draw (:meth:`ParameterPosterior.draw_field
<torchmisspec.parameters.ParameterPosterior.draw_field>`), so every variant of theta is a row of one batched solve.
Each iteration solves every experiment from its first observed state at theta and at theta + h e_k (a
finite-difference Jacobian J), estimates each component's noise variance from the residuals, and takes a
Gauss-Newton step on

    sum (observed - predicted)^2 / sigma_j^2 + (theta - m)^T S^-1 (theta - m),

with step halving where a trial does not decrease it or cannot be integrated, W = (D + U U^T)^-1 (D the residual
variance of each component, U U^T F's posterior covariance of the trajectories, from draws of F). The posterior's
covariance is the Laplace one, A^-1 = (J^T W J + S^-1)^-1, or, when it is wider on average (trace(A R) > k), the
cluster-robust sandwich over experiments (Liang & Zeger 1986) A^-1 (K / (K - 1) sum_e s_e s_e^T + S^-1) A^-1,
s_e = J_e^T (W r)_e the experiment's score: what F's error leaves in the residuals is shared by the times of an
experiment and is not independent noise, and the sandwich counts it once per experiment instead of once per time
(on the chemostat study the Laplace standard deviations were 2 to 3 times too narrow). F's ability to absorb theta
shows as a small J (the trajectories hardly move when F follows theta), and the posterior stays near the prior, as the
closed form says.
"""

from __future__ import annotations

import dataclasses

import torch

from ..._errors import IntegrationError, LinearAlgebraError, NumericalWarning, warn
from ..._ode import FITTING_TOLERANCES, solve
from .closed_form import condition_with_parameters

__all__ = ["fit_parameters", "refine_through_ode", "ITERATIONS"]

#: most Gauss-Newton iterations (each: one batched solve of the experiments at k + 1 values of theta)
ITERATIONS = 6
#: posterior draws of F whose trajectories give F's covariance in trajectory space
DRAWS = 32
#: the iterations stop once a step moves every parameter by less than this fraction of its standard deviation
CONVERGED = 0.05
_MAX_STEPS = 4000


def _predict(system, gp, posterior, trajectories, thetas: torch.Tensor, draws=None, floor=None) -> torch.Tensor:
    """Every experiment from its first observed state under each of ``thetas`` ``(V, k)``: ``(V, K, T, d)``; with
    ``draws`` (posterior draws of F, ``x (V, K, d_in) -> (V, K, d_out)``) variant v under draw v instead of F's mean;
    ``floor`` the noise model's :meth:`~torchmisspec.noise.NoiseModel.resolution`, the solve's."""
    times, states, _ = trajectories.padded()
    K = states.shape[0]
    V = thetas.shape[0]
    first = trajectories.initial_conditions.to(states)
    times = (times if times.dim() == 2 else times.expand(K, -1)).repeat(V, 1)
    known = posterior.draw_field(system, gp, thetas - posterior.mean, K, with_mean=draws is None)  # F's mean in it

    def rhs(y, t, u):
        x = system.select_inputs(y, u)
        out = known(y, t, u, x)
        if draws is None:
            return out
        return out + system.embed(draws(x.to(gp.device, gp.dtype).reshape(V, K, -1)).reshape(V * K, -1).to(y))

    controls = None if trajectories.controls is None else trajectories.controls.repeat(V)
    field, timed, jumps = system.solver_field(rhs, controls)
    rtol, atol = FITTING_TOLERANCES
    out, _ = solve(
        field,
        first.repeat(V, 1),
        times,
        rtol=rtol,
        atol=atol,
        max_steps=_MAX_STEPS,
        what="the parameters' fit through the ODE",
        floor=floor,
        timed=timed,
        jumps=jumps,
    )
    return out.reshape(V, K, *out.shape[1:])


def _weights(res: torch.Tensor, comp: torch.Tensor, U: torch.Tensor, d: int):
    """``v -> W v``, W = (D + U U^T)^-1 by Woodbury: D each component's residual variance (the measurement noise and
    whatever the model misses), U U^T F's posterior covariance in trajectory space."""
    var = torch.zeros(d, dtype=res.dtype, device=res.device).index_add_(0, comp, res**2)
    count = torch.zeros(d, dtype=res.dtype, device=res.device).index_add_(0, comp, torch.ones_like(res))
    inv = 1 / (var / count.clamp_min(1)).clamp_min(1e-300)[comp]
    L = torch.linalg.cholesky(torch.eye(U.shape[1], dtype=U.dtype, device=U.device) + U.T @ (inv[:, None] * U))

    def apply(v: torch.Tensor) -> torch.Tensor:
        a = inv[:, None] * v
        return a - inv[:, None] * (U @ torch.cholesky_solve(U.T @ a, L))

    return apply


def refine_through_ode(
    system,
    gp,
    trajectories,
    posterior,
    *,
    iterations: int = ITERATIONS,
    num_draws: int = DRAWS,
    generator=None,
    noise=None,
):
    """theta's posterior from the observed states (the module's notes), starting at ``posterior`` (the closed form,
    ``gp`` conditioned at its mean); the residuals those of the :class:`~torchmisspec.noise.NoiseModel` ``noise``
    (default: the differences). Returns the refined :class:`~torchmisspec.parameters.ParameterPosterior`, or
    ``posterior`` unchanged (with a warning) when the trajectories cannot be integrated near it."""
    transform = (lambda y: y) if noise is None else noise.transform
    floor = None if noise is None else noise.resolution(trajectories)
    _, states, mask = trajectories.padded()
    observed = mask.unsqueeze(-1) & ~torch.isnan(states)  # (K, T, d)
    observed[:, 0] = False  # the first state is where each solve starts
    target = transform(states[observed])
    comp = torch.arange(states.shape[-1], device=states.device).expand_as(states)[observed]
    exp = torch.arange(states.shape[0], device=states.device).view(-1, 1, 1).expand_as(states)[observed]
    prior_mean, prior_var = posterior.prior_mean, posterior.prior_scale**2
    step = (0.05 * posterior.stddev).clamp_min(1e-6 * posterior.prior_scale)

    def predict(thetas, draws=None):  # (V, n): the observed entries under each theta
        return transform(_predict(system, gp, posterior, trajectories, thetas, draws, floor)[:, observed])

    def penalty(theta):
        return float(((theta - prior_mean) ** 2 / prior_var).sum())

    theta = posterior.mean.clone()
    d, k = states.shape[-1], posterior.mean.shape[0]

    def variants(theta):  # theta and a step along each parameter: the Jacobian's columns in the same solve
        return predict(torch.cat([theta[None], theta[None] + torch.diag(step)]))

    try:
        # F's posterior in trajectory space: num_draws draws of F at theta_0 (their spread does not depend on theta)
        g = generator if generator is not None else torch.Generator(device=gp.device).manual_seed(0)
        paths = predict(theta.expand(num_draws, -1), gp.sample_functions(num_draws, generator=g))
        U = ((paths - paths.mean(0)) / (num_draws - 1) ** 0.5).T  # (n, S)
        pred = variants(theta)
        for _ in range(iterations):
            res = target - pred[0]
            W = _weights(res, comp, U, d)
            J = ((pred[1:] - pred[0]) / step[:, None]).T  # (n, k)
            WJ = W(J)
            A = J.T @ WJ + torch.diag(1 / prior_var)
            delta = torch.linalg.solve(A, WJ.T @ res - (theta - prior_mean) / prior_var)
            base = float(res @ W(res[:, None])[:, 0]) + penalty(theta)
            accepted = False
            for _ in range(6):  # halve until the penalised misfit decreases
                try:
                    trial = variants(theta + delta)
                    r = target - trial[0]
                    accepted = float(r @ W(r[:, None])[:, 0]) + penalty(theta + delta) < base
                except IntegrationError:
                    accepted = False
                if accepted:
                    break
                delta = delta / 2
            if not accepted:
                break
            theta, pred = theta + delta, trial
            if bool((delta.abs() <= CONVERGED * posterior.stddev).all()):
                break
        # the Laplace posterior at the last point
        res = target - pred[0]
        J = ((pred[1:] - pred[0]) / step[:, None]).T
        W = _weights(res, comp, U, d)
        A = J.T @ W(J) + torch.diag(1 / prior_var)
        cov = torch.cholesky_inverse(torch.linalg.cholesky(A))
        # the experiments' scores: their spread is the sandwich's meat (errors shared within an experiment count once)
        scores = torch.zeros(states.shape[0], k, dtype=J.dtype, device=J.device).index_add_(0, exp, J * W(res[:, None]))
        meat = scores.shape[0] / max(scores.shape[0] - 1, 1) * scores.T @ scores + torch.diag(1 / prior_var)
        robust = cov @ meat @ cov
        if float(torch.trace(torch.linalg.solve(cov, robust))) > k:  # wider on average: the data say so
            shrink = (posterior.prior_scale / robust.diagonal().sqrt()).clamp_max(1.0)  # never wider than the prior
            cov = shrink[:, None] * robust * shrink[None, :]
    except (IntegrationError, LinearAlgebraError, torch.linalg.LinAlgError) as exc:
        warn(
            "fit_correction: the fit of G's uncertain parameters through the ODE failed near the estimate from the "
            f"derivative samples ({str(exc)[:200]}); kept that estimate, whose standard deviations treat the "
            "derivative estimator's errors as independent (likely too narrow)",
            NumericalWarning,
        )
        return posterior
    return dataclasses.replace(posterior, mean=theta, covariance=0.5 * (cov + cov.T))


def fit_parameters(gp, samples, system, trajectories, delta=None, noise=None):
    """``(gp conditioned at theta's posterior mean, the samples there)``, the posterior (``gp.parameters_``) in
    closed form from the derivative samples (:func:`~torchmisspec.parameters.condition_with_parameters`), then
    refined through the ODE on ``trajectories`` (:func:`refine_through_ode`); ``gp`` has the hyperparameters to
    use and was trained on ``samples``' inputs, ``system`` declares the parameters, ``noise`` the residuals."""
    outputs = system.correction_outputs
    gp, moved = condition_with_parameters(gp, samples, system, delta)
    refined = refine_through_ode(system, gp, trajectories, gp.parameters_, noise=noise)
    if refined is gp.parameters_:
        return gp, moved
    moved = moved.linearized(system, refined.mean, outputs).shifted(refined.mean - refined.prior_mean, outputs)
    gp = gp.condition(moved.inputs, moved.targets, noise=moved.noise)
    gp.parameters_ = refined
    return gp, moved
