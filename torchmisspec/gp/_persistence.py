"""Saving and loading a fitted :class:`~torchmisspec.gp.CorrectionGP` without pickled code.

A file holds one dictionary of plain values: the configuration (strings, numbers, booleans, ``None``), the GPyTorch
state dictionaries (tensors) and the training data (tensors: inputs, targets and the known per-sample noise, or
``None`` when the model was fitted without). It is written with ``torch.save`` and read with
``torch.load(weights_only=True)``, which refuses anything but tensors and plain containers, so a crafted file
cannot run code on load. The dtype is read from an allow-list, never by ``getattr`` on a string from the file.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from .._errors import InputError
from .._validation import check_path, check_real, check_writable, unreadable, writing
from ..noise import NOISE_MODELS, CountNoise
from ..parameters import ParameterPosterior
from ._calibration import BandCalibration
from ._exact import IndependentOutputsGP
from ._kernels import as_kernel
from ._selection import EVIDENCE_MARGIN

__all__ = ["save", "load", "to_blob", "from_blob", "config_of", "from_config", "read_safely", "FORMAT_VERSION"]

FORMAT_VERSION = 3  # 3: + "train_noise" (files of version 2 have none and load as before)
_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def save(gp, path: str | Path) -> Path:
    """Write ``gp`` (fitted) to ``path``; the folder must exist."""
    path = check_writable(path)
    blob = to_blob(gp)
    with writing(path):
        torch.save(blob, path)
    return path


def config_of(gp) -> dict:
    """The configuration of ``gp`` (fitted or not) as plain values: enough for :func:`from_config` to rebuild it."""
    if getattr(gp, "library", None) is not None:
        raise InputError(
            "save: this model's feature library is Python code, and a model file never holds code (it could run on "
            "load); save the samples and refit with the same library instead"
        )
    dtype = str(gp.dtype).removeprefix("torch.")
    if dtype not in _DTYPES:
        raise InputError(
            f"dtype: expected a model in one of {sorted(_DTYPES)} to save, got {dtype}; convert it with .to()"
        )
    return {
        "kernel": gp.kernel,
        "kernel_config": gp.kernel_spec.config(),  # the kernel object's arguments (plain values)
        "per_output": gp.per_output,
        "degree": gp.degree,
        "max_iter": gp.max_iter,
        "min_gain": getattr(gp, "min_gain", None),
        "fixed": dict(gp.fixed),
        "dtype": dtype,
        "auto": bool(getattr(gp, "auto", False)),  # kernel="auto": a refit chooses again
        "evidence_margin": getattr(gp, "evidence_margin", None),
        "auto_per_output": bool(getattr(gp, "_auto_per_output", gp.per_output)),
        "exact": getattr(gp, "exact", None),  # additive: how an RBF is computed (gp._large)
        "requested_kernel": [gp.requested_kernel.name, gp.requested_kernel.config()],  # additive: the one asked for
    }


def from_config(cls, cfg, path, *, device=None):
    """The unfitted CorrectionGP of a configuration written by :func:`config_of` (checked; errors name ``path``)."""
    if not isinstance(cfg, dict):
        raise InputError(f"{path}: expected a configuration dictionary, got {type(cfg).__name__}")
    dtype_name = cfg.get("dtype")
    if dtype_name not in _DTYPES:
        raise InputError(f"{path}: expected dtype one of {sorted(_DTYPES)}, got {dtype_name!r}")
    fixed = cfg.get("fixed", {})
    if not isinstance(fixed, dict) or set(fixed) - {"lengthscale", "outputscale", "noise_variance"}:
        raise InputError(f"{path}: expected 'fixed' to map hyperparameter names to values, got {fixed!r}")
    try:
        kernel = as_kernel(cfg.get("kernel"), cfg.get("kernel_config") or {})
        gp = cls(
            kernel=kernel,
            per_output=bool(cfg.get("per_output")),
            degree=cfg.get("degree", 2),
            max_iter=cfg.get("max_iter", 200),
            min_gain=cfg.get("min_gain") if kernel.terms else None,
            dtype=_DTYPES[dtype_name],
            device=device,
            exact=cfg.get("exact"),
            **fixed,
        )
        asked = cfg.get("requested_kernel")
        if asked is not None:
            if not (isinstance(asked, list) and len(asked) == 2 and isinstance(asked[1], dict)):
                raise InputError(f"expected 'requested_kernel' as [name, config], got {asked!r:.80}")
            gp.requested_kernel = as_kernel(asked[0], asked[1])
    except (TypeError, InputError) as exc:
        raise InputError(f"{path}: the configuration is not valid ({exc})") from exc
    gp.auto = bool(cfg.get("auto", False))
    if gp.auto:
        try:
            # the features candidate's price (the kernel chosen may be another)
            gp.min_gain = None if cfg.get("min_gain") is None else check_real(cfg["min_gain"], "min_gain", minimum=0.0)
            margin = cfg.get("evidence_margin")  # None in files written before the margin existed
            gp.evidence_margin = (
                EVIDENCE_MARGIN if margin is None else check_real(margin, "evidence_margin", minimum=0.0)
            )
        except InputError as exc:
            raise InputError(f"{path}: the configuration is not valid ({exc})") from exc
    gp._auto_per_output = bool(cfg.get("auto_per_output", gp.per_output))
    return gp


def to_blob(gp) -> dict:
    """The fitted ``gp`` as a dictionary of plain values and tensors (what :func:`save` writes)."""
    gp._require_fitted()
    blob = {
        "format": FORMAT_VERSION,
        "config": config_of(gp),
        "covar_module": {k: v.detach().cpu() for k, v in gp.covar_module.state_dict().items()},
        "likelihood": {k: v.detach().cpu() for k, v in gp.likelihood.state_dict().items()},
        "train_inputs": gp.train_inputs_.detach().cpu(),
        "train_targets": gp.train_targets_.detach().cpu(),
        "train_noise": None if gp.train_noise_ is None else gp.train_noise_.detach().cpu().contiguous(),
        "n_iterations": gp.n_iterations_,
        "n_evaluations": gp.n_evaluations_,
    }
    if getattr(gp, "input_names_", None) is not None:  # additive: files without it load with no names
        blob["input_names"] = list(gp.input_names_)
    if getattr(gp, "system_", None) is not None:  # additive: which system it corrects, as the command line records
        blob["system"] = dict(gp.system_)
    if getattr(gp, "refinement_", None) is not None:  # additive: how it was refined through the ODE
        blob["refinement"] = dict(gp.refinement_)
    if getattr(gp, "parameters_", None) is not None:  # additive: the posterior of G's uncertain parameters
        blob["parameters"] = gp.parameters_.to_dict()
    calibration = getattr(gp, "calibration_", None)
    if calibration is not None:  # the bands' calibrated spread travels with the model (absent in older files)
        blob["calibration"] = calibration.to_dict()
    record = _fit_record(gp)
    if record is not None:  # additive: how the data were measured and what the fit chose (fit_correction's records)
        blob["fit_record"] = record
    return blob


def _fit_record(gp) -> dict | None:
    """The records of :func:`~torchmisspec.fit_correction` a saved model needs for its bands of new measurements
    and its messages: the noise model (its name, and a count's unit), the residual scale per component, whether the
    known model alone was kept and the factor its bands were widened by; ``None`` when it was not fitted by it (a
    user-defined noise model is not saved: its code would have to be)."""
    noise = getattr(gp, "noise_", None)
    if noise is None or NOISE_MODELS.get(noise.name) is not type(noise):
        return None
    unit = None
    if isinstance(noise, CountNoise):
        unit = torch.as_tensor(noise.unit, dtype=torch.float64).detach().cpu().reshape(-1)
    scale = getattr(gp, "noise_scale_", None)
    return {
        "noise": noise.name,
        "noise_unit": unit,
        "noise_scale": None if scale is None else scale.detach().cpu().to(torch.float64),
        "known_model": bool(getattr(gp, "known_model_", False)),
        "dispersion": float(getattr(gp, "dispersion_", 1.0)),
    }


def _restore_fit_record(gp, record, path) -> None:
    """Set ``noise_``, ``noise_scale_``, ``known_model_`` and ``dispersion_`` from a file's ``fit_record``
    (checked; the error names the file)."""

    def bad(what: str):
        return InputError(f"{path}: expected 'fit_record' with {what}, got {record!r:.120}")

    if not isinstance(record, dict) or record.get("noise") not in NOISE_MODELS:
        raise bad(f"'noise' one of {sorted(NOISE_MODELS)}")
    unit, scale = record.get("noise_unit"), record.get("noise_scale")
    model = NOISE_MODELS[record["noise"]]
    if issubclass(model, CountNoise):
        if not (isinstance(unit, torch.Tensor) and unit.numel() >= 1 and bool((unit > 0).all())):
            raise bad(f"a positive 'noise_unit' for {record['noise']}")
        gp.noise_ = model(float(unit) if unit.numel() == 1 else unit.to(torch.float64))
    else:
        gp.noise_ = model()
    if scale is not None and not (
        isinstance(scale, torch.Tensor) and scale.dim() == 1 and bool((torch.isnan(scale) | (scale >= 0)).all())
    ):
        raise bad("'noise_scale' a (d,) tensor of standard deviations >= 0 (NaN: never measured) or None")
    gp.noise_scale_ = None if scale is None else scale.to(device=gp.device, dtype=gp.dtype)
    known, dispersion = record.get("known_model"), record.get("dispersion")
    if not isinstance(known, bool) or isinstance(dispersion, bool) or not isinstance(dispersion, (int, float)):
        raise bad("'known_model' a boolean and 'dispersion' a number")
    gp.known_model_ = known
    gp.dispersion_ = check_real(float(dispersion), "dispersion", minimum=1.0)


def _field(blob: dict, key: str, kind, path: Path, what: str = "CorrectionGP"):
    """``blob[key]``, checked to exist and be a ``kind`` (the error names the file, the field and what it holds)."""
    if not isinstance(blob, dict) or key not in blob:
        raise InputError(
            f"{path}: expected a torchmisspec {what} file with field {key!r}, got "
            + (f"fields {sorted(blob)[:8]}" if isinstance(blob, dict) else type(blob).__name__)
        )
    value = blob[key]
    if not isinstance(value, kind):
        raise InputError(f"{path}: field {key!r} expected {kind}, got {type(value).__name__}")
    return value


def read_safely(path: str | Path, what: str, writer: str):
    """``torch.load(weights_only=True)`` of ``path`` (tensors and plain containers only), with a clear error."""
    path = Path(check_path(path))
    if not path.is_file():
        raise InputError(f"path: expected an existing {what} file, got {str(path)!r}")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: expected a {what} file written by {writer}, got an empty file (0 bytes)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (
        pickle.UnpicklingError,
        EOFError,
        zipfile.BadZipFile,
        RuntimeError,
        ValueError,
        OSError,
        IndexError,  # a text file (a CSV passed as the model): the legacy reader pops an empty stack
        KeyError,
        TypeError,
        AttributeError,
    ) as exc:
        raise InputError(
            f"{path}: expected a {what} file written by {writer} (tensors and plain values only), "
            f"got a file that could not be read safely ({unreadable(exc)})"
        ) from exc


def load(cls, path: str | Path, *, device=None):
    """Read a file written by :func:`save`; the posterior cache is rebuilt (one factorization)."""
    path = Path(check_path(path))
    blob = read_safely(path, "CorrectionGP", "CorrectionGP.save")
    return from_blob(cls, blob, path, device=device)


def from_blob(cls, blob, path, *, device=None):
    """The CorrectionGP of a dictionary written by :func:`to_blob`; ``path`` names the source in errors."""
    if not isinstance(blob, dict):
        raise InputError(f"{path}: expected a dictionary, got {type(blob).__name__}")
    gp = from_config(cls, _field(blob, "config", dict, path), path, device=device)
    X = _field(blob, "train_inputs", torch.Tensor, path).to(gp.device, gp.dtype)
    Y = _field(blob, "train_targets", torch.Tensor, path).to(gp.device, gp.dtype)
    if X.dim() != 2 or Y.dim() != 2 or X.shape[0] != Y.shape[0]:
        raise InputError(
            f"{path}: expected training data (N, d_in) and (N, d_out), got {tuple(X.shape)}, {tuple(Y.shape)}"
        )
    noise = blob.get("train_noise")
    if noise is not None:
        if not isinstance(noise, torch.Tensor) or noise.shape != Y.shape:
            shape = tuple(noise.shape) if isinstance(noise, torch.Tensor) else type(noise).__name__
            raise InputError(
                f"{path}: expected known noise 'train_noise' of shape {tuple(Y.shape)} or None, got {shape}"
            )
        noise = noise.to(gp.device, gp.dtype)
        if not bool(torch.isfinite(noise).all()) or bool((noise < 0).any()):
            raise InputError(
                f"{path}: expected finite non-negative known noise variances in 'train_noise', got values from "
                f"{float(noise.min()):g} to {float(noise.max()):g}"
            )
        noise = noise.T.contiguous()

    gp._d_in = X.shape[1]  # the feature kernel's library depends on the number of inputs
    covar, lik = gp._modules(batch=Y.shape[1], noise=noise)
    try:
        state = dict(_field(blob, "covar_module", dict, path))
        for key, value in covar.state_dict().items():  # files from before the feature kernel's chosen subset was
            if key.endswith((".inclusion", ".spread")):  # recorded: every kept term present for sure, as before
                state.setdefault(key, value)
        covar.load_state_dict(state)
        lik.load_state_dict(_field(blob, "likelihood", dict, path))
    except RuntimeError as exc:
        raise InputError(f"{path}: the saved hyperparameters do not match the kernel {gp.kernel!r} ({exc})") from exc
    gp.model = IndependentOutputsGP(X, Y.T.contiguous(), lik, covar, Y.shape[1]).eval()
    gp._freeze()
    gp.n_iterations_ = int(blob.get("n_iterations", 0))
    gp.n_evaluations_ = int(blob.get("n_evaluations", blob.get("n_iter", 0)))
    names = blob.get("input_names")
    if names is not None and (
        not isinstance(names, list) or len(names) != X.shape[1] or not all(isinstance(n, str) for n in names)
    ):
        what = f"{X.shape[1]} strings (one per input)"
        raise InputError(f"{path}: expected 'input_names' to be {what}, got {names!r:.80}")
    gp.input_names_ = None if names is None else tuple(names)
    system = blob.get("system")
    if system is not None and not (isinstance(system, dict) and all(isinstance(k, str) for k in system)):
        raise InputError(
            f"{path}: expected 'system' to be a dictionary of the corrected system's description, got "
            f"{type(system).__name__}"
        )
    gp.system_ = system
    gp.refinement_ = _refinement(blob.get("refinement"), path)
    gp.posterior()
    if blob.get("parameters") is not None:
        record = blob["parameters"]
        gp.parameters_ = ParameterPosterior.from_dict(
            record, path, num_samples=X.shape[0], output_dim=Y.shape[1], like=X
        )
    if blob.get("calibration") is not None:
        gp.calibration_ = BandCalibration.from_dict(blob["calibration"], path)
    if blob.get("fit_record") is not None:
        _restore_fit_record(gp, blob["fit_record"], path)
    return gp


#: The settings a saved refinement may hold, and the types each may take.
_REFINEMENT = {
    "shooting": (str,),
    "state_noise": (type(None), float, int, list),
    "max_iter": (int,),
    "rtol": (float, int),
    "atol": (float, int),
    "max_steps": (type(None), int),
    "relevance": (bool,),
}


def _refinement(value, path: Path) -> dict | None:
    """The saved settings of a refinement through the ODE, checked (``None`` when the model was not refined)."""
    if value is None:
        return None
    ok = isinstance(value, dict) and set(value) <= set(_REFINEMENT)
    ok = ok and all(isinstance(v, _REFINEMENT[k]) for k, v in value.items())
    if not ok:
        raise InputError(
            f"{path}: expected 'refinement' to be the settings of fit_trajectories ({', '.join(_REFINEMENT)}), got "
            f"{value!r:.80}"
        )
    return dict(value)
