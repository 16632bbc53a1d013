"""The trajectory fit's inner machinery (:func:`~torchmisspec.fit_trajectories`): the MAP of the pseudo-targets and
state offsets through the ODE, and relevance through the ODE for the feature kernels.

* :func:`_maximise_posterior`: L-BFGS (the package's one loop, :func:`~torchmisspec._optim.maximise`) on the log
  posterior of the pseudo-targets and the initial-state offsets given the observed states;
* :func:`_fit_relevance`: for a feature kernel, alternates Levenberg-Marquardt steps on the active coefficients and
  the offsets (:mod:`._levenberg_marquardt`; Jacobians by central differences through one batched solve) with a
  Laplace step and relevance updates of the weights (:func:`_relevance_rounds`), until the active terms and weights
  settle; the result is written back as pseudo-targets (:func:`_as_correction_gp`, :func:`_pseudo_targets`), so the
  model stays a :class:`~torchmisspec.CorrectionGP`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..._errors import FittingError, IntegrationError, LinearAlgebraError, TorchMisspecWarning, warn
from ..._optim import OptimResult, maximise
from ..._validation import progress_bar
from ...data import Trajectories
from ._fit_fallbacks import _shrink_until_integrable, _spanning_inputs
from ._jacobian import _coefficient_columns, _joint_columns
from ._levenberg_marquardt import _levenberg_marquardt
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


@dataclass(frozen=True)
class _TermScale:
    """What MacKay's update compares a term's weight with: each term's mean square feature ``phi2`` ``(p, 1)`` at the
    training inputs, the targets' second moment, and whether the outputs share one weight per term."""

    phi2: torch.Tensor
    second: float
    shared: bool


@dataclass(frozen=True)
class _TermFields:
    """The corrected right-hand sides of the feature coefficients (and of G's uncertain parameters, when they are
    learned: theta = ``mean + scale v``, ``v`` updated in place by the rounds), for the solves of every step."""

    system: object
    features: object  # x (n, d_in) -> (n, p)
    p: int
    mean: torch.Tensor | None  # theta's prior mean and scale; None (and v None) when theta is not learned
    scale: torch.Tensor | None
    v: torch.Tensor | None

    @classmethod
    def of(cls, gp, system, p: int, single: bool, parameters: bool, theta_start) -> _TermFields:
        """The fields of ``gp``'s feature kernel; with ``parameters``, theta starts at its prior mean or at
        ``theta_start`` (its joint fit needs single shooting, ``single``)."""
        kd = dict(dtype=gp.dtype, device=gp.device)
        k = len(system.parameters) if parameters else 0
        if k and not single:
            raise FittingError("the joint fit of G's uncertain parameters through the ODE needs single shooting")
        features = gp.covar_module.base_kernel.features
        if not k:
            return cls(system, features, p, None, None, None)
        mean, scale = system.parameters.mean.to(**kd), system.parameters.scale.to(**kd)
        v = torch.zeros(k, **kd)  # theta = m + s v, starting at the prior mean ...
        if theta_start is not None:  # ... or where asked (the known model's own fit)
            v = ((theta_start.to(**kd) - mean) / scale).clone()
        return cls(system, features, p, mean, scale, v)

    @property
    def k(self) -> int:
        """The number of G's parameters learned (0 without them)."""
        return 0 if self.v is None else self.v.numel()

    def known_at(self, vv):
        """G at theta = m + s vv (the system as declared when not learning theta)."""
        return self.system if vv is None else self.system.at(self.mean + self.scale * vv)

    def field(self, b, vv=None):
        """The right-hand side with F's coefficients ``b`` ``(p, d_out)`` and G at ``vv`` (default: the current v)."""
        known = self.known_at(self.v if vv is None else vv)
        system, features = self.system, self.features

        def field(y, t=None, u=None):
            x = system.select_inputs(y, u)
            return known.known_rhs(y, t, u) + system.embed(features(x) @ b)

        return field

    def fields(self, bs, vs=None):
        """One right-hand side for a stack of models: ``bs`` ``(m, p, d_out)``, copy c's coefficients driving rows
        c K ... c K + K - 1; ``vs`` ``(k,)`` one theta for every copy (one call of G; default the current v), or
        ``(m, k)`` copy c's theta (one call of G per distinct theta, over the rows of the copies that share it)."""
        vs = self.v if vs is None else vs
        system, features, p = self.system, self.features, self.p
        if vs is None or vs.dim() == 1:
            known = self.known_at(vs).known_rhs
        else:
            known = system.copies_rhs(self.mean + self.scale * vs)

        def field(y, t=None, u=None):
            f = features(system.select_inputs(y, u)).reshape(bs.shape[0], -1, p)  # (m, K, p)
            mixed = torch.einsum("mkp,mpo->mko", f, bs).reshape(y.shape[0], -1)
            return known(y, t, u) + system.embed(mixed)

        return field


