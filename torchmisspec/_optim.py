"""The one L-BFGS loop of the package: on an objective that supplies its own gradient through a surrogate.

Every fit maximises through :func:`maximise`: the GP's marginal likelihood (:mod:`torchmisspec.gp._fit`), the
features+rbf kernel's (:mod:`torchmisspec.gp._sum`), the GP in time of the derivative estimates and the trajectory
fit; progress shows when asked.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from ._validation import progress_bar

__all__ = ["OptimResult", "maximise"]


class OptimResult(NamedTuple):
    """What one optimisation pass did.

    Attributes:
        iterations: L-BFGS iterations.
        evaluations: objective evaluations (line-search steps included).
        value: the objective at the last evaluation.
    """

    iterations: int
    evaluations: int
    value: float


def maximise(
    params: list[torch.Tensor],
    evaluate: Callable[[], tuple[torch.Tensor, torch.Tensor]],
    *,
    max_iter: int,
    normaliser: float = 1.0,
    progress: bool = False,
    desc: str = "fit",
    tolerance_grad: float = 1e-7,
    tolerance_change: float = 1e-12,
    history_size: int = 20,
) -> OptimResult:
    """Maximise an objective over ``params`` with L-BFGS (strong Wolfe line search).

    Args:
        params: leaf tensors with ``requires_grad``.
        evaluate: returns ``(value, surrogate)``: the objective's value (no graph needed) and a scalar whose
            gradient in ``params`` equals the objective's gradient (e.g. ``_mll.gradient_surrogate``).
        max_iter: most L-BFGS iterations.
        normaliser: the objective is divided by it for the optimiser (e.g. the number of samples: O(1) gradients).
        tolerance_grad, tolerance_change, history_size: PyTorch L-BFGS's (on the normalised objective).
    """
    opt = torch.optim.LBFGS(
        params,
        lr=1.0,
        max_iter=max_iter,
        history_size=history_size,
        line_search_fn="strong_wolfe",
        tolerance_grad=tolerance_grad,
        tolerance_change=tolerance_change,
    )
    count = [0, float("nan")]
    flags = [p.requires_grad for p in params]
    for p in params:  # the model's parameters are frozen outside fitting (see CorrectionGP._freeze)
        p.requires_grad_(True)
    try:
        return _run(opt, evaluate, normaliser, progress, max_iter, desc, count)
    finally:
        for p, flag in zip(params, flags, strict=True):
            p.requires_grad_(flag)


def _run(opt, evaluate, normaliser, progress, max_iter, desc, count) -> OptimResult:
    with progress_bar(progress, max_iter, desc, "eval") as bar:

        def closure():
            opt.zero_grad()
            value, surrogate = evaluate()
            (-surrogate / normaliser).backward()
            count[0] += 1
            count[1] = float(value.detach())
            bar.update(1)
            bar.set_postfix(mll=f"{count[1]:.6g}")
            return -value.detach() / normaliser

        opt.step(closure)
    state = opt.state[opt._params[0]]
    return OptimResult(int(state.get("n_iter", 0)), count[0], count[1])
