"""The trajectory fit's inner machinery (:func:`~torchmisspec.fit_trajectories`): the MAP of the pseudo-targets and
state offsets through the ODE, and relevance through the ODE for the feature kernels.

* :func:`_maximise_posterior`: L-BFGS (the package's one loop, :func:`~torchmisspec._optim.maximise`) on the log
  posterior of the pseudo-targets and the initial-state offsets given the observed states;
* :func:`_fit_relevance`: for a feature kernel, alternates Levenberg-Marquardt steps on the active coefficients and
  the offsets (Jacobians by central differences through one batched solve) with relevance updates of the weights,
  until the active terms and weights settle; the result is written back as pseudo-targets
  (:func:`_pseudo_targets`), so the model stays a :class:`~torchmisspec.CorrectionGP`.
"""

from __future__ import annotations

import math

import torch

from ..._errors import FittingError, IntegrationError, LinearAlgebraError, TorchMisspecWarning, warn
from ..._ode import EVALS_PER_STEP, trial_budget
from ..._optim import OptimResult, maximise
from ..._validation import progress_bar
from ...data import Trajectories
from ._fit_fallbacks import _shrink_until_integrable, _spanning_inputs
from ._jacobian import _coefficient_columns, _joint_columns
from ._term_price import forward_selection, term_price


def _balanced_noise(residuals, field, trajectories: Trajectories) -> torch.Tensor:
    """Noise variances that balance data and prior at the start: the mean squared misfit per component (of the
    states and any readings)."""
    with torch.no_grad():
        sq0 = residuals(field, None, None).pow(2)  # (n, d + m), from the observed initial states
    seen = residuals.seen.to(sq0.dtype)
    flat = trajectories.flat_states()
    size = float(flat[torch.isfinite(flat)].pow(2).mean())
    return (sq0.sum(0) / seen.sum(0).clamp_min(1.0)).clamp_min(1e-12 * size)


def _maximise_posterior(params, offsets, field_and_prior, residuals, s2, n_obs, *, max_iter, progress, shooting):
    """L-BFGS on the log posterior ``-(sum squares / (2 s2) + prior)`` over ``params`` (and the offsets); a start
    that cannot be integrated is shrunk until it can (:func:`_shrink_until_integrable`), and a trial step that blows
    up the ODE is rejected (a value far below the best, no slope: the line search shortens the step), with a warning;
    the parameters hold the best iterate."""
    d = s2.shape[0]
    sd = s2.sqrt()
    every = [*params] + ([] if offsets is None else [offsets])
    best = {"value": -math.inf, "params": None, "evaluations": 0}

    def attempt():  # the IntegrationError of a solve at the current parameters, or None
        try:
            with torch.no_grad():
                residuals(field_and_prior(params[0])[0], offsets, sd)
        except IntegrationError as exc:
            return exc
        return None

    _shrink_until_integrable(every, attempt)  # a start that cannot be integrated: a smaller one that can

    rejected = [0]

    def evaluate():
        try:
            field, prior = field_and_prior(params[0])
            sq = residuals(field, offsets, sd).pow(2)
            objective = -((sq.reshape(-1, d) / s2).sum() / 2 + prior)  # the log posterior, up to a constant
            value = float(objective.detach())
        except IntegrationError:
            if best["params"] is None:  # the (shrunk) start integrated without gradients, not with them
                raise
            value = math.nan
        best["evaluations"] += 1
        if not math.isfinite(value):  # a trial the ODE cannot follow: far below the best, no slope (rejected:
            # the line search shortens the step)
            rejected[0] += 1
            low = best["value"] - 1e3 * (1.0 + abs(best["value"]))
            objective = sum((p * 0).sum() for p in every) + low
            return objective.detach(), objective
        if value > best["value"]:
            best["value"], best["params"] = value, [p.detach().clone() for p in every]
        return objective.detach(), objective

    try:
        result = maximise(
            every,
            evaluate,
            max_iter=max_iter,
            normaliser=float(n_obs),
            progress=progress,
            desc=f"fit_trajectories ({shooting} shooting)",
        )
    except LinearAlgebraError as exc:
        raise FittingError(f"fit_trajectories failed: {exc}") from exc
    if rejected[0]:  # the optimiser may stop on a rejected trial: the best iterate is the result
        with torch.no_grad():
            for p, value in zip(every, best["params"], strict=True):
                p.copy_(value)
        result = OptimResult(result.iterations, best["evaluations"], best["value"])
        warn(
            f"fit_trajectories: a trial step of the optimiser made the corrected ODE blow up (or stall) {rejected[0]} "
            f"time(s) in {best['evaluations']} evaluations; those steps were rejected (the line search shortened "
            "them) and the fit returns the best correction found. Give state_noise=... (a larger noise weakens the "
            "pull of the data) or fewer max_iter",
            TorchMisspecWarning,
        )
    if not all(bool(torch.isfinite(p).all()) for p in every):
        raise FittingError("fit_trajectories diverged: the parameters became non-finite; give state_noise=...")
    return result


