"""Fitting in the data's own units: every state divided by a scale taken from the data, the model returned in the
user's units (issue 40, item 7; issue 41, item 3).

**Why.** The fits of the package compare states, derivatives and corrections with tolerances, floors, step sizes
and candidate grids. Most of them are relative already (the GP's starting values and constraints, the derivative
estimators' noise, the relevance prices), but not all: the solvers' absolute tolerance (``atol`` 1e-7 inside a fit)
is the size of a state of 1e-3's whole change over a few steps, so the refinement through the ODE integrated such
data coarsely and blew up (``paper_linear`` scaled by 1e-3), and a shared kernel or an unweighted sum of squared
errors over the components lets a state in the thousands drown one in hundredths (the cross-validation chose an RBF
that fitted the small state four times worse). Instead of hunting every absolute constant, the default fit
(:func:`~torchmisspec.fit_correction`) and the fit through the ODE (:func:`~torchmisspec.fit_trajectories`) work in
units of the data: z = y / s, per state component, with F's outputs in the same units (F is a part of dy/dt) and
readings in units of their own. Every step then sees states of order 1, whatever the user's units.

**The scales** are powers of ten, the one nearest each component's root mean square over its observed values
(:func:`data_units`). Powers of ten, because data of order 1 (root mean square between 0.32 and 3.2) are left
exactly as they are, so the fits of such data are the package's fits as before, bit for bit; because a change of
units by a power of ten (grams and kilograms, counts in thousands) is then undone up to rounding, so the fit in
other units makes every choice the same (estimator, model, terms, steps) and its predictions scale exactly; and
because any other data end within a factor of about 3 of 1, where no absolute constant matters. What is not
rescaled: time (the package's tolerances and grids are relative to the time span already), controls (G reads them
in their units) and G's uncertain parameters (G is called with the user's theta).

**The model returned** is the one fitted in the data's units, rewritten exactly in the user's units
(:func:`rescaled`): training inputs, targets and known noise rescaled, an RBF's lengthscale (or, when its inputs'
scales differ, the kernel's ``input_scale``: it keeps seeing standardized inputs), the output scale and noise
variance by the outputs' squared scales, a feature kernel's weights by ``s_out^2 / m(s_in)^2`` for its monomial
``m``. So every consumer (CorrectedODE, bands, design, save and load, the command line) sees an ordinary
:class:`~torchmisspec.CorrectionGP` in the user's units. A shared kernel whose outputs have different scales becomes
a per-output model (the same values in each output's units: the exact rewrite); a model that cannot be rewritten (a
polynomial kernel or a user library of features with rescaled inputs; features+rbf, or an RBF in a feature space,
with inputs or outputs of different scales) is fitted in the user's units instead, as before (:func:`fit_in_units`).
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import dataclasses
import warnings

import torch

from .._ode import power_of_ten
from ..data import Readout, Trajectories
from ..gp import CorrectionGP
from ..gp._rescale import common_scale, rescaled, rescaled_template

__all__ = ["Units", "data_units", "fit_in_units", "refine_in_units", "rescaled", "rescaled_template"]

#: set while a fit runs in the data's units (or in the user's, as the fallback): the fits it calls are not rescaled
#: again
_INSIDE = contextvars.ContextVar("torchmisspec_units_inside", default=False)


@contextlib.contextmanager
def _inside():
    token = _INSIDE.set(True)
    try:
        yield
    finally:
        _INSIDE.reset(token)


@dataclasses.dataclass(frozen=True)
class Units:
    """The data's units: ``state`` ``(d,)`` one scale per state component, ``readings`` ``(m,)`` one per reading of
    a readout (``None`` without one); float64 on the CPU."""

    state: torch.Tensor
    readings: torch.Tensor | None = None

    @property
    def trivial(self) -> bool:
        """Every scale is 1: the user's units are the data's."""
        same = bool((self.state == 1).all())
        return same and (self.readings is None or bool((self.readings == 1).all()))

    @property
    def observed(self) -> torch.Tensor:
        """``(d + m,)``: the scales of the states and the readings (what a fit compares with its paths)."""
        return self.state if self.readings is None else torch.cat([self.state, self.readings])

    def inputs(self, system) -> torch.Tensor:
        """``(d_in,)``: the scales of F's inputs (a control's is 1: controls keep their units)."""
        d = system.state_dim
        return torch.tensor(
            [float(self.state[i]) if i < d else 1.0 for i in system.correction_inputs], dtype=torch.float64
        )

    def outputs(self, system) -> torch.Tensor:
        """``(d_out,)``: the scales of F's outputs (those of the states they act on)."""
        return self.state[list(system.correction_outputs)]

    # ---------------------------------------------------------------------------------------- into the data's units
    def trajectories(self, trajectories: Trajectories) -> Trajectories:
        """``trajectories`` in these units: states (and initial states) over ``state``, readings over ``readings``,
        the readout's weights rewritten to match (times, controls and names unchanged)."""
        kd = dict(dtype=trajectories.dtype, device=trajectories.device)
        s = self.state.to(**kd)
        _, states, _ = trajectories.padded()
        out = trajectories.with_states(states / s)
        if trajectories.initial_states is not None:
            out = out.with_initial_states(trajectories.initial_states / s)
        readout = trajectories.readout
        if readout is not None:
            r = self.readings.to(**kd)
            matrix = readout.matrix.to(**kd) * s / r.unsqueeze(-1)
            rescaled_readout = Readout(matrix, readout.names, state_names=readout.state_names)
            given = trajectories.readings
            readings = [x / r for x in given] if isinstance(given, tuple) else given / r
            out = out.with_readout(rescaled_readout, readings)
        return out

    def system(self, system):
        """``system`` in these units: G_z(z) = G(s z) / s (with its times, controls and theta as they are), the true
        F likewise, the domain and a known matrix rewritten; the same names, inputs and outputs."""
        out = copy.copy(system)
        out._vectorised = dict(system._vectorised)
        out.known = _scaled_known(system, self.state)
        if system.correction is not None:
            out.correction = _scaled_map(system.correction, self.inputs(system), self.outputs(system))
        if system.domain is not None:
            s_in = self.inputs(system).tolist()
            out.domain = tuple((lo / s, hi / s) for (lo, hi), s in zip(system.domain, s_in, strict=True))
        if system.known_matrix is not None:
            s = self.state.to(system.known_matrix)
            out.known_matrix = system.known_matrix * s.unsqueeze(0) / s.unsqueeze(-1)
        return out

    # -------------------------------------------------------------------------------------- back to the user's units
    def samples(self, samples, system):
        """Correction samples in these units, back in the user's (inputs, targets, states, noise, and the residuals
        and basis of G's uncertain parameters; times, controls and theta have no units here)."""
        kd = dict(dtype=samples.targets.dtype, device=samples.targets.device)
        s, s_in, s_out = self.state.to(**kd), self.inputs(system).to(**kd), self.outputs(system).to(**kd)
        change = {
            "inputs": samples.inputs * s_in,
            "targets": samples.targets * s_out,
            "states": samples.states * s,
            "noise": None if samples.noise is None else samples.noise * s_out.pow(2),
            "residuals": None if samples.residuals is None else samples.residuals * s,
            "basis": None if samples.basis is None else samples.basis * s.unsqueeze(-1),
        }
        return dataclasses.replace(samples, **change)

    def records(self, source, target, system) -> None:
        """Copy the records of ``source``'s fit (``name_`` attributes) onto ``target``, those with units rewritten in
        the user's: samples, initial states, state-noise variances, the basis targets of theta's posterior. The
        cross-validation's lengthscales are given in the user's units too (its labels with them); its scores and the
        candidates' log marginal likelihoods stay in the data's units (where they were compared)."""
        s_out = self.outputs(system)
        for name, value in vars(source).items():
            if not name.endswith("_") or name.startswith("_") or name == "log_marginal_likelihood_":
                continue
            if value is not None and name == "samples_":
                value = self.samples(value, system)
            elif value is not None and name == "initial_states_":
                value = value * self.state.to(value)
            elif value is not None and name == "state_noise_":
                value = value * self.observed[: value.shape[-1]].to(value).pow(2)
            elif value is not None and name == "cross_validation_":
                value = value.in_units(common_scale(self.inputs(system)))
            elif value is not None and name == "parameters_" and hasattr(value, "basis_targets"):
                targets = value.basis_targets * s_out.to(value.basis_targets).reshape(1, -1, 1)
                value = dataclasses.replace(value, basis_targets=targets)
            setattr(target, name, value)


