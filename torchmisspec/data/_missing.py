"""Missing entries: local fits of each state component from its own observed times.

States with missing entries are ``(K, T, d)`` tensors with NaN where a component was not observed, and a boolean
mask ``observed (K, T, d)``. Every function here treats each (experiment, component) series separately: the stencil
of time ``t_i`` is the ``width`` observed samples of that component nearest to ``t_i`` in index order (centred when
``t_i`` itself is observed, exactly the stencil the full-data estimators use; otherwise the ``width // 2``
observed samples before ``t_i`` and the rest after, shifted inward at the ends). From the stencil a local polynomial
gives both the value and the derivative at ``t_i``, so missing entries get a fitted value and every entry a
derivative estimate from observed samples only. A time that is missing in every component is simply not a node of
any stencil: masking a whole row gives the same estimates at the other rows as deleting it.
"""

from __future__ import annotations

import torch

from .._errors import InputError


def _nodes(times: torch.Tensor, observed: torch.Tensor, width: int) -> torch.Tensor:
    """``(K, d, T, width)`` time indices of the stencil of every entry; ``times (K, T)``, ``observed (K, T, d)``.

    Series with fewer than ``width`` observations get stencils that include unobserved indices: the caller checks
    the counts first (or discards those series)."""
    K, T, d = observed.shape
    obs = observed.permute(0, 2, 1)  # (K, d, T)
    n = obs.sum(-1, keepdim=True)  # (K, d, 1)
    order = torch.argsort((~obs).to(torch.int8), dim=-1, stable=True)  # observed indices first, in time order
    before = torch.cumsum(obs.to(torch.long), -1) - obs.to(torch.long)  # observed samples strictly before t_i
    start = torch.minimum(before - width // 2, n - width).clamp_min(0)  # (K, d, T)
    compact = (start.unsqueeze(-1) + torch.arange(width, device=times.device)).clamp_max(T - 1)
    return order.gather(-1, compact.reshape(K, d, T * width)).reshape(K, d, T, width)


def _gather(values: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    """``values (K, d, T)`` at ``nodes (K, d, T, w)``."""
    K, d, T, w = nodes.shape
    return values.gather(-1, nodes.reshape(K, d, T * w)).reshape(K, d, T, w)


def lagrange_weights(dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Value and derivative weights of the Lagrange interpolant through nodes at offsets ``dt (..., m)`` from the
    evaluation point (which need not be a node): ``L_j(0)`` and ``L_j'(0)``."""
    m = dt.shape[-1]
    values, derivs = [], []
    for j in range(m):
        value = torch.ones_like(dt[..., 0])
        deriv = torch.zeros_like(dt[..., 0])
        for k in range(m):
            if k == j:
                continue
            value = value * (-dt[..., k]) / (dt[..., j] - dt[..., k])
            term = 1.0 / (dt[..., j] - dt[..., k])
            for ell in range(m):
                if ell in (j, k):
                    continue
                term = term * (-dt[..., ell]) / (dt[..., j] - dt[..., ell])
            deriv = deriv + term
        values.append(value)
        derivs.append(deriv)
    return torch.stack(values, dim=-1), torch.stack(derivs, dim=-1)


def polynomial_weights(dt: torch.Tensor, degree: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Value and derivative weights of the least-squares polynomial of ``degree`` through nodes at offsets
    ``dt (..., w)`` from the evaluation point (Savitzky-Golay on a non-uniform grid; the interpolant when
    ``w = degree + 1``). The derivative weights are zero for degree 0."""
    scale = dt.abs().amax(dim=-1, keepdim=True).clamp_min(torch.finfo(dt.dtype).tiny)
    powers = torch.arange(degree + 1, device=dt.device, dtype=dt.dtype)
    X = (dt / scale).unsqueeze(-1) ** powers  # (..., w, p+1)
    Q, R = torch.linalg.qr(X, mode="reduced")
    e = torch.zeros((*R.shape[:-1], 2), dtype=dt.dtype, device=dt.device)
    e[..., 0, 0] = 1.0
    if degree >= 1:
        e[..., 1, 1] = 1.0
    z = torch.linalg.solve_triangular(R.transpose(-1, -2), e, upper=False)  # (..., p+1, 2)
    w = Q @ z  # (..., w, 2)
    return w[..., 0], w[..., 1] / scale


def check_counts(observed: torch.Tensor, need: int, what: str, experiment_names=None) -> None:
    """Raise :class:`InputError` when some (experiment, component) series has fewer than ``need`` observations."""
    counts = observed.sum(1)  # (K, d)
    if int(counts.min()) >= need:
        return
    k, j = (int(i) for i in (counts < need).nonzero()[0])
    fix = "use an estimator with a smaller stencil or drop that experiment"
    if int(counts[k, j]) < 3:  # not measured there (Trajectories.measured): the fit through the ODE handles it
        fix = (
            "a component an experiment does not measure has no derivative samples: fit_correction learns such data "
            "through the ODE (torchmisspec.learning.refinement.partial)"
        )
    raise InputError(
        f"{what}: expected at least {need} observed values of every state component in every experiment, got "
        f"{int(counts[k, j])} of component {j} in experiment {k} (its other values are missing); {fix}"
    )


def local_fit(
    states: torch.Tensor, times: torch.Tensor, observed: torch.Tensor, *, kind: str, width: int, degree: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(values, derivatives)``, each ``(K, T, d)``: the local fit of every component at every time from its own
    observed samples (``kind="lagrange"``: the interpolant through ``width`` samples; ``"poly"``: least squares of
    ``degree``). ``states (K, T, d)`` (any values where unobserved), ``times (K, T)``, ``observed (K, T, d)``;
    every series must have at least ``width`` observations (see :func:`check_counts`)."""
    nodes = _nodes(times, observed, width)  # (K, d, T, w)
    K, T, d = states.shape
    tk = times.unsqueeze(1).expand(K, d, T)
    dt = _gather(tk, nodes) - tk.unsqueeze(-1)
    y = _gather(states.permute(0, 2, 1), nodes)  # (K, d, T, w), observed values only
    if kind == "lagrange":
        wv, wd = lagrange_weights(dt)
    else:
        wv, wd = polynomial_weights(dt, degree)
    values = (wv * y).sum(-1).permute(0, 2, 1)
    derivs = (wd * y).sum(-1).permute(0, 2, 1)
    return values, derivs


#: Samples of the local quadratic least-squares fit that fills missing entries (:func:`fill`).
FILL_WINDOW = 5


def fill(states: torch.Tensor, times: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
    """``states (K, T, d)`` with every missing entry replaced by the value of a local quadratic least-squares fit
    through the :data:`FILL_WINDOW` nearest observed samples of its component (fewer when the component has fewer:
    the interpolant of degree one less than their number, a constant for one; a component never observed in an
    experiment stays NaN there). Observed entries are unchanged."""
    if bool(observed.all()):
        return states
    counts = observed.sum(1)  # (K, d)
    out = states.clone()
    missing = ~observed
    for width in sorted({min(int(c), FILL_WINDOW) for c in counts.flatten().tolist()} - {0}):  # 0: stays NaN
        series = (counts.clamp_max(FILL_WINDOW) == width).unsqueeze(1)  # (K, 1, d)
        values, _ = local_fit(
            torch.where(observed, states, 0.0), times, observed, kind="poly", width=width, degree=min(2, width - 1)
        )
        out = torch.where(missing & series, values, out)
    return out
