"""A model in other units: :func:`rescaled` rewrites a fitted :class:`~torchmisspec.CorrectionGP` exactly for inputs
multiplied by ``s_in`` and outputs by ``s_out`` (per column), :func:`rescaled_template` an unfitted template.

Used by :mod:`torchmisspec.learning._units` (the fits in the data's units). If F_z is the model in one set of units, the
same model in the other is F(x) = s_out F_z(x / s_in): its training inputs, targets and known noise are rescaled, and so
are the hyperparameters that carry units:

* the output scale and the noise variance, by the outputs' squared scales (a feature kernel's output scale stays at 1:
  its weights carry the scale);
* an RBF's or Matern's lengthscale (also the RBF part of features+rbf, and the RBF in a feature space) by the inputs'
  scale when every input has the same one; when they differ, an RBF or Matern 5/2 keeps its lengthscale and takes
  the inputs' scales as its ``input_scale`` (:class:`~torchmisspec.gp.Stationary`: it sees each input in its own
  units, as it did when it was fitted), which features+rbf and the feature-space RBF cannot;
* the weight of a feature kernel's monomial m by ``s_out^2 / m(s_in)^2`` (its coefficient's prior variance), also
  its removed terms' spread. A polynomial kernel ``(1 + <x, x'>)^m`` and a user library of features are not
  rewritten unless the inputs keep their units.

A shared kernel whose outputs get different scales has, in the new units, a different output scale and noise per
output: it becomes a per-output model with the same values in each output's units (``flip``); a kernel that is only
shared (features+rbf), or has a fixed output scale or noise variance, cannot. :func:`rescaled` returns ``None`` when
the model cannot be rewritten exactly; the caller then keeps to the user's units.
"""

from __future__ import annotations

import copy

import torch

from ._exact import IndependentOutputsGP
from ._kernels import RBF, Features, FeaturesRBF, Matern52, Polynomial
from ._large import RBFFeatures

__all__ = ["common_scale", "rescaled", "rescaled_template"]


def _kind(gp) -> str | None:
    """How ``gp``'s kernel (an auto model's: the one it chose) carries units: ``"lengthscale"`` (an isotropic
    lengthscale), ``"features"`` (a weight per monomial), ``"sum"`` (both: features+rbf), ``"none"`` (no input
    units to rewrite: a polynomial kernel or a user library, only for inputs that keep their units), or ``None``
    (a kernel class of the user's: never rewritten)."""
    spec = gp.kernel_spec
    if type(spec) in (RBF, Matern52) or isinstance(spec, RBFFeatures):
        return "lengthscale"
    if type(spec) in (Features, FeaturesRBF):
        if gp.library is not None:
            return "none"
        return "sum" if type(spec) is FeaturesRBF else "features"
    if type(spec) is Polynomial:
        return "none"
    return None


def common_scale(scales: torch.Tensor) -> float | None:
    """The one value of ``scales``, or ``None`` when they differ."""
    return float(scales[0]) if bool((scales == scales[0]).all()) else None


def _respec(gp, s_in: torch.Tensor):
    """The kernel object in the new units when its inputs' scales differ: an RBF or Matern 5/2 with its
    ``input_scale`` times ``s_in`` (its lengthscale then stays: it is in the units the kernel sees); ``None`` when
    the inputs share one scale (the lengthscale is rescaled instead) or the kernel has no such form."""
    spec = gp.kernel_spec
    if common_scale(s_in) is not None or type(spec) not in (RBF, Matern52):
        return None
    before = torch.tensor(spec.input_scale or (1.0,) * s_in.shape[0], dtype=torch.float64)
    return type(spec)(input_scale=before * s_in)


def _fixed(gp, s_in: torch.Tensor, s_out: torch.Tensor) -> dict | None:
    """``gp.fixed`` in the new units, or ``None`` when a fixed value cannot be rewritten (a lengthscale fixed for
    inputs whose scales differ, of a kernel without an ``input_scale``; an output scale or noise variance fixed for
    outputs whose scales differ)."""
    fixed = dict(gp.fixed)
    if fixed["lengthscale"] is not None and _respec(gp, s_in) is None:
        common = common_scale(s_in)
        if common is None:
            return None
        fixed["lengthscale"] = fixed["lengthscale"] * common
    for name in ("outputscale", "noise_variance"):
        if fixed[name] is None or (name == "outputscale" and gp.kernel_spec.terms):
            continue  # a feature kernel's output scale stays at 1: its weights carry the scale
        common = common_scale(s_out)
        if common is None:
            return None
        fixed[name] = fixed[name] * common * common
    return fixed


def _inputs_fit(gp, kind: str | None, s_in: torch.Tensor) -> bool:
    """Whether ``gp``'s kernel (of this kind) can be rewritten for these input scales."""
    if kind in ("lengthscale", "sum"):
        return common_scale(s_in) is not None or _respec(gp, s_in) is not None
    if kind == "features":
        return True
    return bool((s_in == 1).all())