def data_units(trajectories: Trajectories) -> Units:
    """The data's units (:class:`Units`): per state component (and reading) the power of ten nearest the root mean
    square of its observed values; a component observed only as 0, or never (partly measured data), takes the
    largest one's (1 when there is none)."""
    flat = trajectories.flat_states()
    seen = [bool((torch.isfinite(x) & (x != 0)).any()) for x in flat.T]
    found = [power_of_ten(x) for x in flat.T]
    unseen = max((v for v, ok in zip(found, seen, strict=True) if ok), default=1.0)  # as partial.py sizes them
    state = torch.tensor([v if ok else unseen for v, ok in zip(found, seen, strict=True)], dtype=torch.float64)
    readings = None
    if trajectories.readout is not None:
        given = trajectories.readings
        values = torch.cat(list(given)) if isinstance(given, tuple) else given.reshape(-1, given.shape[-1])
        readings = torch.tensor([power_of_ten(values[:, j]) for j in range(values.shape[1])], dtype=torch.float64)
    return Units(state, readings)


def _scaled_known(system, s: torch.Tensor):
    """G in the data's units, G_z(z) = G(s z) / s, with the signature the system calls it with."""
    G = system.known

    def back(out, like):
        # a wrong type or shape is returned as it is, for the system's check to name: divided by the d scales, an
        # output (..., 1) would broadcast to (..., d) and pass it
        return out / s.to(like) if isinstance(out, torch.Tensor) and out.shape == like.shape else out

    takes_theta = system.theta is not None  # declared parameters, or fixed by system.at(theta): G still takes them
    if system.autonomous and not takes_theta:
        return lambda y: back(G(y * s.to(y)), y)
    if system.autonomous:
        return lambda y, theta: back(G(y * s.to(y), theta), y)
    if not takes_theta:
        return lambda t, y, u: back(G(t, y * s.to(y), u), y)
    return lambda t, y, u, theta: back(G(t, y * s.to(y), u, theta), y)