#: Most outer iterations (MAP, then a relevance update of the weights) of the feature kernel's trajectory fit.
RELEVANCE_ROUNDS = 10
#: L-BFGS iterations of the MAP in the rounds after the first (each starts from the previous optimum).
_LATER_ITERATIONS = 10


def _fit_relevance(
    gp,
    system,
    trajectories,
    residuals,
    n_obs,
    offsets,
    s2,
    *,
    max_iter: int,
    progress: bool = False,
    start=None,
    rounds: int | None = None,
    parameters: bool = False,
    theta_start: torch.Tensor | None = None,
    only: torch.Tensor | None = None,
    propose: bool = False,
):
    """The feature kernel through the ODE: sparse Bayesian learning of its term weights from the trajectories.

    F(x) = sum_j beta_j phi_j(x) with beta_j ~ N(0, w_j). Each round (i) finds the MAP coefficients (and initial
    states) under the current weights by L-BFGS, (ii) approximates their posterior by Laplace with the Gauss-Newton
    Hessian of the state misfit (its Jacobian by central differences: every coefficient, and each state component
    of all initial states at once, since experiments are independent), and (iii) updates the weights by MacKay's
    rule w_j = sum_o beta_oj^2 / sum_o gamma_oj, gamma_oj = 1 - Sigma_oj / w_j (removing terms that fall below
    :data:`~torchmisspec.gp._features.PRUNE`), until the active terms and weights settle. ``start`` (a mean
    square of F per output, ``(d_out,)``): start from F = 0 with every term's prior variance an equal share of it
    instead of from ``gp``'s fit (partly measured data, whose samples do not see F on an unmeasured component).
    ``rounds``: at most this many rounds (default :data:`RELEVANCE_ROUNDS`). ``parameters``: learn the system's
    uncertain parameters of G with the coefficients (single shooting only): theta = m + s v with v ~ N(0, I) is
    part of the Levenberg-Marquardt problem and of the Laplace step, which gives its joint posterior with the
    coefficients, the offsets marginalised; the result's ``parameters_laplace_`` is ``(mean (k,), covariance (k, k),
    covariance with F held fixed (k, k))``; ``theta_start`` ``(k,)``: where theta starts (default its prior mean).
    """
    from ...gp._features import PRUNE

    d = trajectories.state_dim
    base = gp.covar_module.base_kernel
    X = gp.train_inputs_
    Phi = base.features(X)  # (N, p): the monomials or a user library
    p = Phi.shape[1]
    d_out = gp.output_dim
    kd = dict(dtype=gp.dtype, device=gp.device)
    scale = gp.covar_module.outputscale.detach().reshape(-1, 1)  # (B, 1)
    W = (base.weights.detach().reshape(-1, p) * scale).T.expand(p, d_out).clone()  # (p, d_out) prior variances
    shared = W.shape[1] > 1 and not gp.per_output
    # the starting coefficients: the posterior mean of the current fit, beta = W Phi^T alpha
    alpha = gp.posterior().weights  # (N, d_out)
    beta = W * (Phi.T @ alpha)
    second = float(gp.train_targets_.pow(2).mean()) or 1.0
    phi2 = Phi.pow(2).mean(0).unsqueeze(-1).clamp_min(torch.finfo(Phi.dtype).tiny)  # (p, 1)
    # every term starts active: the derivative samples may have removed a term the trajectories support (their
    # estimator's bias is not the trajectories'); a removed term starts with an equal share of the samples' size
    W = torch.where(W > 0, W, (second / (p * phi2)).expand_as(W))
    if start is not None:
        W = (start.to(**kd).reshape(1, -1) / (p * phi2)).expand(p, d_out).clone()
        beta = torch.zeros_like(W)
    if (
        only is not None
    ):  # the terms of a proposal (torchmisspec.learning.refinement._term_price): the others removed from the start
        W = torch.where(only, W, torch.zeros_like(W))
        beta = torch.where(only, beta, torch.zeros_like(beta))

    k = len(system.parameters) if parameters else 0
    if k and not (hasattr(residuals, "many") and offsets is not None):
        raise FittingError("the joint fit of G's uncertain parameters through the ODE needs single shooting")
    m_theta = None if not k else system.parameters.mean.to(**kd)
    s_theta = None if not k else system.parameters.scale.to(**kd)
    v = None if not k else torch.zeros(k, **kd)  # theta = m + s v, starting at the prior mean ...
    if k and theta_start is not None:  # ... or where asked (the known model's own fit)
        v = ((theta_start.to(**kd) - m_theta) / s_theta).clone()

    def known_at(vv):  # G at theta = m + s vv (the system as declared when not learning theta)
        return system if vv is None else system.at(m_theta + s_theta * vv)

    def make_field(b, vv=None):  # vv: G's parameters (default: the current v; None without them)
        known = known_at(v if vv is None else vv)

        def field(y, t=None, u=None):
            x = system.select_inputs(y, u)
            return known.known_rhs(y, t, u) + system.embed(base.features(x) @ b)

        return field

    def make_fields(bs, vs=None):  # bs (m, p, d_out): copy c's coefficients drive rows c K ... c K + K - 1
        # vs: (k,) one theta for every copy (one call of G; default the current v), or (m, k) copy c's theta (one
        # call of G per distinct theta, over the rows of the copies that share it)
        vs = v if vs is None else vs
        known = known_at(vs).known_rhs if vs is None or vs.dim() == 1 else system.copies_rhs(m_theta + s_theta * vs)

        def field(y, t=None, u=None):
            f = base.features(system.select_inputs(y, u)).reshape(bs.shape[0], -1, p)  # (m, K, p)
            mixed = torch.einsum("mkp,mpo->mko", f, bs).reshape(y.shape[0], -1)
            return known(y, t, u) + system.embed(mixed)

        return field

    if s2 is None:
        s2 = _balanced_noise(residuals, make_field(beta), trajectories)
    sd = s2.sqrt()
    iterations = evaluations = 0
    laplace = None
    rounds = RELEVANCE_ROUNDS if rounds is None else rounds
    bar = progress_bar(progress, rounds, "fit_trajectories: term weights through the ODE", "round")
    for round_ in range(rounds):
        bar.update()
        active = W > 0
        if not bool(active.any()):
            beta = torch.zeros_like(W)
            break
        root = W[active].sqrt()
        u = (beta[active] / root).clone().requires_grad_(True)  # coefficients in units of their prior std

        def field_and_prior(uv, active=active, root=root):
            b = torch.zeros((p, d_out), **kd).index_put((active.nonzero(as_tuple=True)), uv * root)
            return make_field(b), 0.5 * uv.pow(2).sum()

        rounds_iter = max_iter if round_ == 0 else min(max_iter, _LATER_ITERATIONS)
        if hasattr(residuals, "many") and offsets is not None:  # single shooting: Levenberg-Marquardt
            its, evals = _levenberg_marquardt(
                u,
                offsets,
                active,
                root,
                beta,
                make_field,
                make_fields,
                residuals,
                sd,
                max_iter=rounds_iter,
                theta=None if not k else (v, make_field, make_fields),
            )
        else:
            result = _maximise_posterior(
                [u], offsets, field_and_prior, residuals, s2, n_obs, max_iter=rounds_iter, progress=False,
                shooting="relevance",
            )  # fmt: skip
            its, evals = result.iterations, result.evaluations
        iterations += its
        evaluations += evals
        b_act = (u.detach() * root).clone()
        beta = torch.zeros((p, d_out), **kd)
        beta[active] = b_act
        # Laplace: Gauss-Newton Hessian of the scaled misfit in (coefficients, initial-state offsets)
        off = None if offsets is None else offsets.detach()
        with torch.no_grad():
            q = int(active.sum())
            if off is not None:  # single shooting: the coefficients', G's parameters' and offsets' columns at once
                J_b = _joint_columns(residuals, make_fields, beta, active, v if k else None, off, sd)
                J_b, Jo = J_b[:, : q + k], J_b[:, q + k :]
            else:  # multiple shooting (no parameters, no offsets)
                J_b = _coefficient_columns(residuals, make_field, beta, active, off, sd, make_fields)
            # G's parameters' prior N(0, 1) in units of their prior sd
            H = J_b.T @ J_b + torch.diag(torch.cat([1.0 / W[active], torch.ones(k, **kd)]))
            if off is not None:  # the offsets' block: column j moves component j of every initial state
                Kx, dd = off.shape
                Hbo = J_b.T @ Jo
                Hoo = Jo.T @ Jo + torch.eye(Kx * dd, **kd)  # the offsets' prior N(0, 1) in units of sd
                H = H - Hbo @ torch.linalg.solve(Hoo, Hbo.T)  # marginal over the offsets (Schur complement)
            try:
                inverse = torch.linalg.inv(H)
                Sigma = inverse.diagonal()[:q]
                if k:  # this round's pieces of theta's posterior (made once, after the last round)
                    laplace = (v.clone(), inverse[q:, q:], torch.linalg.inv(H[q:, q:]), J_b, Jo, beta.clone(), W, off)
            except torch.linalg.LinAlgError:
                break
            new = torch.zeros_like(W)
            gam = (1.0 - Sigma / W[active]).clamp(1e-12, 1.0)
            num = torch.zeros_like(W)
            num[active] = b_act.pow(2)
            den = torch.zeros_like(W)
            den[active] = gam
            if shared:  # one weight per term shared by the outputs
                num = num.sum(1, keepdim=True).expand_as(W)
                den = den.sum(1, keepdim=True).expand_as(W)
            new[active] = num[active] / den[active].clamp_min(1e-12)
            new[new * phi2 < PRUNE * second] = 0.0
            both = (new > 0) & active
            change = float((new[both].log() - W[both].log()).abs().max()) if bool(both.any()) else 0.0
            settled = bool(((new > 0) == active).all()) and change < 1e-2
            beta = beta * (new > 0)
            W = new
        if settled:
            break
    bar.close()
    record = None  # the misfit where the rounds ended and the sparse proposal: only for fit_trajectories' rival
    if propose or only is not None:
        record = _relevance_record(
            residuals, make_field, make_fields, beta, W, offsets, sd, n_obs, gp, propose and not k
        )
    # back to a CorrectionGP: the new weights, and pseudo-targets whose posterior mean is exactly phi(x)^T beta (at
    # inputs enough to span the active terms: more terms than samples could not reproduce beta)
    X, targets, noise = _spanning_inputs(X, gp.train_targets_, gp.train_noise_, base.features, W)
    Phi = base.features(X)
    tmp = gp.condition(X, targets, noise=noise)
    with torch.no_grad():
        wt = (W.T / scale) if gp.per_output else (W[:, :1].T / scale)
        tmp.covar_module.base_kernel.weights.copy_(wt.reshape(tmp.covar_module.base_kernel.weights.shape))
        # a term kept through the ODE is present; one the samples' fit removed too keeps the chance of being present
        # and the spread that the samples gave it (gp._features; the trajectories' own would need the linearised
        # factors); one the samples kept but the trajectories removed counts as absent (chance 0, no spread)
        base = tmp.covar_module.base_kernel
        kept = base.weights.detach() > 0
        was_kept = gp.covar_module.base_kernel.weights.detach().reshape(kept.shape) > 0
        one, zero = torch.ones_like(base.inclusion), torch.zeros_like(base.inclusion)
        base.inclusion.copy_(torch.where(kept, one, torch.where(was_kept, zero, base.inclusion)))
        base.spread.copy_(torch.where(kept | was_kept, zero, base.spread))
        Yhat = _pseudo_targets(tmp, Phi, W, beta)
    refined = tmp.condition(X, Yhat, noise=noise)
    refined.n_iterations_, refined.n_evaluations_ = iterations, evaluations
    refined.n_rhs_evaluations_ = residuals.nfe
    refined.state_noise_ = s2
    refined.relevance_record_ = record
    if offsets is not None:
        refined.initial_states_ = trajectories.initial_conditions + offsets.detach() * sd[:d]
    if k:  # theta's posterior from the last round's Laplace step, with F's coefficients marginalised and held fixed
        refined.parameters_laplace_ = None
        if laplace is not None:
            v_at, cov, fixed, J_p, J_o, b_at, W_at, off_at = laplace
            r = residuals(make_field(b_at, v_at), off_at, sd) / sd
            cov = _robust(cov, J_p, J_o, r, residuals, W_at)
            scaled = (s_theta[:, None] * c * s_theta[None, :] for c in (cov, fixed))
            refined.parameters_laplace_ = (m_theta + s_theta * v_at, *scaled)
    return refined