@dataclass(frozen=True)
class _ThetaLaplace:
    """A round's pieces of theta's posterior (made once, after the last round): v, theta's Laplace covariance with
    F's coefficients marginalised and held fixed (in units of its prior sd), the Jacobian's columns of the
    coefficients and parameters (``J_p``) and of the offsets (``J_o``), and the coefficients, weights and offsets
    they were taken at."""

    v: torch.Tensor
    cov: torch.Tensor
    fixed: torch.Tensor
    J_p: torch.Tensor
    J_o: torch.Tensor
    beta: torch.Tensor
    W: torch.Tensor
    off: torch.Tensor


@dataclass(frozen=True)
class _Rounds:
    """Where the rounds ended: the weights ``W`` and coefficients ``beta`` ``(p, d_out)``, theta's last Laplace
    pieces (``None`` without parameters or when no Laplace step succeeded), and the optimiser's counts."""

    W: torch.Tensor
    beta: torch.Tensor
    laplace: _ThetaLaplace | None
    iterations: int
    evaluations: int


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
    W, beta, terms = _starting_terms(gp, start, only)
    single = hasattr(residuals, "many") and offsets is not None
    fields = _TermFields.of(gp, system, W.shape[0], single, parameters, theta_start)
    if s2 is None:
        s2 = _balanced_noise(residuals, fields.field(beta), trajectories)
    sd = s2.sqrt()
    rounds = RELEVANCE_ROUNDS if rounds is None else rounds
    found = _relevance_rounds(
        W, beta, terms, fields, residuals, offsets, s2, n_obs, max_iter=max_iter, rounds=rounds, progress=progress
    )
    record = None  # the misfit where the rounds ended and the sparse proposal: only for fit_trajectories' rival
    if propose or only is not None:
        proposes = propose and not fields.k
        record = _relevance_record(residuals, fields, found.beta, found.W, offsets, sd, n_obs, gp, proposes)
    refined = _as_correction_gp(gp, found.W, found.beta)
    refined.n_iterations_, refined.n_evaluations_ = found.iterations, found.evaluations
    refined.n_rhs_evaluations_ = residuals.nfe
    refined.state_noise_ = s2
    refined.relevance_record_ = record
    if offsets is not None:
        refined.initial_states_ = trajectories.initial_conditions + offsets.detach() * sd[: trajectories.state_dim]
    if fields.k:  # theta's posterior from the last round's Laplace step, F's coefficients marginalised and held fixed
        laplace = found.laplace
        refined.parameters_laplace_ = None if laplace is None else _theta_posterior(laplace, fields, residuals, sd)
    return refined


def _starting_terms(gp, start, only) -> tuple[torch.Tensor, torch.Tensor, _TermScale]:
    """``(W, beta, scale)``: the prior variances and coefficients ``(p, d_out)`` the rounds start from (``gp``'s fit,
    every term active; or F = 0 with equal shares of ``start``; only the terms ``only`` where given) and what the
    weights are compared with."""
    base = gp.covar_module.base_kernel
    Phi = base.features(gp.train_inputs_)  # (N, p): the monomials or a user library
    p = Phi.shape[1]
    d_out = gp.output_dim
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
        W = (start.to(dtype=gp.dtype, device=gp.device).reshape(1, -1) / (p * phi2)).expand(p, d_out).clone()
        beta = torch.zeros_like(W)
    if only is not None:  # the terms of a proposal (torchmisspec.learning.refinement._term_price): the others removed
        W = torch.where(only, W, torch.zeros_like(W))
        beta = torch.where(only, beta, torch.zeros_like(beta))
    return W, beta, _TermScale(phi2, second, shared)


