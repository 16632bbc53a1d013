"""The feature kernels' read-out: the learned terms of F with their coefficients' posterior (``gp.terms()``).

F = sum_j beta_j phi_j(x) under a feature kernel; given the samples, each coefficient has a Gaussian posterior. In
feature space (the feature kernel) it is :func:`~torchmisspec.gp._features.coefficient_posterior` per output; with
the RBF term beside the library (``features+rbf``) it is read from the dense posterior factor, the RBF part counted
as noise for the coefficients.
"""

from __future__ import annotations

import torch

from ._features import Term, coefficient_posterior

__all__ = ["terms"]


def terms(gp, names=None, *, all_terms: bool = False) -> list[Term]:
    """The learned terms of a feature kernel, with their coefficients' posterior means and standard deviations.

    The posterior of F = sum_j beta_j phi_j(x) given the training samples (and their noise): for each output and
    each term whose weight is not 0 (``all_terms=True``: every term), a :class:`~torchmisspec.gp._features.Term`
    with its posterior probability of being present (``inclusion``)
    whose ``str`` reads like ``"+0.01 +- 0.0003 * y1^2"``. ``names``: the inputs' names (default
    :attr:`input_names_`, the data's names that :func:`~torchmisspec.fit_correction` records, else x1, x2, ...).
    """
    labels = gp.feature_names(names)
    base = gp.covar_module.base_kernel
    X, Y, known = gp.train_inputs_, gp.train_targets_, gp.train_noise_
    Phi = base.features(X).detach()
    if not gp.kernel_spec.feature_space:  # the coefficients' posterior under the whole kernel (RBF term too)
        fac = gp.posterior().factor  # dense: C = Phi W Phi^T + a K_rbf + noise
        w = base.weights.detach().reshape(-1) * gp.covar_module.outputscale.detach().reshape(())
        out = []
        with torch.no_grad():
            for o in range(Y.shape[1]):
                # one factor for every output, or one per output (known noise that differs between outputs)
                chol = fac.chol[0 if fac.chol.shape[0] == 1 else o]
                V = torch.linalg.solve_triangular(chol, Phi * w, upper=False)  # L^-1 Phi W
                std = (w - V.pow(2).sum(0)).clamp_min(0.0).sqrt()
                alpha = fac.alpha[0, :, o] if fac.alpha.shape[0] == 1 else fac.alpha[o, :, 0]
                mean = w * (Phi.T @ alpha)
                for j, label in enumerate(labels):
                    if all_terms or float(w[j]) > 0:
                        out.append(Term(o, label, float(mean[j]), float(std[j]), float(w[j])))
        return out
    W = base.weights.detach().reshape(-1, Phi.shape[1]) * gp.covar_module.outputscale.detach().reshape(-1, 1)
    inclusion = base.inclusion.reshape(W.shape)
    floor = gp._floor(gp.likelihood).noise.detach().reshape(-1)
    out = []
    for o in range(Y.shape[1]):
        b = o if W.shape[0] > 1 else 0
        D = floor[o if floor.numel() > 1 else 0] + (0.0 if known is None else known[:, o])
        D = torch.as_tensor(D, dtype=gp.dtype, device=gp.device).expand(Y.shape[0])
        mean, std = coefficient_posterior(Phi, Y[:, o], D, W[b])
        for j, label in enumerate(labels):
            if all_terms or float(W[b, j]) > 0:
                out.append(Term(o, label, float(mean[j]), float(std[j]), float(W[b, j]), float(inclusion[b, j])))
    return out
