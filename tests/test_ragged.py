"""Ragged data (issue 9, point 6): experiments of different lengths, from construction to the trajectory fit.

Every ragged computation is checked against an independent reference: the same experiments processed one length
group (or one experiment) at a time through the equal-length code paths.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.data import Trajectories, simulate
from torchmisspec.learning.refinement.trajectory_fit import shooting_misfit
from torchmisspec.learning.samples._gp_in_time import _gp_neg_mll
from torchmisspec.learning.samples.observations import correction_samples, estimator_error

DT = torch.float64
LENGTHS = (11, 15, 21, 11, 17)


def grids(lengths=LENGTHS, t_end=6.0):
    g = torch.Generator().manual_seed(3)
    out = []
    for n in lengths:  # non-uniform, strictly increasing, ending anywhere in [0.7, 1] * t_end
        steps = 0.5 + torch.rand(n - 1, generator=g, dtype=DT)
        t = torch.cat([torch.zeros(1, dtype=DT), steps.cumsum(0)])
        out.append(t / t[-1] * t_end * (0.7 + 0.3 * float(torch.rand(1, generator=g))))
    return out


@pytest.fixture(scope="module")
def ragged():
    system = tms.systems.paper_linear()
    y0 = torch.rand(len(LENGTHS), 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    return system, simulate(system, y0, grids())


def test_construction_and_accessors(ragged):
    _, traj = ragged
    assert traj.is_ragged and traj.lengths == LENGTHS and traj.num_samples == sum(LENGTHS)
    assert traj.num_experiments == len(traj) == 5 and traj.state_dim == 2 and traj.dtype == DT
    assert "T=11..21 times" in repr(traj) and "(ragged)" in repr(traj)
    assert torch.equal(traj.initial_conditions, torch.stack([y[0] for y in traj.states]))
    assert torch.equal(traj.flat_states(), torch.cat(traj.states))
    times, states, mask = traj.padded()
    assert times.shape == (5, 21) and states.shape == (5, 21, 2) and mask.sum(-1).tolist() == list(LENGTHS)
    for k, (t, y) in enumerate(traj.experiments()):
        assert torch.equal(states[k][mask[k]], y) and torch.equal(times[k][mask[k]], t)
    groups = traj.by_length()
    assert [idx for idx, _ in groups] == [[0, 3], [1], [4], [2]]
    assert all(not g.is_ragged and g.num_times == LENGTHS[idx[0]] for idx, g in groups)
    sub = traj[[0, 3]]  # equal lengths: stacked into the equal-length form
    assert not sub.is_ragged and sub.states.shape == (2, 11, 2)
    assert traj[1:3].lengths == (15, 21) and traj[2].lengths == (21,)
    with pytest.raises(
        tms.ShapeError,
        match=r"num_times: expected experiments of equal length, got ragged data "
        r"with lengths 11\.\.21; use \.lengths",
    ):
        _ = traj.num_times
    with pytest.raises(tms.ShapeError, match=r"time_grid: .* use \.experiments\(\) or \.padded\(\)"):
        _ = traj.time_grid


def test_lists_of_equal_length_are_stacked():
    t = torch.linspace(0, 1, 4, dtype=DT)
    ys = [torch.randn(4, 2, dtype=DT) for _ in range(3)]
    shared = Trajectories(t, ys)
    assert not shared.is_ragged and shared.times.shape == (4,) and torch.equal(shared.states[1], ys[1])
    per = Trajectories([t, t + 1, t * 2], ys)
    assert not per.is_ragged and per.times.shape == (3, 4)


@pytest.mark.parametrize(
    ("times", "states", "error", "message"),
    [
        ([], [], tms.ShapeError, r"states: expected at least one experiment, got an empty list"),
        ([[0.0, 1.0]], [[1.0, 2.0]], tms.ShapeError, r"states\[0\]: expected a \(T_k, d\) array for experiment 0"),
        (
            [[0.0, 1.0], [0.0, 1.0, 2.0]],
            [[[1.0], [2.0]], [[1.0, 1], [2, 2], [3, 3]]],
            tms.ShapeError,
            r"expected the same state dimension d in every experiment, got \[1, 2\]",
        ),
        (
            [[0.0, 1.0]],
            [[[1.0], [2.0]], [[1.0], [2.0], [3.0]]],
            tms.ShapeError,
            r"times: expected 2 time arrays \(one per experiment in states\), got 1",
        ),
        (
            [[0.0, 1.0], [0.0, 2.0, 1.0]],
            [[[1.0], [2.0]], [[1.0], [2.0], [3.0]]],
            tms.InputError,
            r"times\[1\].*strictly increasing",
        ),
        ([[0.0, 1.0], [0.0, 1.0]], [[[1.0], [2.0]], [[1.0], [2.0], [3.0]]], tms.ShapeError, r"times\[1\]: expected"),
        (
            [0.0, 1.0],
            [[[1.0], [2.0]], [[1.0], [2.0], [3.0]]],
            tms.ShapeError,
            r"expected experiments of equal length for one shared \(T,\) array, got lengths \[2, 3\]",
        ),
        (
            [[0.0, 1.0], [0.0, 1.0, 2.0]],
            [[[1.0], [math.inf]], [[1.0], [2.0], [3.0]]],
            tms.InputError,
            r"states\[0\].*(infinite|finite)",
        ),
        (
            [[0.0, 1.0], [0.0, 1.0]],
            torch.zeros(2, 2, 1),
            tms.InputError,
            r"expected a list of per-experiment state arrays with a list of per-experiment time arrays",
        ),
    ],
)
def test_bad_ragged_input(times, states, error, message):
    with pytest.raises(error, match=message):
        Trajectories(times, states)


@pytest.mark.parametrize("suffix", [".csv", ".tsv", ".txt", ".npz"])
def test_round_trip(ragged, tmp_path, suffix):
    _, traj = ragged
    back = Trajectories.load(traj.save(tmp_path / f"data{suffix}"))
    assert back.is_ragged and back.lengths == traj.lengths
    for (t0, y0), (t1, y1) in zip(traj.experiments(), back.experiments(), strict=True):
        assert torch.equal(t0, t1) and torch.equal(y0, y1)


def test_named_columns_ragged_csv(tmp_path):
    path = tmp_path / "lab.csv"
    path.write_text(
        "run,pressure,t_s,temp\nA,1.0,0.0,5\nB,2.0,0.0,6\nA,1.5,0.5,5.5\nA,1.7,1.0,5.9\nB,2.5,1.0,6.5\n",
        encoding="utf-8",
    )
    traj = Trajectories.load(path, time_column="t_s", experiment_column="run", state_columns=["temp", "pressure"])
    assert traj.is_ragged and traj.lengths == (3, 2)
    assert traj.states[0].tolist() == [[5.0, 1.0], [5.5, 1.5], [5.9, 1.7]] and traj.times[1].tolist() == [0.0, 1.0]


def test_bad_ragged_npz(tmp_path):
    import numpy as np

    path = tmp_path / "bad.npz"
    np.savez(path, times=np.arange(5.0), states=np.ones((5, 2)), lengths=np.array([2, 2]))
    with pytest.raises(tms.ShapeError, match=r"N = sum\(lengths\) = 4, got times \(5,\)"):
        Trajectories.load(path)
    np.savez(path, times=np.arange(5.0), states=np.ones((5, 2)), lengths=np.array([2.5, 2.5]))
    with pytest.raises(tms.InputError, match=r"'lengths' to be a 1-D array of positive integers"):
        Trajectories.load(path)


def test_simulate_ragged_matches_one_experiment_at_a_time(ragged):
    system, traj = ragged
    for (t, y), y0 in zip(traj.experiments(), traj.initial_conditions, strict=True):
        assert torch.allclose(simulate(system, y0, t).states[0], y, rtol=0, atol=1e-9)
    with pytest.raises(tms.ShapeError, match=r"y0: expected \(5, 2\) initial conditions, one per time array"):
        simulate(system, traj.initial_conditions[:2], list(traj.times))


@pytest.mark.parametrize(("derivative", "options"), [("central", {"order": 4}), ("smooth", {"window": 5})])
def test_stencil_estimators_run_per_length_group(ragged, derivative, options):
    system, traj = ragged
    samples = correction_samples(traj, system, derivative=derivative, **options)
    expected = torch.cat(
        [correction_samples(traj[k], system, derivative=derivative, **options).targets for k in range(len(traj))]
    )
    assert torch.allclose(samples.targets, expected, rtol=0, atol=1e-12)
    assert samples.experiment.tolist() == [k for k, n in enumerate(LENGTHS) for _ in range(n)]
    assert torch.equal(samples.states, traj.flat_states())


def test_padded_gp_likelihood_is_the_sum_over_experiments(ragged):
    """The padded samples are decoupled: the ragged likelihood equals the sum of the per-experiment ones."""
    _, traj = ragged
    times, states, mask = traj.padded()
    z = (states - states.mean(1, keepdim=True)).permute(2, 0, 1) * mask  # (d, K, T), zero padding
    log_params = torch.tensor([[0.0, 0.3, -4.0], [-0.5, -0.2, -6.0]], dtype=DT)
    pair = mask.unsqueeze(-1) & mask.unsqueeze(-2)
    ragged_value = _gp_neg_mll(times, z, log_params, pair)
    separate = sum(
        _gp_neg_mll(times[k : k + 1, : LENGTHS[k]], z[:, k : k + 1, : LENGTHS[k]], log_params) for k in range(5)
    )
    assert torch.allclose(ragged_value, separate, rtol=1e-12, atol=0)


def test_gp_derivative_on_ragged_data(ragged):
    system, traj = ragged
    samples = correction_samples(traj, system, derivative="gp")
    assert samples.noise is not None and samples.noise.shape == samples.targets.shape and len(samples) == 75
    truth = system.correction(samples.inputs)  # noise-free data: the samples should be close to F
    # measured: 1.5e-4 relative (shared hyperparameters over the padded batch)
    assert float((samples.targets - truth).pow(2).mean().sqrt()) < 0.01 * float(truth.pow(2).mean().sqrt())


def test_auto_and_self_check_on_ragged_data(ragged):
    system, traj = ragged
    ratio = estimator_error(traj, system, derivative="central", order=4)
    assert 0 <= ratio < 0.05  # measured: 0.002 (4th order, T = 11-21 on [0, 4.2-6])
    samples = correction_samples(traj, system)  # auto
    assert len(samples) == sum(LENGTHS)
    short = Trajectories([t[:2] for t in traj.times], [y[:2] for y in traj.states])  # equal lengths (2)
    with pytest.raises(tms.InputError, match=r"at least 3 samples per trajectory, got T=2"):
        correction_samples(short, system)
    # issue 41 (ChickWeight): an experiment of 2 times among longer ones gives no samples (a warning names it)
    one_short = Trajectories([traj.times[0][:2], traj.times[1]], [traj.states[0][:2], traj.states[1]])
    with pytest.warns(tms.TorchMisspecWarning, match=r"1 experiment\(s\) \(\[0\]\) have fewer than 3 times"):
        assert correction_samples(one_short, system).experiment.unique().tolist() == [1]
    four = Trajectories([traj.times[0][:4], traj.times[1]], [traj.states[0][:4], traj.states[1]])
    with pytest.raises(
        tms.InputError,
        match=r"expected at least 5 samples per trajectory for order=4.*experiment \[0\] of the ragged data",
    ):
        correction_samples(four, system, derivative="central", order=4)


def test_fit_trajectories_on_ragged_data(ragged, one_thread):
    system, traj = ragged
    samples = correction_samples(traj, system, derivative="central", order=2)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-3, noise_variance=1e-6).fit(samples)
    refined = tms.fit_trajectories(gp, system, traj)
    # measured: 1.3e-5 -> 1.1e-6
    assert shooting_misfit(refined, system, traj) < 0.2 * shooting_misfit(gp, system, traj)


def test_plot_ragged_trajectories(ragged):
    import matplotlib

    matplotlib.use("Agg")
    from torchmisspec.plotting import plot_trajectories

    _, traj = ragged
    fig = plot_trajectories(traj)
    lines = [line for line in fig.axes[0].get_lines() if len(line.get_xdata()) == 21]
    assert len(lines) == 5  # one per experiment, padded to the longest
    drawn = sorted(int(torch.isfinite(torch.as_tensor(line.get_xdata())).sum()) for line in lines)
    assert drawn == sorted(LENGTHS)
