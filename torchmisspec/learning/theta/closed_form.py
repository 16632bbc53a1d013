"""theta's posterior from the derivative samples, F integrated out: the closed form, and Gauss-Newton for a G
nonlinear in theta.

A system marks parameters of G as uncertain with a prior, a value and a scale
(``MisspecifiedSystem(G, d, parameters={"c": (0.4, 0.2)})``); G then takes them as its last argument,
``G(y, theta)`` or ``G(t, y, u, theta)``, ``theta`` a tensor ``(k,)`` in the order given.

**G linear in theta** (G(y; theta) = G(y; m) + sum_k (theta_k - m_k) g_k(y), checked numerically at the data):
the samples of the residual r = dy/dt - G(y; m) over every state component are

    r = H delta + F + eps,     delta = theta - m ~ N(0, S),   F ~ GP(0, K) on the corrected components,

with H the basis g_k at the samples, eps the samples' noise (the GP's on the corrected components; on components
that F does not act on, a variance estimated from the residuals). theta is a Gaussian linear model in F's noise,
so it integrates out in closed form (Rasmussen & Williams 2006, §2.7, "explicit basis functions"): with C the GP's
training covariance (K + noise; a noise variance alone on the other components),

    A = S^-1 + H^T C^-1 H,      posterior of delta = N(A^-1 H^T C^-1 r, A^-1),
    log p(r) = log N(r; 0, C) - 1/2 log|S| - 1/2 log|A| + 1/2 b^T A^-1 b,   b = H^T C^-1 r,

and F's posterior given the data, theta integrated out, is the GP's posterior given the targets r - H delta_bar
with the extra covariance (k(x, X) C^-1 H) A^-1 (...)^T. A posterior draw of the corrected model is then exact as a
pair: delta_s ~ N(delta_bar, A^-1), and F_s the GP's draw given r - H delta_s, which is the draw given
r - H delta_bar minus k(x, X) C^-1 H (delta_s - delta_bar): each draw's right-hand side is
G(y; theta_bar) + F_s(x) + sum_k (delta_s - delta_bar)_k (g_k(y) - m_k(x)), m_k the GP's posterior mean given the
targets g_k: the part of g_k that F would absorb (:meth:`ParameterPosterior.draw_terms`).

**Telling theta from F.** F and theta trade off exactly where the kernel can represent g_k. The data then leave
theta_k near its prior: :attr:`ParameterPosterior.identified` is ``False`` where the posterior standard deviation
exceeds :data:`IDENTIFIED_RATIO` times the prior's, and the warning says whether F is the reason (without a
correction the same data would give :attr:`~ParameterPosterior.sd_without_correction`, well inside the prior) or
the data hardly depend on theta_k. A parameter error and a missing term can look alike; saying so is part of the
answer. Parameters whose posteriors correlate beyond :data:`CORRELATION_LIMIT` are reported too (only a
combination is determined).

**G nonlinear in theta** (MAP with a Laplace posterior): the residuals' density with F integrated out,
N(r(theta); 0, C) N(theta; m, S), r(theta) = dy/dt - G(y; theta), is maximised by Gauss-Newton. At theta_0,
G(y; theta) ~ G(y; theta_0) + J_0 (theta - theta_0) (J_0 the Jacobian at the samples, :func:`parameter_basis`), which
is the linear model above with the residuals r(theta_0) + J_0 (theta_0 - m) and the basis J_0
(:meth:`CorrectionSamples.linearized <torchmisspec.CorrectionSamples.linearized>`); its posterior mean is the next
theta_0, until a step moves theta by less than 1 % of its posterior standard deviation. At the MAP, A^-1 is the Laplace
covariance (the Gauss-Newton Hessian). A posterior draw integrates G(y; theta_s) itself, not its linearisation
(:meth:`ParameterPosterior.draw_field`), and so does the fit through the ODE that refines theta on the trajectories.
:attr:`ParameterPosterior.linear` records which case a model is in.
"""

from __future__ import annotations

import math

import torch

from ..._errors import InputError, NumericalWarning, warn
from ..._linalg import cholesky
from ...gp._features import check_dense
from ...parameters import LARGER_CORRECTION, ParameterPosterior, Priors

__all__ = [
    "parameter_posterior",
    "posterior_given",
    "condition_with_parameters",
    "GAUSS_NEWTON_STEPS",
    "PARAMETER_PASSES",
]

#: most Gauss-Newton steps of a nonlinear G's posterior per hyperparameter pass (each: one closed-form posterior)
GAUSS_NEWTON_STEPS = 20
#: Gauss-Newton stops once a step moves every parameter by at most this fraction of its posterior standard deviation
CONVERGED = 0.01


