"""The hyperparameters' own uncertainty: a Laplace approximation of their posterior around the ML-II fit.

ML-II (the fit) gives point values; with few experiments the data barely constrain some of them and predictions
that ignore it are overconfident. :func:`laplace_covariance` is a Gaussian in the log hyperparameters from the
Hessian of the exact log marginal likelihood (autograd through one Cholesky factorization), and
:func:`hyperparameter_samples` draws copies of the GP from it (``CorrectedODE.posterior(hyperparameters="laplace")``).
"""

from __future__ import annotations

import torch

from .._errors import InputError, LinearAlgebraError
from .._linalg import cholesky
from .._validation import check_positive_int
from ._features import check_dense
from ._paths import kernel_hyperparameters, kernel_matrix

__all__ = ["LOG_PRIOR_SD", "laplace_covariance", "hyperparameter_samples"]

#: Standard deviation of the weak prior on each log hyperparameter of :meth:`CorrectionGP.laplace_covariance`
#: (centred at the fitted value: a factor of about 7 either way).
LOG_PRIOR_SD = 2.0


def laplace_covariance(gp) -> tuple[list[str], torch.Tensor, torch.Tensor]:
    """A Laplace approximation of the posterior of the learned hyperparameters, in log space.

    At the fitted (ML-II) values, ``-H`` with H the Hessian of the exact log marginal likelihood in the log
    hyperparameters (autograd through one Cholesky factorization) is the precision of a Gaussian around them;
    a weakly informative prior N(log value, :data:`LOG_PRIOR_SD`^2) on each log hyperparameter is added, which
    keeps the covariance finite where the likelihood is flat (the data barely constrain a hyperparameter, as at
    small K) and clips directions of negative curvature (an optimum on a boundary) to the prior alone.

    Returns:
        ``(names, mean, covariance)``: a name per entry (``"lengthscale"``, ``"outputscale"``,
        ``"noise_variance"``, with an output index for per-output values), the log values ``(P,)`` and the
        ``(P, P)`` covariance. Only the RBF, Matern and polynomial kernels (the feature kernel's weights have
        their own posterior: :meth:`CorrectionGP.terms`).
    """
    gp._require_fitted()
    if gp.kernel_spec.terms:
        raise InputError(
            "laplace_covariance: the feature kernel's weights are not log hyperparameters; its uncertainty is "
            "the coefficients' posterior (gp.terms())"
        )
    free = gp._free_parameters()
    if not free:
        raise InputError(
            "laplace_covariance: expected a GP with a free hyperparameter, got one where every hyperparameter is "
            "fixed (nothing is uncertain): use hyperparameters='fixed'"
        )
    params = [p for _, p in free]
    names = []
    for name, p in free:
        n = p.numel()
        names += [name] if n == 1 else [f"{name}[{i}]" for i in range(n)]
    X, Y, noise = gp.train_inputs_, gp.train_targets_, gp.train_noise_
    Yb = gp._targets_batched(Y, noise)
    for p in params:
        p.requires_grad_(True)
    try:
        with torch.enable_grad():
            # the kernel written out in torch (GPyTorch's RBF has a custom backward without a second derivative)
            check_dense(X.shape[0])
            K = kernel_matrix(gp.kernel_spec, X, X, kernel_hyperparameters(gp), gp.degree)
            floor = gp._floor(gp.likelihood).noise.reshape(-1, 1)
            if noise is None:
                diag = floor
            else:
                diag = (noise.T if gp._batched(noise) else noise[:, 0].unsqueeze(0)) + floor
            if diag.shape[0] != K.shape[0]:
                K = K.expand(diag.shape[0], -1, -1)
            C = K + torch.diag_embed(diag.expand(K.shape[0], K.shape[-1]))
            L = cholesky(C, what="the training covariance (Laplace approximation)")
            alpha = torch.cholesky_solve(Yb, L)
            m = Yb.shape[-1]
            mll = -0.5 * (Yb * alpha).sum() - m * L.diagonal(dim1=-2, dim2=-1).log().sum()
            grads = torch.autograd.grad(mll, params, create_graph=True)
            g = torch.cat([t.reshape(-1) for t in grads])
            rows = [
                torch.cat([t.reshape(-1) for t in torch.autograd.grad(g[i], params, retain_graph=True)])
                for i in range(g.numel())
            ]
    except torch.linalg.LinAlgError as exc:
        raise LinearAlgebraError(
            f"laplace_covariance: the training covariance is not positive definite ({exc})"
        ) from exc
    finally:
        gp._freeze()
    H = torch.stack(rows).detach()
    H = 0.5 * (H + H.T)
    evals, evecs = torch.linalg.eigh(-H)
    precision = (evecs * evals.clamp_min(0.0)) @ evecs.T + torch.eye(len(names), dtype=H.dtype, device=H.device) / (
        LOG_PRIOR_SD**2
    )
    mean = torch.cat([p.detach().reshape(-1) for p in params])
    return names, mean, torch.linalg.inv(precision)


def hyperparameter_samples(gp, num_samples: int, *, generator: torch.Generator | None = None) -> list:
    """``num_samples`` copies of this GP, each conditioned on the same data with hyperparameters drawn from the
    Laplace approximation of their posterior (:func:`laplace_covariance`); for predictions that allow for the
    hyperparameters' own uncertainty (ML-II alone is overconfident when the data are few)."""
    num_samples = check_positive_int(num_samples, "num_samples")
    _, mean, cov = gp.laplace_covariance()
    root = cholesky(cov, what="the hyperparameters' Laplace covariance")
    z = torch.randn((num_samples, mean.numel()), generator=generator, dtype=mean.dtype, device=mean.device)
    draws = mean + z @ root.T
    out = []
    for theta in draws:
        copy_ = gp.condition(gp.train_inputs_, gp.train_targets_, noise=gp.train_noise_)
        start = 0
        with torch.no_grad():
            for _, p in copy_._free_parameters():
                p.copy_(theta[start : start + p.numel()].reshape(p.shape))
                start += p.numel()
        copy_.posterior()
        out.append(copy_)
    return out
