"""Tests of the GP-in-time derivative, the estimator self-check and ``derivative="auto"`` (issue 9, points 1, 3, 4)."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec._errors import InputError
from torchmisspec.data import Trajectories, simulate
from torchmisspec.learning.samples.observations import (
    ESTIMATOR_ERROR_THRESHOLD,
    choose_derivative,
    correction_samples,
    estimator_error,
    gp_derivative,
)

DT = torch.float64


def nonuniform_grids(K: int, T: int, t_end: float, seed: int) -> torch.Tensor:
    """``(K, T)`` strictly increasing grids on [0, t_end] with spacings varying by a factor up to 3."""
    g = torch.Generator().manual_seed(seed)
    steps = 0.5 + torch.rand(K, T - 1, generator=g, dtype=DT)
    t = torch.cat([torch.zeros(K, 1, dtype=DT), torch.cumsum(steps, -1)], -1)
    return t / t[:, -1:] * t_end


def closed_form(K: int, T: int, seed: int):
    """Component 0: sin(w t + phi_k); component 1: a_k exp(-t / 2) on non-uniform per-experiment grids."""
    t = nonuniform_grids(K, T, 4.0, seed)
    g = torch.Generator().manual_seed(seed + 1)
    phi = 2 * math.pi * torch.rand(K, 1, generator=g, dtype=DT)
    a = 1 + torch.rand(K, 1, generator=g, dtype=DT)
    y = torch.stack([torch.sin(1.5 * t + phi), a * torch.exp(-t / 2)], -1)
    dy = torch.stack([1.5 * torch.cos(1.5 * t + phi), -0.5 * a * torch.exp(-t / 2)], -1)
    return t, y, dy


def pendulum() -> tms.MisspecifiedSystem:
    """G = [w, -9.81 sin x] (frictionless), true F = -0.3 w on the velocity equation."""
    return tms.MisspecifiedSystem(
        lambda y: torch.stack([y[..., 1], -9.81 * torch.sin(y[..., 0])], -1),
        2,
        correction=lambda w: -0.3 * w,
        correction_inputs=[1],
        correction_outputs=[1],
        name="pendulum",
    )


def pendulum_data(K: int, T: int, noise: float = 0.0, seed: int = 0) -> Trajectories:
    g = torch.Generator().manual_seed(seed)
    y0 = 2 * torch.rand(K, 2, generator=g, dtype=DT) - 1
    traj = simulate(pendulum(), y0, torch.linspace(0.0, 4.0, T, dtype=DT))
    if noise == 0:
        return traj
    rms = traj.states.pow(2).mean(dim=(0, 1)).sqrt()
    eps = torch.randn(traj.states.shape, generator=g, dtype=DT)
    return Trajectories(traj.times, traj.states + noise * rms * eps)


def key(name: str, **options) -> tuple:
    return name, tuple(sorted(options.items()))


# ---------------------------------------------------------------------------------------------------------------
# gp_derivative
def test_gp_derivative_noise_free_closed_form():
    t, y, dy = closed_form(K=8, T=21, seed=0)
    out = gp_derivative(y, t)
    err = (out.mean - dy).abs()
    assert out.mean.shape == out.variance.shape == (8, 21, 2)
    assert float(err.max()) < 2e-2, float(err.max())
    assert float(err.pow(2).mean().sqrt()) < 3e-3
    assert bool((out.variance >= 0).all())
    assert bool((out.noise < 1e-4).all()), out.noise  # no noise in the data: the learned noise is tiny


def test_gp_derivative_coverage_with_noise():
    t, y, dy = closed_form(K=30, T=21, seed=1)
    noise = 0.02
    g = torch.Generator().manual_seed(2)
    out = gp_derivative(y + noise * torch.randn(y.shape, generator=g, dtype=DT), t)
    z = (out.mean - dy).abs() / out.variance.sqrt()
    coverage = float((z < 1.96).double().mean())
    print(f"95% band coverage over {z.numel()} points: {coverage:.3f}; noise std {out.noise.sqrt().tolist()}")
    assert 0.85 <= coverage <= 1.0
    torch.testing.assert_close(out.noise.sqrt(), torch.full((2,), noise, dtype=DT), rtol=0.25, atol=0.0)
    # and the band is informative, not a huge variance that covers anything
    assert float(out.variance.sqrt().median()) < 0.2


def test_gp_derivative_batched_equals_per_experiment_formula():
    # the batched result equals the textbook posterior of every experiment and component, written with a loop
    t, y, _ = closed_form(K=4, T=9, seed=3)
    g = torch.Generator().manual_seed(4)
    y = y + 0.01 * torch.randn(y.shape, generator=g, dtype=DT)
    out = gp_derivative(y, t)
    for k in range(4):
        for j in range(2):
            ell, s2, n = out.lengthscale[j], out.outputscale[j], out.noise[j]
            tk = t[k]
            diff = tk[:, None] - tk[None, :]
            kern = s2 * torch.exp(-0.5 * diff**2 / ell**2)
            dk = -diff / ell**2 * kern  # d/dt* k(t*, t)
            A = kern + n * torch.eye(9, dtype=DT)
            r = y[k, :, j] - y[k, :, j].mean()
            mean = dk @ torch.linalg.solve(A, r)
            var = s2 / ell**2 - torch.einsum("ij,ij->i", dk, torch.linalg.solve(A, dk.T).T)
            torch.testing.assert_close(out.mean[k, :, j], mean, rtol=1e-6, atol=1e-8)
            torch.testing.assert_close(out.variance[k, :, j], var.clamp_min(0), rtol=1e-5, atol=1e-9)


def test_gp_derivative_shared_grid_equals_per_experiment_grid():
    t, y, _ = closed_form(K=3, T=11, seed=5)
    shared = gp_derivative(y, t[0])
    expanded = gp_derivative(y, t[0].expand(3, -1))
    torch.testing.assert_close(shared.mean, expanded.mean)


def test_gp_derivative_float32_and_errors():
    t, y, _ = closed_form(K=2, T=11, seed=6)
    out = gp_derivative(y.float(), t.float())
    assert out.mean.dtype == out.variance.dtype == torch.float32
    with pytest.raises(InputError, match=r"derivative='gp': expected at least 4 samples per trajectory, got T=3"):
        gp_derivative(y[:, :3], t[:, :3])
    const = y.clone()
    const[..., 1] = 2.0
    with pytest.raises(InputError, match=r"component\(s\) \[1\] constant in every experiment"):
        gp_derivative(const, t)
    with pytest.raises(InputError, match=r"max_iter"):
        gp_derivative(y, t, max_iter=0)


# ---------------------------------------------------------------------------------------------------------------
# correction_samples(derivative="gp") carries the variance as the samples' noise
def test_gp_samples_carry_noise():
    system = pendulum()
    traj = pendulum_data(K=5, T=21, noise=0.01)
    s = correction_samples(traj, system, derivative="gp")
    assert s.noise is not None and s.noise.shape == s.targets.shape == (105, 1)
    out = gp_derivative(traj.states, traj.times)
    torch.testing.assert_close(s.noise, out.variance[..., 1].reshape(-1, 1))
    gen = torch.Generator().manual_seed(0)
    s2 = correction_samples(traj, system, derivative="gp", noise_std=0.1, generator=gen)
    torch.testing.assert_close(s2.noise, s.noise + 0.01)
    assert correction_samples(traj, system, derivative="central").noise is None


# ---------------------------------------------------------------------------------------------------------------
# estimator_error, choose_derivative, derivative="auto"
def test_estimator_error_matches_choice_and_validates():
    system = pendulum()
    traj = pendulum_data(K=4, T=21)
    name, options, errors = choose_derivative(traj, system)
    assert errors[key(name, **options)] == min(errors.values())
    assert estimator_error(traj, system, derivative="central", order=4) == pytest.approx(
        errors[key("central", order=4)]
    )
    with pytest.raises(InputError, match=r"derivative='central' accepts \['order'\], got unknown option\(s\) \['wind"):
        estimator_error(traj, system, derivative="central", window=5)
    with pytest.raises(InputError, match=r"derivative: expected one of \['central', 'smooth', 'gp'\], got 'oracle'"):
        estimator_error(traj, system, derivative="oracle")
    with pytest.raises(InputError, match=r"expected at least 11 samples per trajectory for window=11"):
        estimator_error(pendulum_data(K=2, T=7), system, derivative="smooth", window=11, degree=3)


def test_auto_skips_candidates_needing_more_samples():
    system = pendulum()
    _, _, errors = choose_derivative(pendulum_data(K=4, T=6, seed=1), system)
    assert set(errors) == {
        key("central", order=4),
        key("gp"),
        key("central", order=2),
        key("smooth", window=5, degree=2),
    }


def test_auto_prefers_high_order_or_gp_on_noise_free_data():
    system = pendulum()
    name, options, errors = choose_derivative(pendulum_data(K=8, T=21), system)
    assert (name, options) in (("central", {"order": 4}), ("gp", {}))
    smooth = [v for (n, _), v in errors.items() if n == "smooth"]
    assert errors[key(name, **options)] < 0.5 * min(smooth)


def test_auto_prefers_smoothing_on_noisy_data():
    system = pendulum()
    traj = pendulum_data(K=5, T=81, noise=0.01, seed=2)
    name, options, errors = choose_derivative(traj, system)
    assert key(name, **options) != key("central", order=2)
    assert name in ("smooth", "gp")
    assert errors[key(name, **options)] < 0.6 * errors[key("central", order=2)]
    # and the self-check ranks by the truth: the chosen samples are closer to the true F than central order 2's
    exact = system.select_outputs(system.true_rhs(traj.states) - system.known_rhs(traj.states)).reshape(-1, 1)
    chosen = correction_samples(traj, system, derivative=name, **options)
    central = correction_samples(traj, system, derivative="central", order=2)
    assert float((chosen.targets - exact).pow(2).mean()) < float((central.targets - exact).pow(2).mean())


def test_warning_fires_on_sparse_pendulum_and_not_on_dense():
    system = pendulum()
    with pytest.warns(tms.TorchMisspecWarning, match=r"more densely.*another estimator.*fit_trajectories"):
        sparse = correction_samples(pendulum_data(K=10, T=11), system)
    assert sparse.targets.shape == (110, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)
        dense = correction_samples(pendulum_data(K=6, T=81), system)
    assert dense.targets.shape == (486, 1)
    assert ESTIMATOR_ERROR_THRESHOLD == 0.5


def test_auto_is_the_default_and_explicit_estimators_do_not_self_check():
    system = pendulum()
    traj = pendulum_data(K=3, T=11)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)
        correction_samples(traj, system, derivative="central")  # explicit: no self-check, no warning
    with pytest.warns(tms.TorchMisspecWarning):
        correction_samples(traj, system)


def test_auto_on_per_experiment_grids():
    system = pendulum()
    y0 = pendulum_data(K=4, T=2).initial_conditions
    traj = simulate(system, y0, nonuniform_grids(4, 21, 4.0, seed=7))
    name, options, errors = choose_derivative(traj, system)
    assert errors[key(name, **options)] < ESTIMATOR_ERROR_THRESHOLD
    samples = correction_samples(traj, system)
    assert samples.targets.shape == (84, 1)
    assert (samples.noise is not None) == (name == "gp")


def test_fit_correction_gives_the_estimators_advice_only_where_held_out_data_do_not_contradict_it():
    """Issue 42: the self-check's warning fired on every fit, also where the cross-validation found the correction
    significantly better than the known model. Sparse pendulum data with its missing term: significant, no advice;
    the same times from the known model alone (nothing to correct): the advice is given, with the do-no-harm one.
    On the command line the advice names the command's flags."""
    from torchmisspec.cli import _one_line
    from torchmisspec.learning.samples.observations import ESTIMATOR_ADVICE

    data = pendulum_data(K=10, T=11)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = tms.fit_correction(data, pendulum(), progress=False)
    assert gp.cross_validation_.significant
    assert not [w for w in caught if str(w.message).startswith(ESTIMATOR_ADVICE)]
    known = simulate(pendulum(), data.initial_conditions, data.time_grid, known_only=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = tms.fit_correction(known, pendulum(), progress=False)
    advice = [str(w.message) for w in caught if str(w.message).startswith(ESTIMATOR_ADVICE)]
    assert gp.known_model_ and len(advice) == 1
    line = _one_line(advice[0])
    assert "--derivative names one" in line and "--refine" in line and "tms." not in line


def test_a_refinement_the_estimators_advice_asked_for_that_fails_keeps_the_correction(monkeypatch):
    """Sparse times: the self-check's advice is taken (the kept correction refined through the ODE). Where that
    refinement cannot be fitted, the correction learned from the derivative samples is kept, with a warning and the
    advice; a refinement the user asked for (refine=True) still raises."""
    import torchmisspec.learning.fit as fit_module
    from torchmisspec.learning.samples.observations import ESTIMATOR_ADVICE

    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        raise tms.IntegrationError("the refinement's solve stopped")

    monkeypatch.setattr(fit_module, "fit_trajectories", failing)
    data = pendulum_data(K=10, T=11)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = tms.fit_correction(data, pendulum(), progress=False)
    said = [str(w.message) for w in caught]
    assert calls and gp.is_fitted and not getattr(gp, "known_model_", False)
    assert any("refining the correction through the ODE (the derivative estimator's advice) failed" in m for m in said)
    assert any(m.startswith(ESTIMATOR_ADVICE) for m in said)
    with pytest.raises(tms.IntegrationError):
        tms.fit_correction(data, pendulum(), progress=False, refine=True)