def _relevance_rounds(W, beta, terms, fields, residuals, offsets, s2, n_obs, *, max_iter, rounds, progress) -> _Rounds:
    """Round after round, the MAP of the active coefficients (:func:`_map_coefficients`), their Laplace posterior
    (:func:`_laplace_step`) and MacKay's update of the weights (:func:`_mackay_update`), until the active terms and
    weights settle, no term is left or a Laplace step fails."""
    sd = s2.sqrt()
    iterations = evaluations = 0
    laplace = None
    bar = progress_bar(progress, rounds, "fit_trajectories: term weights through the ODE", "round")
    for round_ in range(rounds):
        bar.update()
        active = W > 0
        if not bool(active.any()):
            beta = torch.zeros_like(W)
            break
        rounds_iter = max_iter if round_ == 0 else min(max_iter, _LATER_ITERATIONS)
        b_act, its, evals = _map_coefficients(W, beta, active, fields, residuals, offsets, s2, n_obs, rounds_iter)
        iterations += its
        evaluations += evals
        beta = torch.zeros(W.shape, dtype=W.dtype, device=W.device)
        beta[active] = b_act
        with torch.no_grad():
            step = _laplace_step(W, beta, active, fields, residuals, offsets, sd)
            if step is None:
                break
            Sigma, theta = step
            laplace = laplace if theta is None else theta
            new, settled = _mackay_update(W, active, b_act, Sigma, terms)
            beta = beta * (new > 0)
            W = new
        if settled:
            break
    bar.close()
    return _Rounds(W, beta, laplace, iterations, evaluations)


def _map_coefficients(W, beta, active, fields, residuals, offsets, s2, n_obs, max_iter) -> tuple:
    """``(active coefficients, iterations, evaluations)``: one round's MAP under the weights ``W``, in units of the
    coefficients' prior sd: Levenberg-Marquardt with single shooting (the offsets, and G's parameters, with them,
    updated in place), L-BFGS on the log posterior with multiple shooting."""
    root = W[active].sqrt()
    u = (beta[active] / root).clone().requires_grad_(True)  # coefficients in units of their prior std
    if hasattr(residuals, "many") and offsets is not None:  # single shooting: Levenberg-Marquardt
        theta = None if not fields.k else (fields.v, fields.field, fields.fields)
        its, evals = _levenberg_marquardt(
            u, offsets, active, root, beta, fields.field, fields.fields, residuals, s2.sqrt(), max_iter=max_iter,
            theta=theta,
        )  # fmt: skip
    else:

        def field_and_prior(uv):
            b = torch.zeros(W.shape, dtype=W.dtype, device=W.device).index_put(active.nonzero(as_tuple=True), uv * root)
            return fields.field(b), 0.5 * uv.pow(2).sum()

        result = _maximise_posterior(
            [u], offsets, field_and_prior, residuals, s2, n_obs, max_iter=max_iter, progress=False,
            shooting="relevance",
        )  # fmt: skip
        its, evals = result.iterations, result.evaluations
    return (u.detach() * root).clone(), its, evals


def _laplace_step(W, beta, active, fields, residuals, offsets, sd) -> tuple | None:
    """``(Sigma, theta's pieces or None)``: the Laplace posterior variances ``(q,)`` of the active coefficients from
    the Gauss-Newton Hessian of the scaled misfit in (coefficients, G's parameters, initial-state offsets), the
    offsets marginalised (Schur complement); ``None`` when the Hessian cannot be inverted."""
    k, kd = fields.k, dict(dtype=W.dtype, device=W.device)
    off = None if offsets is None else offsets.detach()
    q = int(active.sum())
    J_o = None
    if off is not None:  # single shooting: the coefficients', G's parameters' and offsets' columns at once
        J_p = _joint_columns(residuals, fields.fields, beta, active, fields.v, off, sd)
        J_p, J_o = J_p[:, : q + k], J_p[:, q + k :]
    else:  # multiple shooting (no parameters, no offsets)
        J_p = _coefficient_columns(residuals, fields.field, beta, active, off, sd, fields.fields)
    # G's parameters' prior N(0, 1) in units of their prior sd
    H = J_p.T @ J_p + torch.diag(torch.cat([1.0 / W[active], torch.ones(k, **kd)]))
    if off is not None:  # the offsets' block: column j moves component j of every initial state
        Kx, dd = off.shape
        Hbo = J_p.T @ J_o
        Hoo = J_o.T @ J_o + torch.eye(Kx * dd, **kd)  # the offsets' prior N(0, 1) in units of sd
        H = H - Hbo @ torch.linalg.solve(Hoo, Hbo.T)  # marginal over the offsets (Schur complement)
    try:
        inverse = torch.linalg.inv(H)
        theta = None
        if k:
            fixed = torch.linalg.inv(H[q:, q:])
            theta = _ThetaLaplace(fields.v.clone(), inverse[q:, q:], fixed, J_p, J_o, beta.clone(), W, off)
    except torch.linalg.LinAlgError:
        return None
    return inverse.diagonal()[:q], theta