def parameter_posterior(
    gp,
    residuals: torch.Tensor,
    basis: torch.Tensor,
    outputs,
    priors: Priors,
    delta=None,
    *,
    linear: bool = True,
    larger: bool = True,
):
    """The posterior of theta given the residual samples, F integrated out (the module's notes).

    Args:
        gp: the correction GP, fitted on the corrected components of these samples (its training covariance C is
            used; its targets are not).
        residuals: ``(N, d)`` dy/dt - G(y; prior mean) at the samples, every state component.
        basis: ``(N, d, k)`` the basis g_k at the samples.
        outputs: the components F acts on (``gp``'s outputs, in order).
        priors: the :class:`Priors`.
        delta: the current estimate of theta - m ``(k,)`` (``None``: 0), for the noise of the components F does not
            act on (estimated from the residuals r - H delta there).
        linear: whether G is linear in theta (else ``residuals`` and ``basis`` are a linearisation's, and the
            posterior is the Laplace approximation when taken at the MAP), recorded in the result.
        larger: also compute ``sd_larger_correction`` (one dense N x N solve per corrected output; skipped, ``None``,
            on Gauss-Newton's intermediate steps).
    """
    dtype, device = residuals.dtype, residuals.device
    k = len(priors)
    outputs = list(outputs)
    others = [j for j in range(residuals.shape[1]) if j not in outputs and bool(basis[:, j].abs().amax() > 0)]
    S = priors.scale.to(dtype=dtype, device=device) ** 2
    delta = torch.zeros(k, dtype=dtype, device=device) if delta is None else delta.to(residuals)
    post = gp.posterior()
    Hc = basis[:, outputs, :]  # (N, d_out, k)
    rc = residuals[:, outputs]
    fit_r = post.with_targets(rc)
    solves = [post.with_targets(Hc[:, :, j]).weights for j in range(k)]  # C^-1 g_j, (N, d_out) each
    CinvH = torch.stack(solves, dim=-1)  # (N, d_out, k)
    info = torch.einsum("njk,njl->kl", CinvH, Hc)
    b = torch.einsum("njk,nj->k", CinvH, rc)
    noise = _noise(gp, Hc)
    info0 = torch.einsum("njk,njl->kl", Hc / noise.unsqueeze(-1), Hc)
    evidence = fit_r.log_marginal_likelihood
    n = residuals.shape[0]
    info_others = torch.zeros(k, k, dtype=dtype, device=device)
    for j in others:  # components F does not act on: r_j = g_j^T delta + noise, the noise estimated at delta
        Hj, rj = basis[:, j, :], residuals[:, j]
        var = float(((rj - Hj @ delta) ** 2).sum()) / max(n - k, 1)
        var = max(var, 1e-12 * float((rj**2).mean()) + 1e-300)
        info = info + Hj.T @ Hj / var
        info0 = info0 + Hj.T @ Hj / var
        info_others = info_others + Hj.T @ Hj / var
        b = b + Hj.T @ rj / var
        evidence += -0.5 * (float((rj**2).sum()) / var + n * math.log(2 * math.pi * var))
    A = torch.diag(1 / S) + info
    LA = torch.linalg.cholesky(A)
    cov = torch.cholesky_inverse(LA)
    mean = cov @ b
    cov0 = torch.cholesky_inverse(torch.linalg.cholesky(torch.diag(1 / S) + info0))
    evidence += float(-0.5 * S.log().sum() - LA.diagonal().log().sum() + 0.5 * b @ mean)
    return ParameterPosterior(
        names=priors.names,
        prior_mean=priors.mean.to(residuals),
        prior_scale=priors.scale.to(residuals),
        mean=priors.mean.to(residuals) + mean,
        covariance=0.5 * (cov + cov.T),
        sd_without_correction=cov0.diagonal().clamp_min(0).sqrt(),
        log_evidence=float(evidence),
        basis_targets=Hc.detach().clone(),
        linear=linear,
        sd_larger_correction=_sd_larger_correction(gp, Hc, info_others, S) if larger else None,
    )


def posterior_given(gp, samples, system, delta=None):
    """``(theta's posterior, the samples)`` under ``gp``'s hyperparameters (``gp`` trained on ``samples``' inputs):
    the closed form for a G linear in theta; for a nonlinear G, Gauss-Newton to the MAP (the module's notes, at most
    :data:`GAUSS_NEWTON_STEPS` steps, warned when it does not converge), the samples returned linearised at it.
    ``samples``: :class:`~torchmisspec.CorrectionSamples` with ``residuals`` and ``basis`` taken with ``system``;
    ``delta`` the current estimate of theta - m (for the noise of components F does not act on)."""
    outputs, linear = system.correction_outputs, samples.parameters_linear
    posterior = None
    for step in range(1 if linear else GAUSS_NEWTON_STEPS):
        before, used = posterior, samples
        posterior = parameter_posterior(  # the check with a larger F (a dense solve) once, at the last step
            gp, samples.residuals, samples.basis, outputs, system.parameters, delta, linear=linear, larger=linear
        )
        if linear:
            break
        samples = samples.linearized(system, posterior.mean, outputs)
        moved = None if before is None else (posterior.mean - before.mean).abs() / posterior.stddev
        if moved is not None and bool((moved <= CONVERGED).all()):
            break
        if step == GAUSS_NEWTON_STEPS - 1:
            warn(
                f"the Gauss-Newton fit of G's uncertain parameters {list(system.parameters.names)} (G is nonlinear in "
                f"them) did not converge in {GAUSS_NEWTON_STEPS} steps (the last moved them by up to "
                f"{float(moved.max()):.2g} posterior standard deviations); the posterior is the last step's. Tighter "
                "priors, or a parametrisation in which G is closer to linear, help",
                NumericalWarning,
            )
    if not linear:  # the last step's posterior again, with the check of a larger F it skipped
        posterior = parameter_posterior(gp, used.residuals, used.basis, outputs, system.parameters, delta, linear=False)
    return posterior, samples