def _scaled_map(F, s_in: torch.Tensor, s_out: torch.Tensor):
    """x -> F(s_in x) / s_out (the true correction in the data's units)."""

    def scaled(x):
        out = F(x * s_in.to(x))
        fits = isinstance(out, torch.Tensor) and out.shape == x.shape[:-1] + s_out.shape
        return out / s_out.to(out) if fits else out  # another shape: the system's check names it

    return scaled


def _replay(caught) -> None:
    """Issue again the warnings recorded while fitting in the data's units."""
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def fit_in_units(fit, trajectories: Trajectories, system, *, gp, candidates, estimator: dict, **options):
    """``fit`` (:func:`~torchmisspec.fit_correction`) on the data in their own units, the result rewritten in the
    user's (the module docstring); ``None`` when the data are in their units already, when this runs inside such a
    fit, or when a template's fixed values (or ``noise_std``) cannot be rewritten: the caller then fits as it is.
    When the model chosen cannot be rewritten exactly (:func:`~torchmisspec.gp._rescale.rescaled`), the data are
    fitted in the user's units instead."""
    if _INSIDE.get():
        return None
    units = data_units(trajectories)
    if units.trivial:
        return None
    s_in, s_out = units.inputs(system), units.outputs(system)
    templates = [gp] if candidates is None else candidates
    if not isinstance(templates, (list, tuple)) or not all(t is None or isinstance(t, CorrectionGP) for t in templates):
        return None  # the fit's own checks refuse them
    inner = [None if t is None else rescaled_template(t, 1 / s_in, 1 / s_out) for t in templates]
    if any(t is None and u is not None for t, u in zip(inner, templates, strict=True)):
        return None
    extra = dict(estimator)
    noise_std = extra.get("noise_std", 0.0)
    if noise_std:  # noise added to the targets, in the outputs' units
        common = common_scale(s_out)
        if common is None or isinstance(noise_std, bool) or not isinstance(noise_std, (int, float)):
            return None
        extra["noise_std"] = noise_std / common
    given = {"gp": inner[0]} if candidates is None else {"candidates": inner}
    if options.get("noise") is not None:  # residuals whose unit matters (counts) in the data's units
        options = {**options, "noise": options["noise"].in_units(units.state)}
    with _inside():
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = fit(units.trajectories(trajectories), units.system(system), **given, **options, **extra)
        model = rescaled(result, s_in, s_out)
        if model is None:  # no exact form in the user's units: fitted there, as before
            return fit(trajectories, system, gp=gp, candidates=candidates, **options, **estimator)
    units.records(result, model, system)
    _replay(caught)
    return model


def refine_in_units(refine, gp, system, trajectories: Trajectories, *, state_noise, recorded, **options):
    """``refine`` (:func:`~torchmisspec.fit_trajectories`) in the data's own units, the refined model rewritten in
    the user's with ``refinement_["state_noise"] = recorded`` (the user's value); ``None`` when the data are in
    their units already, when this runs inside a fit in the data's units, or when ``gp`` or ``state_noise`` cannot
    be rewritten: the caller then refines as it is."""
    if _INSIDE.get():
        return None
    units = data_units(trajectories)
    if units.trivial:
        return None
    s_in, s_out = units.inputs(system), units.outputs(system)
    inner = rescaled(gp, 1 / s_in, 1 / s_out, flip=False)
    if inner is None:
        return None
    scale = units.observed.to(dtype=gp.dtype, device=gp.device).pow(2)
    noise = None
    if state_noise is not None:
        if isinstance(state_noise, bool):
            return None
        try:
            noise = torch.as_tensor(state_noise, dtype=gp.dtype, device=gp.device).reshape(-1)
        except (TypeError, ValueError, RuntimeError):
            return None
        if noise.numel() not in (1, scale.numel()):
            return None  # the refinement's own check says what is expected
        noise = noise / scale
    with _inside():
        result = refine(inner, units.system(system), units.trajectories(trajectories), state_noise=noise, **options)
    model = rescaled(result, s_in, s_out, flip=False)
    units.records(result, model, system)
    if getattr(result, "refinement_", None) is not None:
        model.refinement_ = {**result.refinement_, "state_noise": recorded}
    return model