def rescaled_template(template, s_in, s_out):
    """An unfitted ``template`` with its fixed hyperparameters in the new units (:func:`rescaled`'s rules), or
    ``None`` when they cannot be rewritten (the fitted model may still fail to be, then :func:`rescaled` says so)."""
    s_in, s_out = (torch.as_tensor(s, dtype=torch.float64).cpu() for s in (s_in, s_out))
    kind = None if template.auto else _kind(template)
    if not template.auto and (kind is None or kind == "none" and not bool((s_in == 1).all())):
        return None
    fixed = _fixed(template, s_in, s_out)
    if fixed is None:
        return None
    if template.auto:  # an auto model fixes at most its noise variance
        return template.clone(noise_variance=fixed["noise_variance"])
    spec = _respec(template, s_in)
    return template.clone(**fixed) if spec is None else template.clone(kernel=spec, **fixed)


def rescaled(gp, s_in, s_out, *, flip: bool = True):
    """The fitted ``gp`` rewritten for inputs times ``s_in`` ``(d_in,)`` and outputs times ``s_out`` ``(d_out,)``
    (see the module docstring), without the records of its fit (as :meth:`CorrectionGP.condition` leaves them: the
    caller copies those it wants); ``gp`` itself when every scale is 1; ``None`` when it cannot be rewritten
    exactly. ``flip=False`` refuses to turn a shared kernel into a per-output one."""
    s_in, s_out = (torch.as_tensor(s, dtype=torch.float64).cpu() for s in (s_in, s_out))
    if bool((s_in == 1).all() and (s_out == 1).all()):
        return gp
    kind = _kind(gp)
    if kind is None or not _inputs_fit(gp, kind, s_in):
        return None
    d_out = gp.output_dim
    B = gp.covar_module.outputscale.reshape(-1).shape[0]
    split = B == 1 and d_out > 1 and common_scale(s_out) is None  # one shared kernel, outputs in different units
    if split and not (flip and kind in ("lengthscale", "features") and not isinstance(gp.kernel_spec, RBFFeatures)):
        return None
    fixed = _fixed(gp, s_in, s_out)
    if fixed is None:
        return None
    holder = copy.copy(gp)
    holder.fixed = fixed
    spec = _respec(gp, s_in)  # an isotropic kernel on inputs of different scales: each input's scale in the kernel
    if spec is not None:
        holder.kernel_spec = holder.requested_kernel = spec
    covar, lik = copy.deepcopy(gp.covar_module), copy.deepcopy(gp.likelihood)
    X, Y, noise = gp.train_inputs_, gp.train_targets_, gp.train_noise_
    if split or spec is not None:  # new modules (per output, or the kernel's new form) holding the same values
        holder.per_output = holder.per_output or split
        covar, lik = holder._modules(batch=d_out, noise=None if noise is None else noise.T.contiguous())
        _copy_expanded(gp.covar_module, covar)
        _copy_expanded(gp._floor(gp.likelihood), holder._floor(lik))
    kd = dict(dtype=gp.dtype, device=gp.device)
    s_in, s_out = s_in.to(**kd), s_out.to(**kd)
    a = s_out.pow(2) if split or B > 1 else s_out[:1].pow(2)  # (B,): the squared output scale of each kernel
    with torch.no_grad():
        _rescale_modules(gp, covar, holder._floor(lik), kind if spec is None else "outputs", s_in, a)
    holder.model = IndependentOutputsGP(X, Y.T.contiguous(), lik, covar, d_out).eval()
    return holder.condition(X * s_in, Y * s_out, noise=None if noise is None else noise * s_out.pow(2))


def _copy_expanded(source: torch.nn.Module, target: torch.nn.Module) -> None:
    """``target``'s (a per-output batch) parameters and buffers set to ``source``'s (shared), broadcast."""
    state = target.state_dict()
    given = source.state_dict()
    target.load_state_dict({k: given[k].expand_as(v).clone() if k in given else v for k, v in state.items()})


def _rescale_modules(gp, covar, floor, kind: str, s_in: torch.Tensor, a: torch.Tensor) -> None:
    """The hyperparameters in place: ``a`` ``(B,)`` the squared output scales of the B kernels (1 or d_out)."""
    base = covar.base_kernel
    B = a.shape[0]
    floor.noise = floor.noise * a.reshape(floor.noise.shape)
    if kind in ("lengthscale", "sum"):
        base.lengthscale = base.lengthscale * float(s_in[0])
    if kind in ("features", "sum"):
        m = torch.exp((base.powers.to(s_in) * s_in.log()).sum(-1))  # (p,): each monomial's scale
        factor = a.reshape(-1, 1) / m.pow(2) if B > 1 else a / m.pow(2)
        target = base.features_kernel if kind == "sum" else base
        target.weights.mul_(factor.reshape(target.weights.shape))
        target.spread.mul_(factor.reshape(target.spread.shape))
    if kind == "sum":
        base.raw_rbf_scale.add_(a.log().reshape(base.raw_rbf_scale.shape))
    if not gp.kernel_spec.terms:
        covar.outputscale = covar.outputscale * a.reshape(covar.outputscale.shape)
