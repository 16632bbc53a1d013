"""Data as labs have it: missing values, noise relative to the signal, state names, messages that misled."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.refinement.trajectory_fit import _shooting
from torchmisspec.learning.samples._estimators import _estimate_flat
from torchmisspec.learning.samples._gp_in_time import _gp_time
from torchmisspec.learning.samples.observations import finite_difference, gp_derivative, smoothed_derivative

DT = torch.float64


def _poly(t: torch.Tensor) -> torch.Tensor:
    """``(T, 2)``: a quadratic and a line in t."""
    return torch.stack([1.0 + 0.5 * t - 0.3 * t**2, 2.0 - t], dim=-1)


@pytest.fixture(scope="module")
def sir():
    """A SIR model missing a saturating term (the issue's lab system, F on (S, I) -> (dS, dI)), 6 experiments of
    different lengths with 2 % multiplicative noise."""

    def known(y):
        S, I = y[..., 0], y[..., 1]
        inf = 0.5 * S * I
        return torch.stack([-inf, inf - 0.1 * I, 0.1 * I], dim=-1)

    def missing(x):
        S, I = x[..., 0], x[..., 1]
        sat = -2.5 * S * I**2 / (1 + 5 * I)
        return torch.stack([-sat, sat], dim=-1)

    kw = dict(correction_inputs=[0, 1], correction_outputs=[0, 1], name="sir", state_names=["S", "I", "R"])
    truth = tms.MisspecifiedSystem(known, 3, correction=missing, **kw)
    system = tms.MisspecifiedSystem(known, 3, **kw)
    g = torch.Generator().manual_seed(4)
    times, states = [], []
    for k in range(6):
        T = 14 + 2 * k
        t = torch.sort(torch.rand(T, generator=g, dtype=DT) * 40).values
        t[0] = 0.0
        i0 = 0.05 + 0.25 * float(torch.rand(1, generator=g))
        s0 = (1 - i0) * (0.5 + 0.5 * float(torch.rand(1, generator=g)))
        y = tms.simulate(truth, torch.tensor([[s0, i0, 1 - s0 - i0]], dtype=DT), t).states[0]
        times.append(t)
        states.append(y * (1 + 0.02 * torch.randn(y.shape, generator=g, dtype=DT)))
    return system, truth, times, states


def _with_holes(states, fraction: float, seed: int = 0):
    """Copies of the per-experiment states with about ``fraction`` of the entries NaN (never a first state)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for y in states:
        y = y.clone()
        holes = torch.rand(y.shape, generator=g) < fraction
        holes[0] = False
        y[holes] = math.nan
        out.append(y)
    return out


# ------------------------------------------------------------------------------------------------ Trajectories
def test_nan_is_a_missing_entry_kept_with_a_mask_and_inf_is_refused():
    t = torch.linspace(0, 1, 6, dtype=DT)
    y = _poly(t).unsqueeze(0).repeat(2, 1, 1)
    y[0, 2, 0] = math.nan
    y[1, 4, 1] = math.nan
    traj = tms.Trajectories(t, y)
    assert traj.num_missing == 2 and traj.has_missing and traj.observed.sum() == 22
    assert traj.num_samples == 12 and traj.times.shape == (6,)  # a partly observed row stays
    assert "2 missing entries" in repr(traj)
    torch.testing.assert_close(traj.filled().states[0, 2, 0], _poly(t)[2, 0])  # a quadratic: its own fit
    y[0, 3, 1] = math.inf
    with pytest.raises(tms.InputError, match=r"expected finite values or NaN for a missing entry, got 1 infinite"):
        tms.Trajectories(t, y)


def test_a_row_missing_everything_is_the_row_deleted():
    t = torch.linspace(0, 2, 9, dtype=DT)
    y = torch.stack([_poly(t), _poly(t) + 1.0])
    masked = y.clone()
    masked[1, 4] = math.nan  # everything at t_4 in experiment 1
    got = tms.Trajectories(t, masked)
    want = tms.Trajectories([t, torch.cat([t[:4], t[5:]])], [y[0], torch.cat([y[1, :4], y[1, 5:]])])
    assert got.lengths == want.lengths == (9, 8) and not got.has_missing
    for (t1, y1), (t2, y2) in zip(got.experiments(), want.experiments(), strict=True):
        assert torch.equal(t1, t2) and torch.equal(y1, y2)
    masked[0, 4] = math.nan  # the same time in both: equal lengths again, a shared grid
    both = tms.Trajectories(t, masked)
    assert both.times.shape == (8,) and both.states.shape == (2, 8, 2)


def test_a_component_an_experiment_does_not_measure_is_partial_data():
    y = torch.rand(2, 5, 3, dtype=DT)
    y[1, :, 2] = math.nan  # never observed in experiment 1
    y[0, 1:, 1] = math.nan  # observed once (its first value): not measured either
    traj = tms.Trajectories(torch.arange(5.0), y, state_names=["a", "b", "c"])
    assert traj.is_partial and "not measured: b in 1 of 2; c in 1 of 2" in repr(traj)
    assert traj.measured.tolist() == [[True, False, True], [True, True, False]]
    filled = traj.filled()
    assert torch.isnan(filled.states[1, :, 2]).all()  # nothing to fill from: stays missing
    assert torch.equal(filled.states[0, :, 1], y[0, 0, 1].expand(5))  # one value: a constant
    first = traj.initial_conditions
    assert torch.isnan(first[1, 2]) and torch.equal(first[0], y[0, 0])
    y0 = torch.ones(2, 3, dtype=DT)
    given = traj.with_initial_states(y0)
    assert torch.equal(given.initial_conditions, y0) and torch.equal(given[1].initial_conditions, y0[1:])
    assert not tms.Trajectories(torch.arange(5.0), torch.rand(2, 5, 3, dtype=DT)).is_partial
    with pytest.raises(tms.ShapeError, match=r"initial_states: expected finite \(2, 3\) states"):
        traj.with_initial_states(torch.ones(3, 3, dtype=DT))
    y[1] = math.nan
    with pytest.raises(tms.InputError, match="expected at least one observed value in every experiment, got none in "):
        tms.Trajectories(torch.arange(5.0), y)


def test_text_tables_read_and_write_missing_cells(tmp_path):
    path = tmp_path / "lab.csv"
    path.write_text(
        "experiment,day,S,I,R\nrun1,0,0.9,0.1,0\nrun1,1,,0.14,0.01\nrun1,2,0.8,NA,0.03\nrun1,3,0.75,0.2,nan\n"
        "run2,0,0.7,0.3,0\nrun2,1.5,0.6,0.35,N/A\nrun2,2,0.55,0.37,0.08\n"
    )
    traj = tms.Trajectories.load(path, time_column="day")
    assert traj.state_names == ("S", "I", "R") and traj.is_ragged and traj.num_missing == 4
    assert torch.isnan(traj.states[0][1, 0]) and torch.isnan(traj.states[1][1, 2])
    for suffix in (".csv", ".tsv", ".txt", ".npz"):
        copy = traj.save(tmp_path / f"copy{suffix}")
        back = tms.Trajectories.load(copy)
        assert back.state_names == traj.state_names
        for (t1, y1), (t2, y2) in zip(back.experiments(), traj.experiments(), strict=True):
            assert torch.equal(t1, t2) and torch.equal(torch.isnan(y1), torch.isnan(y2))
            assert torch.equal(y1.nan_to_num(-1.0), y2.nan_to_num(-1.0))
    assert ",,0.14," in (tmp_path / "copy.csv").read_text().replace("0,1.0,,", ",,")  # an empty cell was written
    bad = {
        "experiment,day,S\nrun1,,0.9\nrun1,1,0.8\n": r"expected a finite time in column 'day' on line 2, got ''",
        "experiment,day,S\n,0,0.9\nrun1,1,0.8\n": r"expected an experiment label in column 'experiment' on line 2",
        "experiment,day,S\nrun1,0,inf\n": r"got 'inf' \(an empty cell, NaN or NA is a missing value",
    }
    for text, message in bad.items():
        path.write_text(text)
        with pytest.raises(tms.InputError, match=message):
            tms.Trajectories.load(path, time_column="day")


def test_state_names_are_kept_by_slicing_moving_and_saving(tmp_path):
    t = torch.linspace(0, 1, 5, dtype=DT)
    traj = tms.Trajectories(t, torch.rand(3, 5, 2, dtype=DT), state_names=["x", "v"])
    assert traj[1:].state_names == traj[[0]].state_names == traj.to(torch.float32).state_names == ("x", "v")
    assert tms.Trajectories(t, torch.rand(1, 5, 2, dtype=DT)).state_names == ("y0", "y1")
    assert tms.Trajectories.load(traj.save(tmp_path / "a.csv")).state_names == ("x", "v")
    assert tms.Trajectories.load(traj.save(tmp_path / "a.npz")).state_names == ("x", "v")
    with pytest.raises(tms.ShapeError, match=r"state_names: expected 2 non-empty strings"):
        tms.Trajectories(t, torch.rand(1, 5, 2, dtype=DT), state_names=["x"])
    with pytest.raises(tms.InputError, match=r"expected distinct state_names"):
        tms.Trajectories(t, torch.rand(1, 5, 2, dtype=DT), state_names=["x", "x"])
    with pytest.raises(tms.ShapeError, match=r"state_names: expected 3 non-empty strings"):
        tms.MisspecifiedSystem(lambda y: -y, 3, state_names=["a", "b"])


# ------------------------------------------------------------------------------------------------ estimators
@pytest.mark.parametrize(
    "estimate, degree",
    [
        (lambda y, t: finite_difference(y, t, order=2), 2),
        (lambda y, t: finite_difference(y, t, order=4), 4),
        (lambda y, t: smoothed_derivative(y, t, window=7, degree=2), 2),
    ],
)
def test_stencils_use_each_components_own_observed_times(estimate, degree):
    """Exact for polynomials of the stencil's degree at every entry, observed or missing, on an irregular grid."""
    t = torch.sort(torch.rand(15, generator=torch.Generator().manual_seed(1), dtype=DT)).values * 3
    coef = torch.tensor([0.3, -1.0, 0.5, 0.2, -0.1], dtype=DT)[: degree + 1]
    y = torch.stack([sum(c * t**p for p, c in enumerate(coef)), 2 * sum(c * t**p for p, c in enumerate(coef))], -1)
    dy = torch.stack([sum(p * c * t ** (p - 1) for p, c in enumerate(coef) if p), torch.zeros_like(t)], -1)
    dy[:, 1] = 2 * dy[:, 0]
    holes = y.clone().unsqueeze(0)
    holes[0, [0, 3, 4, 9], 0] = math.nan  # the first value, two in a row, one inside
    holes[0, [7, 14], 1] = math.nan  # another pattern in the other component, the last value
    torch.testing.assert_close(estimate(holes, t)[0], dy, rtol=1e-7, atol=1e-7)


def test_masked_stencils_agree_with_the_full_data_path():
    """The per-component path with every entry observed is the full-data estimator (one NaN elsewhere forces it)."""
    t = torch.sort(torch.rand(12, generator=torch.Generator().manual_seed(2), dtype=DT)).values
    y = torch.randn(2, 12, 3, generator=torch.Generator().manual_seed(3), dtype=DT)
    with_hole = torch.cat([y, y[:1]])
    with_hole[2, 5, 1] = math.nan  # a third experiment with a hole: the first two take the masked path
    for f in (lambda s: finite_difference(s, t, order=4), lambda s: smoothed_derivative(s, t, window=5, degree=2)):
        torch.testing.assert_close(f(with_hole)[:2], f(y), rtol=1e-9, atol=1e-9)


def test_the_gp_in_time_conditions_on_observed_entries_only():
    t = torch.linspace(0, 6, 25, dtype=DT)
    clean = torch.stack([torch.sin(t), torch.cos(0.7 * t)], -1).unsqueeze(0).repeat(2, 1, 1)
    holes = clean.clone()
    holes[0, [3, 10, 11], 0] = math.nan
    holes[1, [0, 20], 1] = math.nan
    out = gp_derivative(holes, t)
    truth = torch.stack([torch.cos(t), -0.7 * torch.sin(0.7 * t)], -1)
    assert (out.mean - truth).abs().max() < 5e-3  # at the missing entries too
    # a row missing in every component is the row deleted (hyperparameters and estimates)
    row = clean.clone()
    row[:, 12] = math.nan
    masked = _gp_time(row, t.expand(2, -1), torch.isfinite(row), 50)
    keep = torch.arange(25) != 12
    deleted = gp_derivative(clean[:, keep], t[keep])
    torch.testing.assert_close(masked.mean[:, keep], deleted.mean, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(masked.lengthscale, deleted.lengthscale, rtol=1e-3, atol=0)  # a flat optimum


@pytest.mark.parametrize("name", ["central", "smooth", "gp"])
def test_samples_of_a_masked_row_equal_those_of_the_deleted_row(sir, name):
    system, _, times, states = sir
    holes = [y.clone() for y in states]
    holes[2][5] = math.nan
    holes[4][[3, 9]] = math.nan
    deleted_t = [t for t in times]
    deleted_y = [y for y in states]
    deleted_t[2], deleted_y[2] = torch.cat([times[2][:5], times[2][6:]]), torch.cat([states[2][:5], states[2][6:]])
    keep4 = torch.tensor([i not in (3, 9) for i in range(len(times[4]))])
    deleted_t[4], deleted_y[4] = times[4][keep4], states[4][keep4]
    a = tms.correction_samples(tms.Trajectories(times, holes), system, derivative=name)
    b = tms.correction_samples(tms.Trajectories(deleted_t, deleted_y), system, derivative=name)
    torch.testing.assert_close(a.targets, b.targets, rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(a.inputs, b.inputs)
    assert torch.equal(a.experiment, b.experiment)


def test_samples_skip_missing_outputs_and_fill_what_g_needs(sir):
    system, _, times, states = sir
    holes = [y.clone() for y in states]
    holes[0][4, 0] = math.nan  # an output (S): no sample at that time
    holes[0][6, 2] = math.nan  # R, neither input nor output: filled by the estimator's fit, the sample kept
    traj = tms.Trajectories(times, holes)
    samples = tms.correction_samples(traj, system, derivative="central")
    assert len(samples) == traj.num_samples - 1
    assert bool(torch.isfinite(samples.states).all()) and bool(torch.isfinite(samples.targets).all())
    dydt, _, filled = _estimate_flat("central", traj, {"order": 2})
    row = 6 - 1  # the sample of time 6 (time 4 gave none)
    torch.testing.assert_close(samples.states[row], filled[6])
    t = times[0].tolist()
    nodes = (5, 7, 8)  # R's 3 nearest observed times around time 6: the interpolant through them, at time 6
    weights = [math.prod((t[6] - t[m]) / (t[n] - t[m]) for m in nodes if m != n) for n in nodes]
    interpolant = sum(w * float(states[0][n, 2]) for w, n in zip(weights, nodes, strict=True))
    assert abs(float(samples.states[row, 2]) - interpolant) < 1e-12
    assert torch.equal(samples.states[row, :2], states[0][6, :2])  # observed entries are the observations


def test_auto_chooses_on_data_with_missing_entries(sir):
    system, _, times, states = sir
    traj = tms.Trajectories(times, _with_holes(states, 0.05))
    name, options, errors = tms.learning.samples.observations.choose_derivative(traj, system)
    assert math.isfinite(errors[(name, tuple(sorted(options.items())))])
    assert math.isfinite(tms.learning.samples.observations.estimator_error(traj, system, derivative="central", order=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        samples = tms.correction_samples(traj, system)
    assert bool(torch.isfinite(samples.targets).all())


def test_too_few_observations_of_a_component_are_named():
    t = torch.linspace(0, 1, 8, dtype=DT)
    y = _poly(t).unsqueeze(0).clone()
    y[0, 1:7, 1] = math.nan  # component 1 seen twice only
    with pytest.raises(tms.InputError, match=r"at least 3 observed values .* got 2 of component 1 in experiment 0"):
        finite_difference(y, t)
    with pytest.raises(
        tms.InputError, match=r"derivative='gp': expected at least 4 samples .*experiment 0, component 1"
    ):
        gp_derivative(y, t)


# ------------------------------------------------------------------------------------------------ fits and bands
def test_shooting_residuals_compare_observed_entries_only(sir):
    system, _, times, states = sir
    traj = tms.Trajectories(times, _with_holes(states, 0.1))
    solver = dict(rtol=1e-6, atol=1e-8, max_steps=None, what="test")
    for shooting in ("single", "multiple"):
        residuals, n_obs, _ = _shooting(traj, shooting, solver, system)
        r = residuals(system.known_rhs, None, None)
        first_rows = sum(int(torch.isfinite(y[0]).sum()) for y in traj.states) if shooting == "multiple" else 0
        assert n_obs == int(torch.isfinite(traj.flat_states()).sum()) - first_rows
        assert bool(torch.isfinite(r).all()) and int((r[~residuals.seen] != 0).sum()) == 0


@pytest.mark.slow
def test_the_loop_on_data_with_missing_cells(sir):
    """fit_correction -> CorrectedODE.posterior -> calibrate on ~5 % missing cells (a first state missing too),
    with state_noise='2%'."""
    system, truth, times, states = sir
    holes = _with_holes(states, 0.05, seed=1)
    holes[1][0, 1] = math.nan  # a missing first state: estimated from the component's nearest observations
    traj = tms.Trajectories(times, holes)
    assert 0.03 < traj.num_missing / (3 * traj.num_samples) < 0.08
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system, progress=False)
    assert gp.input_names_ == ("S", "I")
    model = tms.CorrectedODE(system, gp)
    y0 = torch.tensor([[0.7, 0.05, 0.25], [0.9, 0.1, 0.0]], dtype=DT)
    grid = torch.linspace(0, 30, 11, dtype=DT)
    true = tms.simulate(truth, y0, grid).states
    known = tms.simulate(system, y0, grid, known_only=True).states
    assert tms.trajectory_rmse(model.predict(y0, grid), true) < 0.5 * tms.trajectory_rmse(known, true)
    g = torch.Generator().manual_seed(0)
    cal = model.calibrate(
        traj, gp.samples_, state_noise="2%", folds=3, num_samples=16, generator=g, progress=False
    )  # 3 folds: still every experiment held out once
    observed_after_first = sum(int(torch.isfinite(y[1:]).sum()) for y in traj.states)
    assert cal.num_points == observed_after_first and math.isfinite(cal.scale)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        post = model.posterior(y0, grid, num_samples=16, generator=g)
    assert bool(torch.isfinite(post.samples).all())


def test_relative_state_noise_in_calibrate_and_other_strings_refused(sir):
    system, _, times, states = sir
    traj = tms.Trajectories(times, states)
    samples = tms.correction_samples(traj, system, derivative="central")
    model = tms.CorrectedODE(system, tms.CorrectionGP(lengthscale=0.3).fit(samples))
    with pytest.raises(tms.InputError, match=r"state_noise: expected 'auto', a percentage such as '2%'"):
        model.calibrate(traj, samples, state_noise="2 percent")
    with pytest.raises(tms.InputError, match=r"state_noise: expected 'auto', a percentage such as '2%'"):
        model.calibrate(traj, samples, state_noise="-2%")


# ------------------------------------------------------------------------------------------------ names
def test_fit_correction_records_the_input_names_for_terms_and_the_model_file(tmp_path):
    system = tms.systems.paper_linear()
    y0 = torch.rand(6, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    sim = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=DT))
    traj = tms.Trajectories(sim.times, sim.states, state_names=["u", "w"])
    template = tms.CorrectionGP(kernel="features", degree=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system, gp=template, derivative="central", order=4, refine=False, progress=False)
    assert gp.input_names_ == ("u", "w")
    labels = {t.name for t in gp.terms(all_terms=True)}
    assert {"u", "w", "u^2", "u w", "w^2"} <= labels
    assert {t.name for t in gp.terms(["a", "b"], all_terms=True)} >= {"a", "b"}  # given names still win
    back = tms.CorrectionGP.load(gp.save(tmp_path / "m.pt"))
    assert back.input_names_ == ("u", "w")
    blob = torch.load(tmp_path / "m.pt", weights_only=True)
    del blob["input_names"]  # a file written before names were saved
    torch.save(blob, tmp_path / "old.pt")
    old = tms.CorrectionGP.load(tmp_path / "old.pt")
    assert old.input_names_ is None and {"x1", "x2"} <= {t.name for t in old.terms(all_terms=True)}
    # default names in the data: the system's names are used
    named = tms.MisspecifiedSystem(system.known, 2, state_names=["p", "q"], correction_inputs=[1])
    assert named.input_names(sim) == ("q",) and named.input_names(traj) == ("w",)
    assert system.input_names(sim) is None


# ------------------------------------------------------------------------------------------------ messages
def test_a_missing_state_column_in_ragged_data_is_named(sir, tmp_path):
    """It was AttributeError: 'tuple' object has no attribute 'shape' (the message formatted a ragged shape)."""
    system, _, times, states = sir
    traj = tms.Trajectories(times, [y[:, :2] for y in states], state_names=["S", "I"])
    msg = r"expected state dimension 3 of system 'sir', got trajectories.state_dim=2 \(state columns \['S', 'I'\]"
    for call in (
        lambda: tms.correction_samples(traj, system),
        lambda: tms.fit_correction(traj, system),
        lambda: tms.learning.samples.observations.estimator_error(traj, system, derivative="central"),
    ):
        with pytest.raises(tms.ShapeError, match=msg):
            call()
    path = tms.Trajectories(times, states, state_names=["S", "I", "R"]).save(tmp_path / "lab.csv")
    with pytest.raises(
        tms.InputError, match=r"expected state columns \['S', 'I', 'X'\], got columns .*\(missing \['X'\]\)"
    ):
        tms.Trajectories.load(path, state_columns=["S", "I", "X"])


def test_transposed_ragged_states_are_named():
    t = [torch.linspace(0, 1, 10, dtype=DT), torch.linspace(0, 1, 25, dtype=DT)]
    with pytest.raises(tms.ShapeError, match=r"look transposed, \(d, T_k\) instead of \(T_k, d\).*\[y.T for y in"):
        tms.Trajectories(t, [torch.zeros(3, 10, dtype=DT), torch.zeros(3, 25, dtype=DT)])


def test_a_g_that_mixes_the_rows_of_a_batch_is_named():
    """``torch.stack([y[1], -y[0]])`` has the right shape for a batch of d states, and silently swaps them."""
    swapped = tms.MisspecifiedSystem(lambda y: torch.stack([y[1], -y[0]]), 2)
    y0 = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=DT)
    with pytest.raises(tms.ShapeError, match=r"G must broadcast over leading dimensions.*mixes the batch's rows"):
        tms.simulate(swapped, y0, torch.linspace(0, 1, 3, dtype=DT))
    fine = tms.MisspecifiedSystem(lambda y: torch.stack([y[..., 1], -y[..., 0]], -1), 2)
    tms.simulate(fine, y0, torch.linspace(0, 1, 3, dtype=DT))  # checked once, then not again
    assert fine._vectorised["G"]
    assert np.isfinite(fine.known_rhs(y0).numpy()).all()
