"""The corrected model dy/dt = G(y) + mu(y), mu the GP posterior mean of F, integrated with torchdiffeq; and
trajectories under posterior draws of F (:meth:`CorrectedODE.posterior`), with uncertainty bands."""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import nn

from .._errors import InputError, IntegrationError, NotFittedError, ShapeError, TorchMisspecWarning, clipped, warn
from .._ode import initial_conditions_and_times, solve
from .._validation import check_input_names, check_positive_int, check_real
from ..data import Trajectories
from ..gp import CorrectionGP
from ..learning.choice._time_pieces import MIN_PIECE, piece_samples, time_pieces
from ..learning.refinement.partial import complete, estimate_initial_states, initial_guess
from ..learning.refinement.trajectory_fit import _mean_field
from ..learning.samples.observations import _check_trajectories_and_system
from ..parallel import adaptive_threads
from ..parameters import ParameterPosterior
from ..systems import MisspecifiedSystem
from ._bands import TrajectoryPosterior
from ._draws import draws_region, solve_draws, warn_left
from .calibration import calibrate_bands
from .solver import Solver, as_solver

__all__ = ["SUPPORT_THRESHOLD", "UPDATE_ERROR", "CorrectedODE", "TrajectoryPosterior"]


#: Default ``update_error`` of :meth:`CorrectedODE.posterior`: a certified bound of 0.1 % of the prior standard
#: deviation on the compression of the draws' update (far below any posterior standard deviation it is added to).
UPDATE_ERROR = 1e-3


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
        check_input_names(gp, system.input_names(), f"system '{system.name}'")
        self.system = system
        self.gp = gp
        #: G's uncertain parameters: their posterior from the fit (``gp.parameters_``), or the prior when the GP was
        #: not fitted with them; G runs at its mean (``system.at``) and each posterior draw at a draw of theta
        self.parameters_ = None
        if system.parameters is not None:
            record = getattr(gp, "parameters_", None)
            if record is None or tuple(record.names) != system.parameters.names:
                record = ParameterPosterior.prior(
                    system.parameters, len(gp.train_inputs_), gp.output_dim, gp.train_inputs_
                )
            self.parameters_ = record
            system = system.at(record.mean)
        self._known = system  # G at the parameters' posterior mean (the system itself when it has none)
        self.nfe = 0  # right-hand-side evaluations of the last predict()
        #: ``(B,)`` booleans of the last :meth:`predict` (and :meth:`posterior`'s mean paths): the forecasts whose
        #: solve failed before their last output time (NaN from the first output time not reached)
        self.incomplete = None

    @property
    def calibration_(self):
        """The :class:`~torchmisspec.prediction.calibration.BandCalibration` of the GP's bands (``None`` before any
        :meth:`calibrate`): kept on the GP (``gp.calibration_``), so it is saved and loaded with it."""
        return getattr(self.gp, "calibration_", None)

    def correction(self, y: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """mu placed on the full state: ``(..., d)`` from states ``(..., d)`` (and controls ``(..., m)`` when F
        depends on them)."""
        return self._correction(self.system.check_states(y, "y"), None, u)

    def _correction(self, y: torch.Tensor, cache, u: torch.Tensor | None = None) -> torch.Tensor:
        x = self.system.select_inputs(y, u)
        shape = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1]).to(self.gp.device, self.gp.dtype)
        # inside predict() the cache was validated once for the whole solve; a direct call checks everything
        mu = self.gp.predict_mean(x) if cache is None else cache.mean(x, check=False)
        return self.system.embed(mu.reshape(*shape, -1).to(y.device, y.dtype))

    def field(self, y: torch.Tensor, t=None, u: torch.Tensor | None = None) -> torch.Tensor:
        """G + mu for states ``(..., d)``; ``t`` and ``u`` as for :meth:`MisspecifiedSystem.known_rhs
        <torchmisspec.MisspecifiedSystem.known_rhs>` (needed when the system has time or controls)."""
        return self._known.known_rhs(y, t, u) + self.correction(y, u)

    def forward(self, t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """torchdiffeq's ``func(t, y)`` for a system without controls (with controls, use :meth:`predict`)."""
        return self.field(y, None if self.system.autonomous else t)

    @adaptive_threads()
    def predict(
        self,
        y0,
        times,
        *,
        solver: Solver | None = None,
        controls=None,
    ) -> torch.Tensor:
        """Integrate the corrected model from every initial condition in one batched solve.

        Args:
            y0: ``(B, d)`` initial conditions at ``times[..., 0]`` (or ``(d,)`` for one).
            times: ``(T,)`` shared, or ``(B, T)`` per initial condition; strictly increasing.
            controls: for a system with controls, the B experiments' input profiles
                (:class:`~torchmisspec.signals.Controls`; each experiment its own, still one solve).
            solver: the solver's settings (:class:`~torchmisspec.Solver`: method, tolerances, step limit, options);
                default ``Solver()``: dopri5 at the package's prediction tolerances (see :mod:`torchmisspec._ode`),
                at most 10,000 steps, beyond which :class:`IntegrationError` names the initial conditions that stalled
                the solve.

        Returns:
            states ``(B, T, d)`` in the GP's dtype. A forecast whose solve fails before its last output time (its
            trajectory blows up or stalls there) keeps what was computed up to the failure and is NaN from the first
            output time not reached: it is flagged in ``model.incomplete`` (``(B,)`` booleans) and named in one
            :class:`~torchmisspec.TorchMisspecWarning`; the other forecasts are solved again without it.
            Raises :class:`IntegrationError` where nothing could be computed: every forecast fails before its
            second output time (or the method keeps nothing: only torchdiffeq's adaptive Runge-Kutta methods do).

        Differentiable: when ``y0`` or ``times`` requires grad, or a hyperparameter of the GP does (set
        ``requires_grad_(True)`` on its raw GPyTorch parameter, e.g. ``gp.covar_module.base_kernel.raw_lengthscale``;
        the GP then recomputes its posterior solve with the graph), the result keeps the autograd graph through the
        solver (torchdiffeq's direct backpropagation), so ``states.sum().backward()`` gives sensitivities.
        Otherwise no graph is built.
        """
        y0, times = initial_conditions_and_times(
            y0, times, self.system.state_dim, self.system.check_states, dtype=self.gp.dtype, device=self.gp.device
        )
        return self._forecast(y0, times, self._controls(controls, y0), as_solver(solver).keywords())

    def _forecast(self, y0: torch.Tensor, times: torch.Tensor, controls, solver: dict) -> torch.Tensor:
        """:meth:`predict`'s solves: all forecasts at once; where the solve fails, the rows it names keep what it
        computed (NaN after) and the others are solved again together."""
        B = y0.shape[0]
        self.incomplete = torch.zeros(B, dtype=torch.bool)
        out, failure, nfe = None, None, 0
        pending = torch.arange(B, device=y0.device)
        while pending.numel():
            grid = times if times.dim() == 1 else times[pending]
            u = None if controls is None else controls[pending.tolist()]
            try:
                states, named = self._solve(y0[pending], grid, u, partial=True, **solver), []
                nfe += self.nfe
            except IntegrationError as exc:
                states = getattr(exc, "states", None)
                named = [i for i in getattr(exc, "suspects", []) if i < pending.numel()]
                if states is None or not named:
                    raise
                nfe, failure = nfe + exc.nfe, failure or exc
            if out is None and not named:
                return states  # the first solve succeeded
            out = states.new_full((B, *states.shape[1:]), math.nan) if out is None else out
            out[pending] = states
            if not named:
                break
            self.incomplete[pending[named].cpu()] = True
            keep = torch.ones(pending.numel(), dtype=torch.bool, device=pending.device)
            keep[named] = False
            pending = pending[keep]
        self.nfe = nfe
        reached = torch.isfinite(out).all(-1)  # (B, T)
        if not bool(reached[:, 1:].any()):  # nothing beyond the initial conditions
            raise failure
        stopped = self.incomplete.nonzero().flatten().tolist()
        last = [float((times if times.dim() == 1 else times[b])[int(reached[b].sum()) - 1]) for b in stopped[:5]]
        warn(
            f"CorrectedODE.predict: {len(stopped)} of {B} forecast(s) stop early (initial condition(s) "
            f"{stopped[:10]}{' ...' if len(stopped) > 10 else ''}, their last output reached at t = "
            f"{', '.join(f'{t:.4g}' for t in last)}{' ...' if len(stopped) > 5 else ''}): their states are NaN from "
            f"the first output time not reached, flagged in model.incomplete. The first solve that failed: "
            f"{clipped(str(failure), 500)}",
            TorchMisspecWarning,
        )
        return out

    def _solve(self, y0, times, controls, *, box=None, partial=False, **solver) -> torch.Tensor:
        """One batched solve of the corrected model; ``box`` stops the rows that leave it, and with ``partial`` a
        failure carries what was computed (:func:`torchmisspec._ode.solve`)."""
        y0, times = initial_conditions_and_times(
            y0, times, self.system.state_dim, self.system.check_states, dtype=self.gp.dtype, device=self.gp.device
        )
        hyper = torch.is_grad_enabled() and self.gp._hyperparameters_require_grad()
        # refreshed here if the GP changed since its last prediction; with the graph to the hyperparameters when
        # one of them requires grad
        cache = self.gp.posterior(differentiable=hyper)
        controls = self._controls(controls, y0)

        def rhs(y: torch.Tensor, t, u) -> torch.Tensor:
            return self._known.known_rhs(y, t, u) + self._correction(y, cache, u)

        field, timed, jumps = self.system.solver_field(rhs, controls)
        with torch.set_grad_enabled(_wants_graph(y0, times) or hyper):
            states, self.nfe = solve(
                field,
                y0,
                times,
                what="CorrectedODE.predict",
                timed=timed,
                jumps=jumps,
                box=box,
                partial=partial,
                **solver,
            )
        return states

    @adaptive_threads()
    def posterior(
        self,
        y0,
        times,
        *,
        num_samples: int = 64,
        generator: torch.Generator | None = None,
        num_features: int | None = None,
        feature_error: float | None = None,
        update_error: float | None = UPDATE_ERROR,
        solver: Solver | None = None,
        support_threshold: float | None = None,
        hyperparameters: str = "fixed",
        hyperparameter_samples: int = 8,
        scale: float | None = None,
        controls=None,
    ) -> TrajectoryPosterior:
        """Trajectories under posterior draws of F: uncertainty bands on the predicted paths.

        ``num_samples`` functions F_s are drawn from the GP posterior by pathwise conditioning
        (:meth:`CorrectionGP.sample_functions <torchmisspec.CorrectionGP.sample_functions>`): each is one function
        that the solver evaluates wherever a path goes, so path s is the trajectory of dy/dt = G(y) + F_s(y). All
        B x S paths are integrated in one batched solve; the trajectory of the posterior mean (:meth:`predict`) is
        integrated too, for comparison and for the extrapolation check. The draws include the GP's noise model
        (learned noise, or the known per-sample noise of the training samples) through the posterior itself.

        Extrapolation check: along every posterior-mean path the posterior standard deviation of F is divided by the
        prior's (the largest over the outputs); a path on which this ratio exceeds ``support_threshold`` (default
        :data:`SUPPORT_THRESHOLD` = sqrt(1/2): the data have removed less than half of the prior variance there) is
        flagged in ``extrapolating`` and one :class:`~torchmisspec.TorchMisspecWarning` per call names how many.

        Args:
            y0: ``(B, d)`` initial conditions (or ``(d,)``).
            times: ``(T,)`` or ``(B, T)``, strictly increasing.
            num_samples: S >= 1 posterior draws of F.
            generator: ``torch.Generator`` on the GP's device, for reproducible draws.
            num_features: the number of prior features of the draws (see ``sample_functions``).
            feature_error: the prior features' error bound, instead of ``num_features`` (see ``sample_functions``).
            update_error: the draws' update is compressed onto a subset of the training inputs with a certified bound
                of ``update_error`` times the prior standard deviation on the change (default :data:`UPDATE_ERROR`;
                ``None``: exact); ``posterior.update_error`` is the bound reached.
            solver: the solver's settings (:class:`~torchmisspec.Solver`), as for :meth:`predict`: for the mean
                paths and the sampled paths alike.
            support_threshold: the extrapolation threshold in (0, 1].
            hyperparameters: ``"fixed"`` (default: the fitted values) or ``"laplace"``: the draws are split among
                ``hyperparameter_samples`` sets of hyperparameters drawn from the Laplace approximation of their
                posterior (``CorrectionGP.hyperparameter_samples``), so the bands allow for the hyperparameters'
                own uncertainty (ML-II alone is overconfident with few experiments; ``docs/studies/calibration.md``).
            hyperparameter_samples: the number of hyperparameter sets with ``"laplace"`` (at most ``num_samples``).
            controls: for a system with controls, the B experiments' input profiles, as for :meth:`predict`.
            scale: a factor c > 0 on every path's deviation from the mean path, y_c = y_mean + c (y_s - y_mean);
                default: the scale found by :meth:`calibrate`, or 1 (the GP's own bands) before any calibration. To
                first order in the draws' deviation this is the path of F_c = mu + c (F_s - mu) (the posterior
                covariance of F times c^2), but the paths are those of the GP's own draws: a widened field far
                from the data is never integrated, so a calibrated posterior cannot stall where the GP's own
                does not (integrating F_c with c = 8 made the solver stall in the issue's trial).

        Diverging draws: a sampled path that leaves the region of the data (``posterior.region``: the box of the
        initial conditions, the mean paths and the GP's observed states widened
        :data:`~torchmisspec.prediction._draws.REGION_WIDTHS` = 2 times its width on each side, within the observed
        states' box widened :data:`~torchmisspec.prediction._draws.REGION_LIMIT_WIDTHS` = 10 times) is stopped there in
        the one batched solve (never integrated to the step limit), and is NaN from its first output time outside it;
        one that stalls inside it keeps what was computed (NaN after) and the others are solved again together. One
        :class:`~torchmisspec.TorchMisspecWarning` names how many draws left and from which initial conditions; the
        bands, mean and quantiles come from the draws that remain (:class:`TrajectoryPosterior`), and
        ``posterior.fraction_remaining`` is the fraction of each initial condition's draws that stayed to the end.

        Returns:
            :class:`TrajectoryPosterior`.

        Raises:
            IntegrationError: the mean path cannot be computed beyond the initial conditions (:meth:`predict`; one
                that fails later is NaN from there, with a warning), or a sampled path fails where the solver names
                no culprit.

        Paths are differentiable with respect to ``y0`` and ``times`` when they require grad (the draws
        themselves are fixed functions: gradients in the hyperparameters go through :meth:`predict` only).
        """
        threshold = _check_threshold(support_threshold)
        num_samples = check_positive_int(num_samples, "num_samples")
        scale = self._band_scale(scale)
        solver = as_solver(solver)
        y0, times = initial_conditions_and_times(
            y0, times, self.system.state_dim, self.system.check_states, dtype=self.gp.dtype, device=self.gp.device
        )
        B, S = y0.shape[0], num_samples
        options = dict(num_features=num_features, feature_error=feature_error, update_error=update_error)
        draws = self._function_draws(S, hyperparameters, hyperparameter_samples, dict(options, generator=generator))
        controls = self._controls(controls, y0)
        mean_path = self.predict(y0, times, solver=solver, controls=controls)
        field, timed, jumps = self._draws_field(draws, S, B, controls, generator)
        grid = times if times.dim() == 1 else times.repeat(S, 1)
        settings = dict(**solver.keywords(), timed=timed, jumps=jumps)
        region = draws_region(y0, mean_path, self.gp)
        with torch.set_grad_enabled(_wants_graph(y0, times)):
            paths, self.nfe, stopped, escaped = solve_draws(field, y0.repeat(S, 1), grid, settings, B, region)
        left = torch.isnan(paths).any(-1).any(-1).reshape(S, B)  # the draws that left the region, or stalled in it
        if bool(left.any()):
            warn_left(left, stopped)
        times_out = times if times.dim() == 2 else times.expand(B, -1)
        support, extrapolating = self._extrapolation(mean_path, times_out, controls, threshold)
        samples = paths.reshape(S, B, *paths.shape[1:])
        if scale != 1.0:  # the paths' deviations from the mean path, scaled (never a re-integration)
            samples = mean_path + scale * (samples - mean_path)
        return TrajectoryPosterior(
            times=times_out,
            samples=samples,
            mean_path=mean_path,
            support=support,
            extrapolating=extrapolating,
            threshold=threshold,
            update_error=draws.update_error,
            state_names=self.system.state_names,
            fraction_remaining=1.0 - left.to(y0.dtype).mean(0),
            region=region,
            escaped=escaped.reshape(S, B, *escaped.shape[1:]),
        )

    def _band_scale(self, scale) -> float:
        """The bands' scale: ``scale`` checked, or the calibrated one (1 before any calibration, said in a warning,
        since the GP's own bands are usually too narrow)."""
        if scale is None and self.calibration_ is None:
            warn(
                "CorrectedODE.posterior: these bands are the GP's own, not calibrated on held-out experiments; with "
                "few experiments they are usually too narrow (docs/studies/calibration.md). Call "
                "model.calibrate(observed) once (it is kept and saved with the GP), or pass scale=1.0 to use the "
                "GP's own bands knowingly",
                TorchMisspecWarning,
            )
        if scale is None:
            scale = 1.0 if self.calibration_ is None else self.calibration_.scale
        return check_real(scale, "scale", positive=True)

    def _function_draws(self, S: int, hyperparameters: str, hyperparameter_samples: int, options: dict):
        """S posterior draws of F as one callable ``(S, M, d_in) -> (S, M, d_out)``: at the fitted hyperparameters
        (``"fixed"``), or split among hyperparameter sets drawn from their Laplace posterior (``"laplace"``)."""
        if hyperparameters not in ("fixed", "laplace"):
            raise InputError(f"hyperparameters: expected 'fixed' or 'laplace', got {hyperparameters!r}")
        if hyperparameters == "fixed":
            return self.gp.sample_functions(S, **options)
        M = min(check_positive_int(hyperparameter_samples, "hyperparameter_samples"), S)
        gps = self.gp.hyperparameter_samples(M, generator=options["generator"])
        sizes = [S // M + (1 if m < S % M else 0) for m in range(M)]
        return _Mixture([g.sample_functions(n, **options) for g, n in zip(gps, sizes, strict=True)])

    def _draws_field(self, draws, S: int, B: int, controls, generator):
        """The solver's field of the S x B sampled paths (:meth:`MisspecifiedSystem.solver_field
        <torchmisspec.MisspecifiedSystem.solver_field>`): rows s * B ... s * B + B - 1 follow G + F_s, and G at a
        draw of its parameters theta with each draw of F when G has uncertain parameters."""
        system, known = self.system, self._known
        theta = None
        if self.parameters_ is not None:  # a draw of theta with each draw of F (parameters.py)
            p = self.parameters_
            theta = p.draw_field(system, self.gp, p.sample(S, generator=generator) - p.mean, B)

        def rhs(y: torch.Tensor, t, u) -> torch.Tensor:  # y (S * B, d): draw s drives rows s * B ... s * B + B - 1
            x = system.select_inputs(y, u)
            g = known.known_rhs(y, t, u) if theta is None else theta(y, t, u, x)
            return g + system.embed(draws(x.reshape(S, B, -1)).reshape(S * B, -1))

        return system.solver_field(rhs, None if controls is None else controls.repeat(S))

    def _extrapolation(self, mean_path: torch.Tensor, times_out: torch.Tensor, controls, threshold: float):
        """``(support (B, T), extrapolating (B,))`` along the mean paths (:meth:`_support`), with one warning naming
        the paths that leave the data's support (none for a model known to need no correction: F = 0 has none)."""
        support = self._support(mean_path.detach(), None if controls is None else controls.at(times_out.detach()))
        extrapolating = support.amax(dim=-1) > threshold
        if bool(extrapolating.any()) and not getattr(self.gp, "known_model_", False):
            n, B = int(extrapolating.sum()), extrapolating.shape[0]
            first = extrapolating.nonzero().flatten()[:10].tolist()
            warn(
                f"CorrectedODE.posterior: {n} of {B} predicted path(s) leave the data's support (the posterior "
                f"standard deviation of F along the mean path exceeds {threshold:.3g} times the prior's; initial "
                f"conditions {first}{' ...' if n > 10 else ''}): there the correction is the prior's guess and the "
                "bands are as wide as the prior. Collect data nearer those states, or trust those paths less",
                TorchMisspecWarning,
            )
        return support, extrapolating

    def initial_states(self, trajectories) -> torch.Tensor:
        """``(K, d)`` every experiment's initial state under this model: the first observed states, with each
        component an experiment does not measure (:attr:`Trajectories.measured
        <torchmisspec.Trajectories.measured>`) estimated by fitting this model's mean path to the measured values
        (:func:`torchmisspec.learning.refinement.partial.estimate_initial_states`): for an experiment whose unmeasured
        starting values are not known. (:meth:`calibrate` does not use it: a held-out experiment starts from its first
        row, as a prediction would.)"""
        trajectories = self._partial(trajectories)
        if not trajectories.is_partial:
            return trajectories.initial_conditions
        start = trajectories.with_initial_states(initial_guess(trajectories))
        return estimate_initial_states(self._known, self._mean_rhs(), start, ~trajectories.measured)

    def complete(self, trajectories):
        """``trajectories`` with every component an experiment does not measure filled in by this model's mean path
        from :meth:`initial_states` (what :func:`~torchmisspec.correction_samples` needs of partly measured data);
        fully measured trajectories are returned as they are."""
        trajectories = self._partial(trajectories)
        if not trajectories.is_partial:
            return trajectories
        return complete(self._known, self._mean_rhs(), trajectories, self.initial_states(trajectories))

    def _partial(self, trajectories):
        """``trajectories`` checked and in the GP's dtype and device."""
        _check_trajectories_and_system(trajectories, self.system)  # shapes, controls, states named as the system's
        return trajectories.to(dtype=self.gp.dtype, device=self.gp.device)

    def _mean_rhs(self):
        """G (at theta's mean) + the posterior mean of F, as ``rhs(y, t, u)``."""
        return _mean_field(self._known, self.gp.posterior())

    def calibrate(self, trajectories, samples=None, **options):
        """Calibrate the bands of :meth:`posterior` on held-out experiments and make the result its default scale.

        With one experiment (every state measured, at least ``2 * MIN_PIECE`` times), the held-out experiments are
        pieces of its time (:func:`~torchmisspec.learning.choice._time_pieces.time_pieces`): each piece is forecast from
        its first state by the model refitted on the others (``result.held_out`` is ``"time pieces"``).

        ``samples`` default to the ones :func:`~torchmisspec.fit_correction` recorded on the GP (``gp.samples_``).
        See :func:`torchmisspec.prediction.calibration.calibrate_bands` (the arguments after ``samples`` are its
        keywords: ``level``, ``folds``, ``num_samples``, ``refit``, ``state_noise``, ``generator``, ``executor`` (the
        folds through a ``concurrent.futures.Executor``) and options for :meth:`posterior`, e.g.
        ``hyperparameters="laplace"``, which later calls should then use too, or ``solver=Solver(...)``). Costs one
        GP fit per fold plus about ten held-out posteriors per fold.

        Returns:
            the :class:`~torchmisspec.prediction.calibration.BandCalibration`, also kept on the GP as
            ``gp.calibration_`` (saved with it by ``gp.save``); later ``posterior`` calls use its ``scale`` unless given
            another.
        """
        if samples is None:
            samples = getattr(self.gp, "samples_", None)
            if samples is None:
                raise InputError(
                    "samples: expected the correction samples the GP was fitted on, got none: this GP has none "
                    "recorded (only fit_correction records them, as gp.samples_): pass calibrate(trajectories, samples)"
                )
        pieces = None
        if isinstance(trajectories, Trajectories) and trajectories.num_experiments == 1:
            pieces = time_pieces(trajectories)
            if pieces is None:
                raise InputError(
                    "trajectories: calibration holds out experiments, or with one experiment pieces of its time (each "
                    f"forecast from its first state); expected 2 or more experiments, or one with every state measured "
                    f"and at least {2 * MIN_PIECE} times, got one of {trajectories.experiments()[0][0].shape[0]} times"
                    + (" with some state not measured" if trajectories.is_partial else "")
                    + "; collect another experiment to calibrate, or use the GP's own bands (posterior(..., scale=1.0))"
                )
            samples, trajectories = piece_samples(samples, trajectories), pieces
        if getattr(trajectories, "is_partial", False) and trajectories.initial_states is None:
            # a held-out experiment starts where a prediction of a new one would: at its first observed values
            # (an unmeasured component never observed there at its mean over the others), not at values fitted to
            # its own later data, which would hide the initial states' uncertainty from the bands
            trajectories = trajectories.with_initial_states(initial_guess(trajectories))
        result = calibrate_bands(self, trajectories, samples, **options)  # a failure keeps the previous one
        if pieces is not None:
            result = dataclasses.replace(result, held_out="time pieces")
        self.gp.calibration_ = result
        return result

    def _controls(self, controls, y0: torch.Tensor):
        """The batch's controls, checked against the system, in the GP's dtype and on its device."""
        controls = self.system.check_controls(controls, y0.shape[0])
        return None if controls is None else controls.to(dtype=y0.dtype, device=y0.device)

    def _support(self, states: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, T)``: posterior over prior standard deviation of F at the states ``(B, T, d)`` (largest output)."""
        x = self.system.select_inputs(states, u)
        flat = x.reshape(-1, x.shape[-1]).to(self.gp.device, self.gp.dtype)
        return self.gp.posterior().sd_ratio(flat).reshape(states.shape[:-1])


#: Default ``support_threshold`` of :meth:`CorrectedODE.posterior`: posterior / prior standard deviation of F above
#: which a state is outside the data's support (the data have removed less than half of the prior variance).
SUPPORT_THRESHOLD = math.sqrt(0.5)


class _Mixture:
    """Function draws from several GPs (one per hyperparameter set), concatenated along the draws."""

    def __init__(self, parts) -> None:
        self.parts = parts
        self.update_error = max(p.update_error for p in parts)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:  # x (S, M, d_in)
        out, start = [], 0
        for p in self.parts:
            out.append(p(x[start : start + p.num_samples]))
            start += p.num_samples
        return torch.cat(out)


def _check_threshold(support_threshold) -> float:
    """The extrapolation threshold of :meth:`CorrectedODE.posterior`: a ratio of standard deviations in (0, 1]
    (:data:`SUPPORT_THRESHOLD` for ``None``)."""
    if support_threshold is None:
        return SUPPORT_THRESHOLD
    threshold = check_real(support_threshold, "support_threshold", positive=True)
    if threshold > 1.0:
        raise InputError(f"support_threshold: expected a ratio of standard deviations in (0, 1], got {threshold!r}")
    return threshold


def _wants_graph(*tensors: torch.Tensor) -> bool:
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