def _relevance_record(residuals, make_field, make_fields, beta, W, offsets, sd, n_obs, gp, propose: bool) -> dict:
    """Where the rounds ended: the scaled misfit, the number of kept terms and, with ``propose`` (one weight per
    coefficient), the sparse set :func:`~torchmisspec.learning.refinement._term_price.forward_selection` proposes there
    (``None`` otherwise, or when a solve fails)."""
    off = None if offsets is None else offsets.detach()
    with torch.no_grad():
        try:
            r = (residuals(make_field(beta), off, sd) / sd).reshape(-1)
        except IntegrationError:
            return {"misfit": math.inf, "terms": int((W > 0).sum()), "active": W > 0, "proposal": None}
        record = {"misfit": float(r.pow(2).sum()), "terms": int((W > 0).sum()), "active": W > 0, "proposal": None}
        if not propose or not (gp.per_output or W.shape[1] == 1):
            return record
        try:
            every = torch.ones_like(W, dtype=torch.bool)
            if off is None:
                J, J_f = _coefficient_columns(residuals, make_field, beta, every, off, sd, make_fields), None
            else:
                J = _joint_columns(residuals, make_fields, beta, every, None, off, sd)
                J, J_f = J[:, : every.numel()], J[:, every.numel() :]
            f = None if off is None else off.reshape(-1)
            price = term_price(gp, n_obs)
            record["proposal"] = forward_selection(J, r, beta.reshape(-1), price, J_f, f).reshape(W.shape)
        except (IntegrationError, LinearAlgebraError, torch.linalg.LinAlgError):
            pass
    return record


