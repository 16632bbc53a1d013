"""What a :class:`~torchmisspec.design.Campaign` writes as plain values: its input profiles, its model's
hyperparameters (the history), and for a campaign started from :func:`~torchmisspec.fit_correction` the measured
trajectories and the options of the fit it refits with, as tensors and plain values only (:meth:`Campaign.save`
never writes code, and :meth:`Campaign.load` checks what it reads)."""

from __future__ import annotations

import torch

from .._errors import InputError, TorchMisspecError
from ..data import Readout, Trajectories
from ..data._join import readings_of
from ..gp import CorrectionGP, _persistence
from ..noise import NOISE_MODELS, CountNoise
from ..signals import Controls

#: The options of :func:`~torchmisspec.fit_correction` saved as plain values (``gp`` and ``candidates`` as template
#: configurations, ``noise`` by name).
PLAIN = ("select", "derivative", "folds", "refine", "progress")


def hyperparameters(gp: CorrectionGP) -> dict:
    """``gp``'s hyperparameters (and log marginal likelihood once fitted) as plain values, for the history."""
    out = {}
    for name in ("lengthscale", "outputscale", "noise_variance"):
        value = getattr(gp, name)
        if value is None:
            continue
        out[name] = float(value) if not isinstance(value, torch.Tensor) or value.numel() == 1 else value.tolist()
    if gp.is_fitted:
        out["log_marginal_likelihood"] = float(gp.log_marginal_likelihood_)
    return out


def controls_blob(controls: Controls) -> dict:
    """The profiles as plain tensors and strings."""
    lengths = controls.lengths.tolist()
    return {
        "knots": [controls.knots[k, :n].cpu() for k, n in enumerate(lengths)],
        "values": [controls.values[k, :n].cpu() for k, n in enumerate(lengths)],
        "kind": controls.kind,
        "names": list(controls.names),
    }


def controls_from(blob, path, field: str = "controls") -> Controls | None:
    """The profiles :func:`controls_blob` wrote (``None`` for none)."""
    if blob is None:
        return None
    try:
        return Controls(list(blob["knots"]), list(blob["values"]), kind=blob["kind"], names=blob["names"])
    except (KeyError, TypeError, TorchMisspecError) as exc:
        raise InputError(f"{path}: field {field!r} is damaged ({type(exc).__name__}: {exc})") from exc


def data_blob(traj: Trajectories) -> dict:
    """``traj`` as tensors and strings (one entry per experiment)."""
    controls = traj.controls
    return {
        "times": [t.detach().cpu() for t, _ in traj.experiments()],
        "states": [y.detach().cpu() for _, y in traj.experiments()],
        "state_names": list(traj.state_names),
        "controls": None if controls is None else controls_blob(controls),
        "readout": None if traj.readout is None else {
            "matrix": traj.readout.matrix.detach().cpu(), "names": list(traj.readout.names),
        },
        "readings": None if traj.readings is None else [r.detach().cpu() for r in readings_of(traj)],
        "initial_states": None if traj.initial_states is None else traj.initial_states.detach().cpu(),
    }  # fmt: skip


def data_from(blob, path, dtype: torch.dtype, device) -> Trajectories | None:
    """The trajectories :func:`data_blob` wrote (``None`` for a campaign without them); damaged: an InputError."""
    if blob is None:
        return None
    try:
        controls, r = controls_from(blob["controls"], path, "data"), blob["readout"]
        readout = None if r is None else Readout(r["matrix"], r["names"], state_names=blob["state_names"])
        readings = None if blob["readings"] is None else list(blob["readings"])
        traj = Trajectories(
            list(blob["times"]), list(blob["states"]), state_names=blob["state_names"], controls=controls,
            initial_states=blob["initial_states"], readout=readout, readings=readings,
        )  # fmt: skip
    except (KeyError, TypeError, TorchMisspecError) as exc:
        raise InputError(f"{path}: field 'data' is damaged ({type(exc).__name__}: {exc})") from exc
    return traj.to(dtype=dtype, device=device)


def options_blob(options: dict) -> dict:
    """``fit_correction``'s keywords as plain values; an option that is code (a user's noise model, a template
    with a feature library, an estimator's function) cannot be saved: an InputError says which."""
    out = {}
    for key, value in options.items():
        if key == "noise":
            out[key] = _noise_blob(value)
        elif key == "gp":
            out[key] = None if value is None else _persistence.config_of(value)
        elif key == "candidates":
            out[key] = None if value is None else [_persistence.config_of(t) for t in value]
        elif value is None or isinstance(value, (str, int, float, bool)):
            out[key] = value
        else:
            raise InputError(
                f"save: the campaign refits with fit_correction's option {key}={value!r:.60}, which is not a plain "
                "value and cannot be saved (a file never holds code); start the campaign from a fit without it"
            )
    return out


