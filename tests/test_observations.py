"""Tests of torchmisspec.learning.samples.observations: derivative estimators and correction samples F~ = dy/dt -
G(y)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchmisspec._errors import InputError, ShapeError
from torchmisspec.data import Trajectories, simulate
from torchmisspec.learning.samples.observations import (
    CorrectionSamples,
    correction_samples,
    finite_difference,
    smoothed_derivative,
)
from torchmisspec.systems import LinearField, MisspecifiedSystem, paper_gravity, paper_linear

DT = torch.float64


def curve(t: torch.Tensor) -> torch.Tensor:
    """y(t) = [sin t, exp(-t/2) cos 3t], shape (T, 2)."""
    return torch.stack([torch.sin(t), torch.exp(-t / 2) * torch.cos(3 * t)], dim=-1)


def curve_dot(t: torch.Tensor) -> torch.Tensor:
    e = torch.exp(-t / 2)
    return torch.stack([torch.cos(t), e * (-0.5 * torch.cos(3 * t) - 3 * torch.sin(3 * t))], dim=-1)


def random_grid(n: int, seed: int, t_end: float = 3.0) -> torch.Tensor:
    """Strictly increasing grid on [0, t_end] with n + 1 points and spacings varying by a factor up to 3."""
    g = torch.Generator().manual_seed(seed)
    steps = 0.5 + torch.rand(n, generator=g, dtype=DT)
    t = torch.cat([torch.zeros(1, dtype=DT), torch.cumsum(steps, 0)])
    return t / t[-1] * t_end


def refine(t: torch.Tensor) -> torch.Tensor:
    """Halve every spacing by inserting the midpoints (the old nodes stay at even positions)."""
    mid = (t[1:] + t[:-1]) / 2
    return torch.cat([torch.stack([t[:-1], mid], dim=-1).reshape(-1), t[-1:]])


def observed_orders(estimate, grid0: torch.Tensor, levels: int) -> dict[str, list[float]]:
    """log2 of successive error ratios under grid halving, at the interior original nodes, both ends, all nodes."""
    errs = {"interior": [], "first": [], "last": [], "all": []}
    t = grid0
    for level in range(levels):
        err = (estimate(curve(t).unsqueeze(0), t)[0] - curve_dot(t)).abs().amax(dim=-1)  # (T,)
        orig = err[:: 2**level]  # the original nodes
        errs["interior"].append(orig[1:-1].max().item())
        errs["first"].append(err[0].item())
        errs["last"].append(err[-1].item())
        errs["all"].append(err.max().item())
        t = refine(t)
    return {k: [math.log2(a / b) for a, b in itertools.pairwise(v)] for k, v in errs.items()}


def make_traj(t: torch.Tensor, y: torch.Tensor) -> Trajectories:
    return Trajectories(t, y.unsqueeze(0))


# ---------------------------------------------------------------------------------------------------------------
# finite_difference
@pytest.mark.parametrize("order", [2, 4])
@pytest.mark.parametrize("grid", ["uniform", "nonuniform"])
def test_finite_difference_convergence_order(order, grid):
    grid0 = torch.linspace(0.0, 3.0, 21, dtype=DT) if grid == "uniform" else random_grid(20, seed=order)
    rates = observed_orders(lambda y, t: finite_difference(y, t, order=order), grid0, levels=6)
    print(f"finite_difference order={order} {grid}: " + ", ".join(f"{k}={v[-1]:.3f}" for k, v in rates.items()))
    for where, r in rates.items():
        # the last two halvings are in the asymptotic regime
        assert all(abs(p - order) < 0.25 for p in r[-2:]), (where, r)


@pytest.mark.parametrize("order, degree", [(2, 2), (4, 4)])
def test_finite_difference_exact_on_polynomials(order, degree):
    t = random_grid(12, seed=3)
    coef = torch.tensor([0.3, -1.2, 0.7, 0.25, -0.1], dtype=DT)[: degree + 1]
    powers = torch.arange(degree + 1, dtype=DT)
    y = (t.unsqueeze(-1) ** powers) @ coef
    dy = (t.unsqueeze(-1) ** (powers[1:] - 1) * powers[1:]) @ coef[1:]
    got = finite_difference(y.reshape(1, -1, 1), t, order=order)[0, :, 0]
    torch.testing.assert_close(got, dy, atol=1e-10, rtol=0)


def test_finite_difference_per_experiment_grids_match_single_calls():
    grids = torch.stack([random_grid(30, seed=s) for s in range(3)])  # (3, 31)
    states = torch.stack([curve(g) for g in grids])  # (3, 31, 2)
    batched = finite_difference(states, grids, order=4)
    single = torch.cat([finite_difference(states[k : k + 1], grids[k], order=4) for k in range(3)])
    torch.testing.assert_close(batched, single, atol=1e-12, rtol=0)
    shared = finite_difference(states, grids[0], order=2)
    assert shared.shape == (3, 31, 2)
    batched = smoothed_derivative(states, grids, window=9, degree=3)
    single = torch.cat([smoothed_derivative(states[k : k + 1], grids[k], window=9, degree=3) for k in range(3)])
    torch.testing.assert_close(batched, single, atol=1e-12, rtol=0)


def test_finite_difference_follows_dtype():
    t = torch.linspace(0, 1, 11, dtype=torch.float32)
    out = finite_difference(curve(t).unsqueeze(0), t.double())
    assert out.dtype == torch.float32
    assert finite_difference(curve(t.double()).unsqueeze(0), t).dtype == torch.float64


def test_finite_difference_bad_inputs():
    t = torch.linspace(0, 1, 2, dtype=DT)
    with pytest.raises(InputError, match=r"expected at least 3 samples per trajectory for order=2, got T=2"):
        finite_difference(torch.zeros(1, 2, 1, dtype=DT), t)
    t4 = torch.linspace(0, 1, 4, dtype=DT)
    with pytest.raises(InputError, match=r"expected at least 5 samples per trajectory for order=4, got T=4"):
        finite_difference(torch.zeros(2, 4, 3, dtype=DT), t4, order=4)
    with pytest.raises(InputError, match=r"order: expected one of \[2, 4\], got 3"):
        finite_difference(torch.zeros(1, 5, 1, dtype=DT), torch.arange(5.0), order=3)
    with pytest.raises(ShapeError, match=r"states: expected shape \(K, T, d\), got \(5, 1\)"):
        finite_difference(torch.zeros(5, 1, dtype=DT), torch.arange(5.0))
    with pytest.raises(ShapeError, match=r"times: expected shape \(5,\) or \(1, 5\)"):
        finite_difference(torch.zeros(1, 5, 1, dtype=DT), torch.arange(6.0))
    states = torch.zeros(1, 5, 1, dtype=DT)
    states[0, 2, 0] = float("inf")  # NaN is a missing entry (tests/test_missing.py); inf is refused
    with pytest.raises(InputError, match=r"states: expected finite values or NaN for a missing entry"):
        finite_difference(states, torch.arange(5.0))
    with pytest.raises(InputError, match=r"times: expected strictly increasing"):
        finite_difference(torch.zeros(1, 5, 1, dtype=DT), torch.tensor([0.0, 1.0, 1.0, 2.0, 3.0]))


# ---------------------------------------------------------------------------------------------------------------
# smoothed_derivative
@pytest.mark.parametrize("window, degree", [(5, 1), (7, 2), (9, 3), (11, 4)])
def test_smoother_exact_on_polynomials(window, degree):
    t = random_grid(25, seed=degree) * 2 - 1.5
    coef = torch.tensor([0.3, -1.2, 0.7, 0.25, -0.1], dtype=DT)[: degree + 1]
    powers = torch.arange(degree + 1, dtype=DT)
    y = (t.unsqueeze(-1) ** powers) @ coef
    dy = (t.unsqueeze(-1) ** (powers[1:] - 1) * powers[1:]) @ coef[1:]
    got = smoothed_derivative(torch.stack([y, 2 * y], -1).unsqueeze(0), t, window=window, degree=degree)[0]
    torch.testing.assert_close(got, torch.stack([dy, 2 * dy], -1), atol=1e-10, rtol=0)


def test_smoother_reduces_noise_error():
    g = torch.Generator().manual_seed(1)
    t = random_grid(300, seed=7, t_end=6.0)
    clean = curve(t)
    noisy = clean + 1e-3 * torch.randn(clean.shape, generator=g, dtype=DT)
    truth = curve_dot(t)
    rmse_central = (finite_difference(noisy.unsqueeze(0), t)[0] - truth).pow(2).mean().sqrt()
    rmse_smooth = (smoothed_derivative(noisy.unsqueeze(0), t, window=11, degree=2)[0] - truth).pow(2).mean().sqrt()
    print(f"noisy derivative RMSE: central {rmse_central:.3e}, smooth {rmse_smooth:.3e}")
    assert rmse_smooth < 0.5 * rmse_central


def test_smoother_converges_on_clean_data():
    # degree-2 local fit: the derivative error is O(h^2) like the central difference
    rates = observed_orders(lambda y, t: smoothed_derivative(y, t, window=7, degree=2), random_grid(40, 5), 5)
    print("smoothed_derivative window=7 degree=2: " + ", ".join(f"{k}={v[-1]:.3f}" for k, v in rates.items()))
    assert all(abs(r[-1] - 2) < 0.3 for r in rates.values()), rates


def test_smoother_bad_inputs():
    states = torch.zeros(1, 9, 2, dtype=DT)
    t = torch.arange(9.0)
    with pytest.raises(InputError, match=r"window: expected an odd integer >= 3, got 6"):
        smoothed_derivative(states, t, window=6)
    with pytest.raises(InputError, match=r"window > degree\), got window=3 and degree=3"):
        smoothed_derivative(states, t, window=3, degree=3)
    with pytest.raises(InputError, match=r"degree: expected an integer >= 1"):
        smoothed_derivative(states, t, degree=0)
    with pytest.raises(InputError, match=r"expected at least 11 samples per trajectory for window=11, got T=9"):
        smoothed_derivative(states, t, window=11)
    with pytest.raises(InputError, match=r"window: expected an integer >= 1, got 7.0 \(float\)"):
        smoothed_derivative(states, t, window=7.0)


# ---------------------------------------------------------------------------------------------------------------
# correction_samples
@pytest.fixture(scope="module")
def linear_fine():
    system = paper_linear()
    y0 = torch.tensor([[0.8, -0.5], [-0.6, 0.9], [0.3, 0.4]], dtype=DT)
    return system, simulate(system, y0, torch.linspace(0.0, 6.0, 601, dtype=DT))


@pytest.fixture(scope="module")
def gravity_traj():
    system = paper_gravity()
    # roughly circular orbits around the known central mass 0.2 at the origin
    y0 = torch.tensor([[1.0, 0.0, 0.0, 0.45], [0.0, -1.5, 0.35, 0.0]], dtype=DT)
    return system, simulate(system, y0, torch.linspace(0.0, 5.0, 201, dtype=DT))


def test_oracle_samples_are_exact_without_noise(linear_fine):
    system, traj = linear_fine
    s = correction_samples(traj, system, derivative="oracle")
    assert isinstance(s, CorrectionSamples)
    K, T, d = traj.states.shape
    assert s.inputs.shape == (K * T, 2) and s.targets.shape == (K * T, 2) and s.states.shape == (K * T, d)
    assert s.experiment.dtype == torch.long and s.experiment.tolist() == [k for k in range(K) for _ in range(T)]
    assert len(s) == K * T
    torch.testing.assert_close(s.states, traj.states.reshape(-1, d), atol=0, rtol=0)
    torch.testing.assert_close(s.targets, system.true_correction(s.inputs), atol=1e-15, rtol=0)


def test_oracle_noise_std_and_reproducibility():
    system = paper_linear()
    g = torch.Generator().manual_seed(0)
    states = torch.rand(20, 2000, 2, generator=g, dtype=DT) * 2 - 1  # need not be a solution for the oracle
    traj = Trajectories(torch.arange(2000, dtype=DT), states)

    def draw(seed: int):
        gen = torch.Generator().manual_seed(seed)
        return correction_samples(traj, system, derivative="oracle", noise_std=0.05, generator=gen)

    a, b, c = draw(3), draw(3), draw(4)
    torch.testing.assert_close(a.targets, b.targets, atol=0, rtol=0)
    assert not torch.equal(a.targets, c.targets)
    resid = a.targets - system.true_correction(a.inputs)
    print(f"oracle noise: empirical std {resid.std().item():.5f} (target 0.05), mean {resid.mean().item():.2e}")
    assert abs(resid.std().item() / 0.05 - 1) < 0.02
    assert abs(resid.mean().item()) < 0.05 * 4 / math.sqrt(resid.numel())


def test_gravity_inputs_are_positions_targets_are_velocity_components(gravity_traj):
    system, traj = gravity_traj
    s = correction_samples(traj, system, derivative="oracle")
    N = traj.num_experiments * traj.num_times
    assert s.inputs.shape == (N, 2) and s.targets.shape == (N, 2) and s.states.shape == (N, 4)
    torch.testing.assert_close(s.inputs, traj.states.reshape(-1, 4)[:, :2], atol=0, rtol=0)
    torch.testing.assert_close(s.targets, system.true_correction(s.inputs), atol=1e-14, rtol=0)
    # the central estimate also recovers F (the position equations carry no correction)
    c = correction_samples(traj, system, derivative="central", order=4)
    err = (c.targets - system.true_correction(c.inputs)).abs().max().item()
    print(f"gravity central order 4 max |F~ - F| = {err:.2e}")
    assert err < 1e-6


@pytest.mark.parametrize(
    "derivative, kwargs, tol",
    [
        ("central", {"order": 2}, 1e-6),
        ("central", {"order": 4}, 1e-8),
        ("smooth", {"window": 7, "degree": 2}, 2e-6),
    ],
)
def test_estimated_samples_approximate_true_correction(linear_fine, derivative, kwargs, tol):
    system, traj = linear_fine
    s = correction_samples(traj, system, derivative=derivative, **kwargs)
    f_true = system.true_correction(s.inputs)
    err = (s.targets - f_true).abs().max().item()
    print(f"paper_linear {derivative} {kwargs}: max |F~ - F| = {err:.2e} (max |F| = {f_true.abs().max().item():.2e})")
    assert err < tol


def test_noise_added_to_estimated_samples(linear_fine):
    system, traj = linear_fine
    clean = correction_samples(traj, system, derivative="central")
    gen = torch.Generator().manual_seed(0)
    noisy = correction_samples(traj, system, derivative="central", noise_std=0.1, generator=gen)
    resid = noisy.targets - clean.targets
    assert abs(resid.std().item() / 0.1 - 1) < 0.1


@pytest.mark.parametrize("derivative", ["oracle", "central", "smooth"])
def test_samples_follow_float32(linear_fine, derivative):
    system, traj = linear_fine
    s = correction_samples(traj.to(torch.float32), system, derivative=derivative)
    assert s.inputs.dtype == s.targets.dtype == s.states.dtype == torch.float32
    ref = correction_samples(traj, system, derivative=derivative)
    # float32 round-off only: a difference quotient of states rounded to eps |y| loses ~eps |y| / dt
    eps, dt = torch.finfo(torch.float32).eps, float(traj.times.diff().min())
    bound = 20 * eps * float(traj.states.abs().max()) / (dt if derivative != "oracle" else 1.0)
    err = float((s.targets.double() - ref.targets).abs().max())
    assert err < bound, (err, bound)


def test_correction_samples_bad_inputs(linear_fine):
    system, traj = linear_fine
    with pytest.raises(InputError, match=r"trajectories: expected a torchmisspec Trajectories object, got Tensor"):
        correction_samples(traj.states, system)
    with pytest.raises(InputError, match=r"system: expected a MisspecifiedSystem, got str"):
        correction_samples(traj, "paper_linear")
    with pytest.raises(ShapeError, match=r"expected state dimension 4 of system 'paper_gravity', got .*state_dim=2"):
        correction_samples(traj, paper_gravity())
    short = Trajectories(torch.tensor([0.0, 1.0]), torch.zeros(1, 2, 2))
    with pytest.raises(InputError, match=r"expected at least 3 samples per trajectory for order=2, got T=2"):
        correction_samples(short, system, derivative="central")
    with pytest.raises(InputError, match=r"derivative='auto': expected at least 3 samples.*got T=2"):
        correction_samples(short, system)
    with pytest.raises(InputError, match=r"expected at least 7 samples per trajectory for window=7, got T=2"):
        correction_samples(short, system, derivative="smooth")
    no_f = MisspecifiedSystem(LinearField(torch.eye(2)), 2, name="known_only")
    msg = r"oracle derivatives need a system with a true correction.*'auto', 'central', 'smooth' or 'gp'"
    with pytest.raises(InputError, match=msg):
        correction_samples(traj, no_f, derivative="oracle")
    correction_samples(traj, no_f, derivative="central")  # real-data estimators work without a true F
    msg = r"derivative: expected one of \['auto', 'oracle', 'central', 'smooth', 'gp'\], got 'spline'"
    with pytest.raises(InputError, match=msg):
        correction_samples(traj, system, derivative="spline")
    for bad in (-0.1, float("nan"), float("inf"), "x", True):
        with pytest.raises(InputError, match=r"noise_std: expected a finite number >= 0"):
            correction_samples(traj, system, derivative="central", noise_std=bad)
    with pytest.raises(InputError, match=r"generator: expected a torch.Generator or None, got int"):
        correction_samples(traj, system, derivative="central", noise_std=0.1, generator=0)


def test_infinite_states_surface():
    states = torch.zeros(1, 5, 2, dtype=DT)
    states[0, 3, 1] = float("inf")  # NaN is a missing entry (tests/test_missing.py)
    msg = (
        r"states: expected finite values or NaN for a missing entry, got 1 infinite entry \(first at index \(0, 3, 1\)"
    )
    with pytest.raises(InputError, match=msg):
        Trajectories(torch.arange(5.0), states)


def test_non_finite_targets_raise():
    # a state exactly on a point mass of the true correction gives an infinite F
    system = paper_gravity()
    states = torch.zeros(1, 3, 4, dtype=DT)
    states[0, :, 0], states[0, :, 1] = 0.0, 4.0
    with pytest.raises(InputError, match=r"correction samples dy/dt - G\(y\) of system 'paper_gravity'"):
        correction_samples(Trajectories(torch.arange(3.0), states), system, derivative="oracle")


def test_with_shared_noise_takes_each_samples_noisiest_output():
    samples = CorrectionSamples(
        torch.zeros(3, 1, dtype=torch.float64),
        torch.zeros(3, 2, dtype=torch.float64),
        torch.zeros(3, 1, dtype=torch.float64),
        torch.zeros(3, dtype=torch.long),
        torch.tensor([[1.0, 2.0], [3.0, 0.5], [4.0, 4.0]], dtype=torch.float64),
    )
    shared = samples.with_shared_noise()
    assert shared.noise.tolist() == [[2.0, 2.0], [3.0, 3.0], [4.0, 4.0]]
    assert shared.with_shared_noise() is shared  # already shared: unchanged
    assert shared.targets is samples.targets