def _robust(cov: torch.Tensor, J_p: torch.Tensor, J_o: torch.Tensor, r: torch.Tensor, residuals, W) -> torch.Tensor:
    """G's parameters' covariance ``(k, k)`` (in units of their prior sd) from the joint fit through the ODE: the
    Laplace one ``cov``, or, when it is wider on average, the cluster-robust sandwich over experiments (Liang & Zeger
    1986; as :mod:`torchmisspec.learning.theta.through_ode` does): what the polynomial F cannot represent of the true
    one is shared by the times of an experiment, not independent noise, and the Laplace posterior would let theta absorb
    it with a confidence it has not earned. ``J_p`` ``(n d, q + k)``: the columns of the active coefficients (prior
    variances ``W``) and of the parameters; ``J_o`` the offsets'; ``r`` ``(n, d)`` the scaled residuals."""
    k = cov.shape[0]
    q = J_p.shape[1] - k
    kd = dict(dtype=cov.dtype, device=cov.device)
    J = torch.cat([J_p, J_o], dim=1)
    prior = torch.cat([1.0 / W[W > 0], torch.ones(k + J_o.shape[1], **kd)])
    inverse = torch.linalg.inv(J.T @ J + torch.diag(prior))
    d = r.shape[1]
    rows = residuals.experiment.repeat_interleave(d)
    K = int(rows.max()) + 1
    scores = torch.zeros(K, J.shape[1], **kd).index_add_(0, rows, J * r.reshape(-1, 1))
    meat = K / max(K - 1, 1) * scores.T @ scores + torch.diag(prior)
    robust = (inverse @ meat @ inverse)[q : q + k, q : q + k]
    if float(torch.trace(torch.linalg.solve(cov, robust))) > k:  # wider on average: the data say so
        shrink = (1 / robust.diagonal().sqrt()).clamp_max(1.0)  # never wider than the prior (sd 1 in these units)
        return shrink[:, None] * robust * shrink[None, :]
    return cov