def options_from(blob, path) -> dict | None:
    """The keywords :func:`options_blob` wrote (``None`` for a campaign without them)."""
    if blob is None:
        return None
    if not isinstance(blob, dict):
        raise InputError(f"{path}: field 'fit_options' is damaged (expected a dictionary, got {type(blob).__name__})")
    out = {}
    for key, value in blob.items():
        where = f"{path} (field 'fit_options', {key})"
        if key == "noise":
            out[key] = _noise_from(value, where)
        elif key == "gp":
            out[key] = None if value is None else _persistence.from_config(CorrectionGP, value, where)
        elif key == "candidates":
            out[key] = None if value is None else [_persistence.from_config(CorrectionGP, v, where) for v in value]
        elif value is None or isinstance(value, (str, int, float, bool)):
            out[key] = value
        else:
            raise InputError(f"{where}: expected a plain value, got {type(value).__name__}")
    return out


def pipeline_from(blob, path):
    """The :class:`~torchmisspec.Pipeline` :func:`options_blob` wrote as its keywords (``None`` for a campaign
    without one; a file of an earlier version also holds ``progress``, which is not the pipeline's)."""
    from ..learning.pipeline import Pipeline

    options = options_from(blob, path)
    if options is None:
        return None
    options.pop("progress", None)
    try:
        return Pipeline.from_keywords(**options)
    except InputError as exc:
        raise InputError(f"{path}: field 'fit_options' is damaged ({exc})") from exc


def _noise_blob(noise) -> dict | None:
    if noise is None or isinstance(noise, str):
        return noise
    if NOISE_MODELS.get(noise.name) is not type(noise):
        raise InputError(
            f"save: the campaign refits with the noise model {noise!r}, which is code and cannot be saved; start the "
            f"campaign from a fit with one of {sorted(NOISE_MODELS)}"
        )
    unit = torch.as_tensor(noise.unit, dtype=torch.float64).reshape(-1) if isinstance(noise, CountNoise) else None
    return {"name": noise.name, "unit": unit}


def _noise_from(blob, where: str):
    if blob is None or isinstance(blob, str):
        return blob
    if not isinstance(blob, dict) or blob.get("name") not in NOISE_MODELS:
        raise InputError(f"{where}: expected a noise model's name among {sorted(NOISE_MODELS)}, got {blob!r:.80}")
    model = NOISE_MODELS[blob["name"]]
    if not issubclass(model, CountNoise):
        return model()
    unit = blob.get("unit")
    if not (isinstance(unit, torch.Tensor) and unit.numel() >= 1 and bool((unit > 0).all())):
        raise InputError(f"{where}: expected a positive count unit, got {unit!r:.80}")
    return model(float(unit) if unit.numel() == 1 else unit)


def check_header(blob, path, system, field, FORMAT: str, VERSION: int) -> None:  # noqa: N803 (the file's constants)
    """A campaign file of this format and version, saved for a system of this name and dimension."""
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise InputError(
            f"{path}: expected a torchmisspec Campaign file (format {FORMAT!r}), got "
            + (f"format {blob.get('format')!r}" if isinstance(blob, dict) else type(blob).__name__)
        )
    if blob.get("version") != VERSION:
        raise InputError(f"{path}: expected Campaign file version {VERSION}, got {blob.get('version')!r}")
    saved = field("system", dict)
    if saved.get("name") != system.name or saved.get("state_dim") != system.state_dim:
        raise InputError(
            f"system: expected the system the campaign was run with, '{saved.get('name')}' (state_dim "
            f"{saved.get('state_dim')}), got '{system.name}' (state_dim {system.state_dim})"
        )


def checked_samples(field, path, d_in: int, d_out: int) -> tuple[list, list, list]:
    """The saved correction samples (inputs, targets, known noise per block), checked for shapes and finite values."""
    inputs, targets, noise = field("inputs", list), field("targets", list), field("noise", list)
    if not (len(inputs) == len(targets) == len(noise)):
        raise InputError(
            f"{path}: expected as many input, target and noise blocks, got {len(inputs)}, {len(targets)}, {len(noise)}"
        )
    for x, y, e in zip(inputs, targets, noise, strict=True):
        ok = isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor) and x.dim() == 2 and y.dim() == 2
        ok = ok and x.shape == (y.shape[0], d_in) and y.shape[1] == d_out
        ok = ok and (e is None or (isinstance(e, torch.Tensor) and e.shape == y.shape))
        if not ok or not bool(torch.isfinite(x).all() and torch.isfinite(y).all()):
            raise InputError(f"{path}: the saved samples are damaged (shapes or values)")
    return inputs, targets, noise


def checked_records(field, path, n: int) -> tuple[dict, list]:
    """The saved candidate lists (asked, pending, measured: indices among the n candidates) and the history."""
    lists = {key: field(key, list) for key in ("asked", "pending", "measured")}
    for key, values in lists.items():
        low = -1 if key == "measured" else 0
        if not all(isinstance(i, int) and low <= i < n for i in values):
            raise InputError(f"{path}: field {key!r} expected candidate indices in [0, {n}), it is damaged")
    history = field("history", list)
    if not all(isinstance(h, dict) and h.get("event") in ("ask", "tell") for h in history):
        raise InputError(f"{path}: field 'history' is damaged")
    return lists, history