def _mackay_update(W, active, b_act, Sigma, terms: _TermScale) -> tuple[torch.Tensor, bool]:
    """``(new weights, settled)``: MacKay's rule ``w_j = sum_o beta_oj^2 / sum_o gamma_oj`` (one weight per term
    summed over the outputs when they share it), terms below :data:`~torchmisspec.gp._features.PRUNE` of the
    targets' second moment removed; settled when the active set holds and no weight moved by 1 % or more."""
    from ...gp._features import PRUNE

    new = torch.zeros_like(W)
    gam = (1.0 - Sigma / W[active]).clamp(1e-12, 1.0)
    num = torch.zeros_like(W)
    num[active] = b_act.pow(2)
    den = torch.zeros_like(W)
    den[active] = gam
    if terms.shared:  # one weight per term shared by the outputs
        num = num.sum(1, keepdim=True).expand_as(W)
        den = den.sum(1, keepdim=True).expand_as(W)
    new[active] = num[active] / den[active].clamp_min(1e-12)
    new[new * terms.phi2 < PRUNE * terms.second] = 0.0
    both = (new > 0) & active
    change = float((new[both].log() - W[both].log()).abs().max()) if bool(both.any()) else 0.0
    return new, bool(((new > 0) == active).all()) and change < 1e-2


def _as_correction_gp(gp, W: torch.Tensor, beta: torch.Tensor):
    """Back to a :class:`~torchmisspec.CorrectionGP`: the new weights ``W``, and pseudo-targets whose posterior mean
    is exactly ``phi(x)^T beta`` (at inputs enough to span the active terms: more terms than samples could not
    reproduce beta)."""
    base = gp.covar_module.base_kernel
    scale = gp.covar_module.outputscale.detach().reshape(-1, 1)  # (B, 1)
    X, targets, noise = _spanning_inputs(gp.train_inputs_, gp.train_targets_, gp.train_noise_, base.features, W)
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
    return tmp.condition(X, Yhat, noise=noise)


def _theta_posterior(laplace: _ThetaLaplace, fields: _TermFields, residuals, sd) -> tuple:
    """``parameters_laplace_``: theta's mean ``(k,)``, its covariance with F's coefficients marginalised (or the
    cluster-robust one, :func:`_robust`) and with F held fixed ``(k, k)``, in theta's own units."""
    r = residuals(fields.field(laplace.beta, laplace.v), laplace.off, sd) / sd
    cov = _robust(laplace.cov, laplace.J_p, laplace.J_o, r, residuals, laplace.W)
    s = fields.scale
    scaled = (s[:, None] * c * s[None, :] for c in (cov, laplace.fixed))
    return (fields.mean + s * laplace.v, *scaled)


def _relevance_record(residuals, fields: _TermFields, beta, W, offsets, sd, n_obs, gp, propose: bool) -> dict:
    """Where the rounds ended: the scaled misfit, the number of kept terms and, with ``propose`` (one weight per
    coefficient), the sparse set :func:`~torchmisspec.learning.refinement._term_price.forward_selection` proposes there
    (``None`` otherwise, or when a solve fails)."""
    off = None if offsets is None else offsets.detach()
    with torch.no_grad():
        try:
            r = (residuals(fields.field(beta), off, sd) / sd).reshape(-1)
        except IntegrationError:
            return {"misfit": math.inf, "terms": int((W > 0).sum()), "active": W > 0, "proposal": None}
        record = {"misfit": float(r.pow(2).sum()), "terms": int((W > 0).sum()), "active": W > 0, "proposal": None}
        if not propose or not (gp.per_output or W.shape[1] == 1):
            return record
        try:
            every = torch.ones_like(W, dtype=torch.bool)
            if off is None:
                J, J_f = _coefficient_columns(residuals, fields.field, beta, every, off, sd, fields.fields), None
            else:
                J = _joint_columns(residuals, fields.fields, beta, every, None, off, sd)
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