def _levenberg_marquardt(
    u, offsets, active, root, beta, make_field, make_fields, residuals, sd, *, max_iter: int, theta=None
):
    """Minimise ``1/2 ||r(u, o) / s||^2 + 1/2 ||u||^2`` (the MAP of the coefficients ``u``, in units of their prior
    standard deviations, and the initial-state offsets ``o``, in units of the state noise) by Levenberg-Marquardt
    steps: the Jacobian by central differences, every perturbed model in one batched solve. The problem has a few
    dozen parameters and is nearly linear in them, so a handful of steps replaces L-BFGS's dozens of evaluations,
    each of which differentiated through the solver. ``theta``: ``(v, field, fields)`` to learn G's uncertain
    parameters too, v ``(k,)`` in units of their prior standard deviations (``+ 1/2 ||v||^2``), ``field(b, v)`` and
    ``fields(bs, vs)`` taking them. ``u``, ``offsets`` (and v) are updated in place; returns ``(iterations, objective
    evaluations)``."""
    q = u.numel()
    K, d = offsets.shape
    kd = dict(dtype=u.dtype, device=u.device)
    k = 0 if theta is None else theta[0].numel()

    def coefficients(uv):
        b = torch.zeros_like(beta)
        b[active] = uv * root
        return b

    def fields(vv):  # (field, fields) with G at vv
        if theta is None:
            return make_field, make_fields
        return (lambda b: theta[1](b, vv)), (lambda bs: theta[2](bs, vv))

    failed = []

    def objective(uv, vv, ov, max_steps=None):  # a solve that fails is an infinite misfit: a rejected step
        try:
            r = residuals(fields(vv)[0](coefficients(uv)), ov, sd, max_steps) / sd
        except IntegrationError as exc:
            failed[:] = [exc]
            return math.inf, None
        prior = uv.pow(2).sum() + (0 if vv is None else vv.pow(2).sum())
        return 0.5 * float(r.pow(2).sum() + prior), r.reshape(-1)

    with torch.no_grad():
        uv, ov = u.detach().clone(), offsets.detach().clone()
        vv = None if theta is None else theta[0].detach().clone()
        value, r = objective(uv, vv, ov)
        if r is None:  # the start cannot be integrated: a smaller correction (at last G alone) that can
            _shrink_until_integrable(
                [uv, ov] + ([] if vv is None else [vv]),
                lambda: None if objective(uv, vv, ov)[1] is not None else failed[0],
                failed[0],
            )
            value, r = objective(uv, vv, ov)
        lam, evaluations, iterations = 1e-3, 1, 0
        steps = residuals.last / EVALS_PER_STEP  # the current point's solve: the trial steps' budget
        while iterations < max_iter:
            iterations += 1
            b = coefficients(uv)
            field, fields_ = fields(vv)
            J = _joint_columns(residuals, make_fields, b, active, vv, ov, sd)
            J[:, :q] *= root
            prior = torch.cat([uv] + ([] if vv is None else [vv]) + [torch.zeros(K * d, **kd)])
            grad = J.T @ r + prior
            H = J.T @ J
            H[range(q + k), range(q + k)] += 1.0
            accepted = False
            for _ in range(8):
                A = H + lam * torch.diag(H.diagonal().clamp_min(1e-12))
                try:
                    step = -torch.linalg.solve(A, grad)
                except torch.linalg.LinAlgError:
                    lam *= 10.0
                    continue
                new_u, new_o = uv + step[:q], ov + step[q + k :].reshape(K, d)
                new_v = None if vv is None else vv + step[q : q + k]
                new_value, new_r = objective(new_u, new_v, new_o, trial_budget(steps))
                evaluations += 1
                if new_value < value:
                    accepted = True
                    break
                lam *= 10.0
            if not accepted:
                break
            gain = value - new_value
            uv, vv, ov, value, r = new_u, new_v, new_o, new_value, new_r
            lam, steps = max(lam * 0.3, 1e-9), residuals.last / EVALS_PER_STEP
            if gain <= 1e-8 * max(value, 1.0):
                break
        u.data.copy_(uv)
        offsets.data.copy_(ov)
        if theta is not None:
            theta[0].copy_(vv)
    return iterations, evaluations


