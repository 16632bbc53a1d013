"""The corrected model dy/dt = G(y) + mu(y), mu the GP posterior mean of F, integrated with torchdiffeq."""

from __future__ import annotations

import torch
from torch import nn

from ._errors import InputError, NotFittedError, ShapeError
from ._ode import PREDICTION_TOLERANCES, initial_conditions_and_times, solve
from ._threads import adaptive_threads
from .gp import CorrectionGP
from .systems import MisspecifiedSystem

__all__ = ["CorrectedODE"]


class CorrectedODE(nn.Module):
    """Right-hand side G(y) + mu(y), with mu the posterior mean of the fitted correction GP.

    mu acts on the system's correction outputs and reads its correction inputs. The GP's posterior solve is cached
    when the GP is fitted, so a right-hand-side call costs G plus one kernel block k(y, X) @ alpha: nothing is
    refactorized. ``forward(t, y)`` follows torchdiffeq's ``func(t, y)`` convention and is differentiable in ``y``.

    Args:
        system: the misspecified system (its true correction, if any, is not used).
        gp: a fitted :class:`CorrectionGP` whose inputs/outputs match the system's correction indices.
    """

    def __init__(self, system: MisspecifiedSystem, gp: CorrectionGP) -> None:
        super().__init__()
        if not isinstance(system, MisspecifiedSystem):
            raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")
        if not isinstance(gp, CorrectionGP):
            raise InputError(f"gp: expected a CorrectionGP, got {type(gp).__name__}")
        if not gp.is_fitted:
            raise NotFittedError("gp: expected a fitted CorrectionGP; call gp.fit(samples.inputs, samples.targets)")
        if gp.input_dim != system.input_dim or gp.output_dim != system.output_dim:
            raise ShapeError(
                f"gp: expected a GP with {system.input_dim} inputs and {system.output_dim} outputs (the system's "
                f"correction_inputs={list(system.correction_inputs)} and correction_outputs="
                f"{list(system.correction_outputs)}), got one fitted with {gp.input_dim} inputs and "
                f"{gp.output_dim} outputs"
            )
        self.system = system
        self.gp = gp
        self.nfe = 0  # right-hand-side evaluations of the last predict()

    def correction(self, y: torch.Tensor) -> torch.Tensor:
        """mu placed on the full state: ``(..., d)`` from states ``(..., d)``."""
        return self._correction(y, None)

    def _correction(self, y: torch.Tensor, cache) -> torch.Tensor:
        x = self.system.select_inputs(y)
        shape = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1]).to(self.gp.device, self.gp.dtype)
        # inside predict() the cache was validated once for the whole solve; a direct call checks everything
        mu = self.gp.predict_mean(x) if cache is None else self.gp._mean_from(cache, x)
        return self.system.embed(mu.reshape(*shape, -1).to(y.device, y.dtype))

    def field(self, y: torch.Tensor) -> torch.Tensor:
        """G(y) + mu(y) for states ``(..., d)``."""
        return self.system.known_rhs(y) + self.correction(y)

    def forward(self, t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.field(y)

    @adaptive_threads()
    def predict(
        self,
        y0,
        times,
        *,
        method: str = "dopri5",
        rtol: float = PREDICTION_TOLERANCES[0],
        atol: float = PREDICTION_TOLERANCES[1],
        options: dict | None = None,
        max_steps: int | None = None,
    ) -> torch.Tensor:
        """Integrate the corrected model from every initial condition in one batched solve.

        Args:
            y0: ``(B, d)`` initial conditions at ``times[..., 0]`` (or ``(d,)`` for one).
            times: ``(T,)`` shared, or ``(B, T)`` per initial condition; strictly increasing.
            method: torchdiffeq method (dopri5 by default).
            rtol: relative tolerance (the package's prediction tolerance by default: see :mod:`torchmisspec._ode`).
            atol: absolute tolerance (likewise).
            options: further torchdiffeq solver options.
            max_steps: most solver steps (default 10,000); beyond it :class:`IntegrationError` names the initial
                conditions that stalled the solve.

        Returns:
            states ``(B, T, d)`` in the GP's dtype. Raises :class:`IntegrationError` if a trajectory blows up.
        """
        y0, times = initial_conditions_and_times(
            y0, times, self.system.state_dim, self.system.check_states, dtype=self.gp.dtype, device=self.gp.device
        )
        cache = self.gp._posterior_cache()  # refreshed here if the GP changed since its last prediction

        def field(y: torch.Tensor) -> torch.Tensor:
            return self.system.known_rhs(y) + self._correction(y, cache)

        with torch.no_grad():
            states, self.nfe = solve(
                field,
                y0,
                times,
                method=method,
                rtol=rtol,
                atol=atol,
                options=options,
                max_steps=max_steps,
                what="CorrectedODE.predict",
            )
        return states
