"""Each experiment's own parameters as known inputs: the system and the data the rest of the package fits F with.

Once every experiment's varying parameters theta_i are estimated, G(y; theta_i) is a known model with a constant
input per experiment. :func:`subject_system` writes it so: the varying parameters become controls appended to the
system's own (a constant profile each, :func:`with_subject_inputs`), the shared ones are fixed, and F keeps its
inputs (the states and the system's controls, never the appended parameters: F is what the mechanism lacks in every
subject). The whole package then applies unchanged: :func:`~torchmisspec.fit_correction` learns the shared F through
the ODE with each experiment's own G, and predictions and bands run with the subject's parameters as its inputs.

G is called row by row with each row's parameters (``torch.func.vmap`` of the user's ``G(y, theta)``, one call for
the whole batch); a G that vmap cannot trace is called once per distinct theta instead.
"""

from __future__ import annotations

import dataclasses

import torch

from .._errors import InputError
from ..signals import Controls
from ..systems import MisspecifiedSystem
from ..systems._rows import per_row

__all__ = ["subject_system", "with_subject_inputs", "parameter_names", "with_appended_controls", "drawn_controls"]


def parameter_names(system: MisspecifiedSystem, varying: list[int]) -> list[str]:
    """The appended controls' names: the parameters' (``theta_`` before one that a state or control already has)."""
    taken = set(system.state_names or ()) | set(system.control_names)
    names = [system.parameters.names[i] for i in varying]
    return [f"theta_{n}" if n in taken else n for n in names]


def subject_system(system: MisspecifiedSystem, varying: list[int], theta: torch.Tensor) -> MisspecifiedSystem:
    """``system`` with the parameters at positions ``varying`` read from appended controls (one per parameter) and
    the others fixed at ``theta (k,)``: a system without uncertain parameters whose G takes each experiment's own."""
    m, d = system.num_controls, system.state_dim
    theta = theta.detach().to(torch.float64)
    rows = per_row(system.known, system.autonomous)
    vary = torch.tensor(varying)
    names = [system.parameters.names[i] for i in varying]

    def known(t, y, u):
        n = y[..., 0].numel()
        th = theta.to(y).expand(*y.shape[:-1], -1).clone()
        th[..., vary] = u[..., m:].to(y)
        tt = torch.as_tensor(t, dtype=y.dtype, device=y.device).expand(y.shape[:-1]).reshape(n)
        out = rows(tt, y.reshape(n, d), u[..., :m].reshape(n, m), th.reshape(n, th.shape[-1]))
        return out.reshape(y.shape)

    name = f"{system.name} (each experiment's own {', '.join(names)})"
    return with_appended_controls(system, known, parameter_names(system, varying), name)


def with_appended_controls(system: MisspecifiedSystem, known, names: list[str], name: str, parameters=None):
    """A system of ``system``'s states and F, its G ``known(t, y, u[, theta])`` taking ``system``'s controls followed by
    the controls ``names`` (F never sees those), with the uncertain ``parameters`` given (default none)."""
    return MisspecifiedSystem(
        known,
        system.state_dim,
        correction=system.correction,
        correction_inputs=system.correction_inputs,
        correction_outputs=system.correction_outputs,
        domain=system.domain,
        name=name,
        state_names=system.state_names,
        num_controls=system.num_controls + len(names),
        control_names=list(system.control_names) + list(names),
        time_dependent=True,
        parameters=parameters,
    )


def with_subject_inputs(trajectories, thetas: torch.Tensor, names: list[str]):
    """``trajectories`` with every experiment's varying parameters ``thetas (K, k_v)`` appended to its controls as
    constant profiles (named ``names``), the system's own controls kept."""
    K = trajectories.num_experiments
    if thetas.shape[0] != K:
        raise InputError(f"thetas: expected one row per experiment ({K}), got {thetas.shape[0]}")
    starts = torch.stack([t[0] for t, _ in trajectories.experiments()])
    return _replace_controls(trajectories, subject_controls(trajectories.controls, thetas, names, starts))


def subject_controls(controls: Controls | None, thetas: torch.Tensor, names: list[str], starts=None):
    """The controls of ``thetas.shape[0]`` experiments: ``controls``' profiles (repeated to that many rows when it
    holds fewer, in blocks) with ``thetas`` appended as constants; without controls, one knot at each row's first
    time ``starts`` (default 0)."""
    n = thetas.shape[0]
    thetas = thetas.detach().to(torch.float64)
    if controls is None:
        knots = torch.zeros(n, 1, dtype=torch.float64) if starts is None else starts.reshape(n, 1).to(thetas)
        return Controls(knots, thetas[:, None, :], names=names)
    if controls.is_function:
        raise InputError(
            "controls: a population fit needs sampled input profiles (Controls(knots, values)), got one built from a "
            "function; sample it at the experiments' times"
        )
    reps = n // controls.num_experiments
    knots, values = controls.knots.repeat(reps, 1), controls.values.repeat(reps, 1, 1)
    const = thetas[:, None, :].to(values).expand(-1, values.shape[1], -1)
    lengths = controls.lengths.repeat(reps).tolist()
    profiles = torch.cat([values, const], -1)
    return Controls(
        [knots[i, :s] for i, s in enumerate(lengths)],
        [profiles[i, :s] for i, s in enumerate(lengths)],
        kind=controls.kind,
        names=list(controls.names) + list(names),
    )


def drawn_controls(system, layout, eta: torch.Tensor, shared: torch.Tensor, start, controls=None) -> Controls:
    """The controls of subjects drawn as ``eta (S, k_v)`` (``layout``'s varying parameters; the ``shared`` ones
    fixed), each from the time ``start``: ``controls``' profiles (the system's own inputs, or ``None``) with the
    varying parameters appended, as the subject system's G reads them."""
    thetas = layout.theta(eta, shared)[:, layout.vary]
    starts = torch.as_tensor(start, dtype=torch.float64).reshape(-1)[:1].expand(thetas.shape[0])
    return subject_controls(controls, thetas, parameter_names(system, layout.vary), starts)


def _replace_controls(trajectories, controls: Controls):
    if not trajectories.is_ragged:
        return dataclasses.replace(trajectories, controls=controls)
    listed = dict(times=list(trajectories.times), states=list(trajectories.states))
    return dataclasses.replace(trajectories, controls=controls, readings=trajectories._listed_readings(), **listed)


def fitted_system(system, nlme):
    """The system F reads under the population fit ``nlme``: the varying parameters as inputs, the shared ones
    fixed at the fit's values."""
    return subject_system(system, nlme.layout.vary, nlme.thetas[0])