def _pseudo_targets(gp, Phi: torch.Tensor, W: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """Targets ``Y (N, d_out)`` whose posterior mean under ``gp`` (a feature kernel with prior variances ``W``) is
    ``phi(x)^T beta``: with C the training covariance, ``Y_o = C Phi_a (Phi_a^T Phi_a)^-1 W_a^-1 beta_a`` over the
    active terms a of output o (then ``W_a Phi_a^T C^-1 Y_o = beta_a``)."""
    X = gp.train_inputs_
    posterior = gp.posterior()
    V = torch.zeros((X.shape[0], beta.shape[1]), dtype=beta.dtype, device=beta.device)
    for o in range(beta.shape[1]):
        act = W[:, o] > 0
        if bool(act.any()):
            P = Phi[:, act]
            if int(torch.linalg.matrix_rank(P)) == P.shape[1]:
                V[:, o] = P @ torch.linalg.solve(P.T @ P, beta[act, o] / W[act, o])
            else:  # the least-squares form (the nearest model the inputs can carry: _spanning_inputs avoids it)
                V[:, o] = torch.linalg.pinv(P).T @ (beta[act, o] / W[act, o])
    B = posterior.factor.alpha.shape[0]  # one C per output, or one shared: C_o V_o (feature space: never formed)
    CV = posterior.training_covariance_times(V.T.unsqueeze(-1) if B > 1 else V.unsqueeze(0))
    return CV.squeeze(-1).T if B > 1 else CV[0]