def condition_with_parameters(gp, samples, system, delta=None):
    """``(gp conditioned on r - H theta_bar, the samples there)``: theta's posterior under ``gp``'s hyperparameters
    (:func:`posterior_given`), and ``gp``'s hyperparameters conditioned on the samples at its mean, the posterior kept
    as ``parameters_``."""
    posterior, samples = posterior_given(gp, samples, system, delta)
    moved = samples.shifted(posterior.mean - posterior.prior_mean, system.correction_outputs)
    out = gp.condition(moved.inputs, moved.targets, noise=moved.noise)
    out.parameters_ = posterior
    return out, moved


def _sd_larger_correction(gp, Hc: torch.Tensor, info_others: torch.Tensor, S: torch.Tensor) -> torch.Tensor | None:
    """theta's posterior standard deviations ``(k,)`` with F allowed to be larger on each corrected output: its
    prior variance :data:`LARGER_CORRECTION` times the fitted one, and at least what a change of 2 prior standard
    deviations in any parameter makes to G there (C = a K / mean diag K + diag(noise)). Where such an F could stand in
    for a parameter, the data leave it near its prior. ``None`` where the dense training covariance is out of reach
    (many samples)."""
    try:
        check_dense(Hc.shape[0])  # a model fitted in feature space on many samples: no N x N matrix
        K, diag = gp._kernel_parts(gp.train_inputs_, gp.train_noise_)
    except InputError:
        return None
    K, diag, info = K.detach().to(Hc), diag.detach().to(Hc), info_others.clone()
    n = Hc.shape[0]
    for o in range(Hc.shape[1]):
        Ko = K[min(o, K.shape[0] - 1)]
        size = Ko.diagonal().mean().clamp_min(1e-300)
        effect = 4 * (S * Hc[:, o, :].pow(2).mean(0)).max()  # (2 prior sd x g_k)^2, the largest parameter's
        C = torch.maximum(LARGER_CORRECTION * size, effect) * Ko / size
        L = cholesky(C + torch.diag(diag[min(o, diag.shape[0] - 1)].expand(n)))
        info = info + Hc[:, o, :].T @ torch.cholesky_solve(Hc[:, o, :], L)
    A = torch.diag(1 / S) + info
    return torch.cholesky_inverse(torch.linalg.cholesky(0.5 * (A + A.T))).diagonal().clamp_min(0).sqrt()


#: passes of the fit of G's uncertain parameters before the model is chosen: each fits the GP's hyperparameters on
#: the samples at the current estimate of theta and updates theta's posterior (its mean moves the targets)
PARAMETER_PASSES = 3


def _parameter_passes(samples, system, template):
    """``(theta's posterior, the correction samples)`` after :data:`PARAMETER_PASSES` alternations of the
    hyperparameters of the GP ``template`` (by marginal likelihood on the samples at the current theta) and theta's
    closed-form posterior given them (:func:`~torchmisspec.fit_correction` chooses F at its mean); for a G nonlinear
    in theta, each pass's posterior is Gauss-Newton's to convergence (the samples linearised at each step's mean, the
    module's notes), and the samples come back linearised at the last mean. The posterior's
    ``sd_larger_correction`` is the largest over the passes: the first fits F to the residuals at the prior mean,
    where F carries all that is missing, and a later pass may shrink F once theta takes that up (the trade-off it
    exists to report)."""
    outputs, posterior, seen = system.correction_outputs, None, None
    for _ in range(PARAMETER_PASSES):
        delta = None if posterior is None else posterior.mean - system.theta
        moved = samples if delta is None else samples.shifted(delta, outputs)
        model = template.clone().fit(moved.inputs, moved.targets, noise=moved.noise)
        posterior, samples = posterior_given(model, samples, system, delta)
        posterior = seen = posterior.absorbing(seen)
    return posterior, samples


def _noise(gp, Hc: torch.Tensor) -> torch.Tensor:
    """The GP's noise variance per sample and output ``(N, d_out)`` (the learned floor plus known noise)."""
    floor = torch.as_tensor(gp.noise_variance, dtype=Hc.dtype, device=Hc.device).reshape(-1)
    noise = floor.expand(Hc.shape[1]).expand(Hc.shape[0], -1)
    if gp.train_noise_ is not None:
        noise = noise + gp.train_noise_.to(Hc)
    return noise
