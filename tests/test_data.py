import warnings

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.systems import MisspecifiedSystem


def _expm_reference(A, y0, grid):
    """States (K, T, d) of dy/dt = A y from y0 (K, d) on per-row grids (K, T) by the matrix exponential."""
    return torch.stack(
        [
            torch.stack([torch.linalg.matrix_exp(A * (t - row[0])) @ y for t in row])
            for y, row in zip(y0, grid, strict=True)
        ]
    )


def test_simulate_known_linear_matches_matrix_exp(linear_system, paper_times, generator):
    y0 = torch.rand(6, 2, generator=generator, dtype=torch.float64) * 2 - 1
    traj = tms.simulate(linear_system, y0, paper_times, known_only=True)
    ref = _expm_reference(linear_system.known_matrix, y0, paper_times.expand(6, -1))
    assert traj.states.shape == (6, 11, 2)
    torch.testing.assert_close(traj.states, ref, rtol=0, atol=1e-9)


def test_simulate_linear_system_without_correction_uses_known_model(generator):
    A = torch.tensor([[-0.3, 1.0], [-1.0, -0.2]], dtype=torch.float64)
    system = MisspecifiedSystem(tms.systems.LinearField(A), 2)  # no true correction: G alone
    y0 = torch.randn(3, 2, generator=generator, dtype=torch.float64)
    times = torch.tensor([0.0, 0.1, 0.5, 0.55, 2.0, 4.5], dtype=torch.float64)  # irregular spacing
    ref = _expm_reference(A, y0, times.expand(3, -1))
    torch.testing.assert_close(tms.simulate(system, y0, times).states, ref, rtol=0, atol=1e-9)


def test_simulate_per_experiment_time_grids(linear_system, generator):
    y0 = torch.rand(3, 2, generator=generator, dtype=torch.float64)
    grid = torch.tensor([[0.0, 1.0, 2.0, 6.0], [1.0, 1.5, 4.0, 4.1], [-2.0, 0.0, 0.3, 3.0]], dtype=torch.float64)
    traj = tms.simulate(linear_system, y0, grid, known_only=True)
    torch.testing.assert_close(traj.states, _expm_reference(linear_system.known_matrix, y0, grid), rtol=0, atol=1e-9)
    # with the true correction, each row equals a separate solve on its own grid
    full = tms.simulate(linear_system, y0, grid)
    for k in range(3):
        single = tms.simulate(linear_system, y0[k : k + 1], grid[k])
        torch.testing.assert_close(full.states[k], single.states[0], rtol=0, atol=1e-9)


def test_effect_of_the_correction_matches_first_order_perturbation(linear_system, paper_times, generator):
    """true - known = int_0^t expm(A (t - s)) F(y(s)) ds; to first order in F, y(s) is the known trajectory
    (Duhamel). F is ~1 % of G here, so the first-order formula must match the simulated gap to a few percent."""
    y0 = torch.rand(5, 2, generator=generator, dtype=torch.float64) * 2 - 1
    true = tms.simulate(linear_system, y0, paper_times).states
    known = tms.simulate(linear_system, y0, paper_times, known_only=True).states
    A = linear_system.known_matrix
    s = torch.linspace(0.0, float(paper_times[-1]), 1201, dtype=torch.float64)
    ys = torch.einsum("sij,kj->ksi", torch.linalg.matrix_exp(A * s.reshape(-1, 1, 1)), y0)  # known path, fine grid
    F = linear_system.true_correction(ys)  # (K, S, 2)
    expected = []
    for t in paper_times:
        m = s <= t + 1e-12
        kernel = torch.linalg.matrix_exp(A * (t - s[m]).reshape(-1, 1, 1))  # (S', 2, 2)
        integrand = torch.einsum("sij,ksj->ksi", kernel, F[:, m])
        expected.append(torch.trapezoid(integrand, s[m], dim=1) if m.sum() > 1 else torch.zeros_like(y0))
    expected = torch.stack(expected, 1)  # (K, T, 2)
    gap = true - known
    assert float(gap.abs().max()) > 1e-3  # F has a visible effect over [0, 6] ...
    rel = float((gap - expected).norm() / expected.norm())
    assert rel < 0.1, rel  # ... of the size first-order perturbation theory predicts


@pytest.mark.parametrize("suffix", [".npz", ".csv"])
@pytest.mark.parametrize("per_experiment", [False, True])
def test_trajectories_save_load_roundtrip(tmp_path, suffix, per_experiment, generator):
    states = torch.randn(4, 5, 3, generator=generator, dtype=torch.float64)
    times = torch.cumsum(torch.rand(4 if per_experiment else 1, 5, generator=generator, dtype=torch.float64) + 0.1, -1)
    times = times if per_experiment else times[0]
    traj = tms.Trajectories(times, states)
    loaded = tms.Trajectories.load(traj.save(tmp_path / f"traj{suffix}"))
    torch.testing.assert_close(loaded.states, traj.states, rtol=0, atol=0)
    torch.testing.assert_close(loaded.times, traj.times, rtol=0, atol=0)


def test_trajectories_indexing_and_properties(generator):
    traj = tms.Trajectories(torch.arange(4.0), torch.randn(3, 4, 2, generator=generator))
    assert (traj.num_experiments, traj.num_times, traj.state_dim, len(traj)) == (3, 4, 2, 3)
    assert traj[1].states.shape == (1, 4, 2)
    assert traj[np.int64(2)].states.shape == (1, 4, 2)
    assert traj[[0, 2]].time_grid.shape == (2, 4)
    torch.testing.assert_close(traj.initial_conditions, traj.states[:, 0])


# ------------------------------------------------------------------------------------------------------ bad input
def test_trajectories_reject_infinite_states():
    states = torch.zeros(2, 3, 2)
    states[1, 2, 0] = float("inf")  # NaN is a missing entry (tests/test_missing.py)
    with pytest.raises(tms.InputError, match=r"states: expected finite values or NaN for a missing entry, got 1 inf"):
        tms.Trajectories(torch.arange(3.0), states)


def test_trajectories_reject_inf_times():
    with pytest.raises(tms.InputError, match="times: expected finite"):
        tms.Trajectories(torch.tensor([0.0, float("inf"), 2.0]), torch.zeros(1, 3, 2))


def test_trajectories_reject_non_increasing_times():
    with pytest.raises(tms.InputError, match=r"times: expected strictly increasing values, got 1.0 followed by 1.0"):
        tms.Trajectories(torch.tensor([0.0, 1.0, 1.0]), torch.zeros(1, 3, 2))


def test_trajectories_reject_shape_mismatch():
    with pytest.raises(tms.ShapeError, match=r"times: expected shape \(3,\) or \(2, 3\).*got \(4,\)"):
        tms.Trajectories(torch.arange(4.0), torch.zeros(2, 3, 2))
    with pytest.raises(tms.ShapeError, match=r"states: expected shape \(K, T, d\), got \(3, 2\)"):
        tms.Trajectories(torch.arange(3.0), torch.zeros(3, 2))


def test_load_rejects_bad_files(tmp_path):
    bad = tmp_path / "x.dat"
    bad.write_text("1,2")
    with pytest.raises(tms.InputError, match=r"expected a .npz, .csv, .tsv or .txt file name"):
        tms.Trajectories.load(bad)
    empty = tmp_path / "e.csv"
    empty.write_text("experiment,time,y0\n")
    with pytest.raises(tms.InputError, match="at least one data row"):
        tms.Trajectories.load(empty)
    wrong = tmp_path / "w.csv"
    wrong.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(
        tms.InputError, match=r"expected a time column 'time', got columns \[.*\]; name the one .*--time-column"
    ):
        tms.Trajectories.load(wrong)


# ------------------------------------------------------------------------------------- text tables, named columns
@pytest.mark.parametrize("suffix", [".csv", ".tsv", ".txt"])
def test_named_columns_round_trip_with_per_experiment_grids(tmp_path, suffix, generator):
    states = torch.randn(3, 6, 2, generator=generator, dtype=torch.float64)
    times = torch.cumsum(torch.rand(3, 6, generator=generator, dtype=torch.float64) + 0.1, -1)
    traj = tms.Trajectories(times, states)
    path = traj.save(
        tmp_path / f"obs{suffix}", time_column="t [s]" if suffix != ".txt" else "t", state_columns=["x", "v"]
    )
    header = path.read_text(encoding="utf-8").splitlines()[0]
    assert header.split({".csv": ",", ".tsv": "\t", ".txt": None}[suffix]) == [
        "experiment",
        "t [s]" if suffix != ".txt" else "t",
        "x",
        "v",
    ]
    loaded = tms.Trajectories.load(path, time_column="t [s]" if suffix != ".txt" else "t")
    assert torch.equal(loaded.states, traj.states) and torch.equal(loaded.times, traj.times)  # exactly
    # state columns by name pick and order the components
    swapped = tms.Trajectories.load(path, time_column="t [s]" if suffix != ".txt" else "t", state_columns=["v", "x"])
    assert torch.equal(swapped.states, traj.states.flip(-1))


def test_csv_any_column_order_row_order_and_no_experiment_column(tmp_path):
    path = tmp_path / "lab.csv"
    # columns in any order, rows shuffled, text experiment labels kept in order of first appearance
    path.write_text(
        "speed,run,position,clock,comment\n0.2,b,1.2,1.0,9\n0.1,a,1.1,1.0,9\n0.0,a,1.0,0.0,9\n0.3,b,1.3,0.0,9\n",
        encoding="utf-8",
    )
    traj = tms.Trajectories.load(
        path, time_column="clock", experiment_column="run", state_columns=["position", "speed"]
    )
    assert traj.times.tolist() == [0.0, 1.0]  # one shared grid
    assert traj.states.tolist() == [[[1.3, 0.3], [1.2, 0.2]], [[1.0, 0.0], [1.1, 0.1]]]
    single = tmp_path / "one.tsv"
    single.write_text("time\tx\n2\t20\n0\t0\n1\t10\n", encoding="utf-8")
    traj = tms.Trajectories.load(single)  # no experiment column: one experiment, rows sorted by time
    assert traj.states.shape == (1, 3, 1) and traj.states[0, :, 0].tolist() == [0.0, 10.0, 20.0]
    numeric = tmp_path / "n.txt"
    numeric.write_text("experiment time y\n10 0 1\n2 0 2\n10.0 1 3\n2 1 4\n", encoding="utf-8")
    # numeric labels are sorted as numbers, and 10 and 10.0 are the same experiment
    assert tms.Trajectories.load(numeric).states[:, :, 0].tolist() == [[2.0, 4.0], [1.0, 3.0]]
    excel = tmp_path / "excel.csv"
    excel.write_bytes("\ufeffexperiment,time,x\n1,0,5\n2,0,6\n".encode())  # a byte-order mark, as Excel writes
    assert tms.Trajectories.load(excel).states.shape == (2, 1, 1)


def test_repr_is_short():
    traj = tms.Trajectories(torch.linspace(0, 6, 11, dtype=torch.float64), torch.zeros(40, 11, 2, dtype=torch.float64))
    assert repr(traj) == "Trajectories(K=40 experiments, T=11 times on [0, 6] (shared grid), d=2, float64)"
    grids = torch.tensor([[0.0, 1.0], [0.5, 2.5]])
    assert repr(tms.Trajectories(grids, torch.zeros(2, 2, 1))) == (
        "Trajectories(K=2 experiments, T=2 times on [0, 2.5] (per-experiment grids), d=1, float32)"
    )


@pytest.mark.parametrize(
    ("text", "kwargs", "error", "message"),
    [
        ("time,x\n0,1\n", {"state_columns": ["x", "y"]}, tms.InputError,
         r"expected state columns \['x', 'y'\], got columns \['time', 'x'\] \(missing \['y'\]\)"),
        ("time,x\n0,1\n", {"experiment_column": "run"}, tms.InputError,
         r"expected an experiment column 'run', got columns \['time', 'x'\]"),
        ("time,x\n0,1\n", {"time_column": "t"}, tms.InputError, r"expected a time column 't'"),
        ("time,x,x\n0,1,2\n", {}, tms.InputError, r"expected distinct column names in the header, got \['x'\]"),
        ("time,x\n0,1\n1,abc\n", {}, tms.InputError, r"expected a number in column 'x' on line 3, got 'abc'"),
        ("time,x\n0,1\n1,inf\n", {}, tms.InputError, r"expected a finite number in column 'x' on line 3, got 'inf'"),
        ("time,x\n,1\n1,2\n", {}, tms.InputError, r"expected a finite time in column 'time' on line 2, got ''"),
        ("time,x\n0,\n1,nan\n", {}, tms.InputError,
         r"expected at least one observed value in every experiment, got none in experiment 0"),
        ("time,x\n0,1\n1\n", {}, tms.ShapeError,
         r"expected 2 columns in every row \(as in the header\), got 1 in data row 2 \(line 3"),
        ("experiment,time,x\n0,0,1\n0,0,2\n", {}, tms.InputError,
         r"expected one row per experiment and time, got time 0.0 more than once for experiment '0'"),
        # a label column not named 'experiment': the message names the option that reads it
        ("flask,time,x\nA,0,1\nB,0,2\n", {"state_columns": ["x"]}, tms.InputError,
         r"got time 0.0 more than once \(no column 'experiment' labels the experiments: name yours with "
         r"experiment_column='flask', --experiment-column flask on the command line\)"),
        ("flask,time,x\nA,0,1\nB,0,2\n", {}, tms.InputError,
         r"got 'A' \(a missing value is an empty cell, NaN or NA\); if 'flask' labels the experiments, name it "
         r"with experiment_column='flask'"),
        ("time\n0\n", {}, tms.InputError, r"expected at least one state column besides \['time'\]"),
        ("time,x\n0,1\n", {"state_columns": ["time"]}, tms.InputError, r"got the time / experiment column"),
        ("time,x\n0,1\n", {"state_columns": "x"}, tms.InputError, r"expected a list of column names"),
        ("", {}, tms.InputError, r"expected a header row naming the columns, got an empty file"),
    ],
)  # fmt: skip
def test_text_tables_reject_bad_columns_and_rows(tmp_path, text, kwargs, error, message):
    path = tmp_path / "bad.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(error, match=message):
        tms.Trajectories.load(path, **kwargs)


def test_text_tables_are_read_as_utf8_only(tmp_path):
    path = tmp_path / "latin.tsv"
    path.write_bytes("time\tx\xe9\n0\t1\n".encode("latin-1"))
    with pytest.raises(tms.InputError, match=r"expected a UTF-8 text TSV file \(tab separated\)"):
        tms.Trajectories.load(path)


def test_save_rejects_bad_column_names(tmp_path):
    traj = tms.Trajectories(torch.arange(3.0), torch.zeros(2, 3, 2))
    with pytest.raises(tms.ShapeError, match=r"state_columns: expected 2 names"):
        traj.save(tmp_path / "a.csv", state_columns=["x"])
    with pytest.raises(tms.InputError, match=r"expected distinct column names, got \['x'\]"):
        traj.save(tmp_path / "a.csv", state_columns=["x", "x"])
    with pytest.raises(tms.InputError, match="expected names without spaces"):
        traj.save(tmp_path / "a.txt", state_columns=["x", "y 2"])
    with pytest.raises(tms.InputError, match=r"expected a .npz, .csv, .tsv or .txt file name"):
        traj.save(tmp_path / "a.json")


def test_simulate_rejects_wrong_state_dim(linear_system, paper_times):
    with pytest.raises(tms.ShapeError, match=r"y0: expected a last dimension of size state_dim=2.*got shape \(4, 3\)"):
        tms.simulate(linear_system, torch.zeros(4, 3), paper_times)


def test_simulate_rejects_nan_and_bad_times(linear_system):
    with pytest.raises(tms.InputError, match="y0: expected finite"):
        tms.simulate(linear_system, torch.tensor([[float("nan"), 0.0]]), torch.arange(3.0))
    with pytest.raises(tms.InputError, match="times: expected strictly increasing"):
        tms.simulate(linear_system, torch.zeros(1, 2), torch.tensor([0.0, 2.0, 1.0]))
    with pytest.raises(tms.ShapeError, match=r"times: expected \(2, T\) to match y0"):
        tms.simulate(linear_system, torch.zeros(2, 2), torch.arange(6.0).reshape(3, 2))


def test_simulate_reports_blow_up():
    system = MisspecifiedSystem(lambda y: y**2, 1, name="riccati")  # y' = y^2 blows up at t = 1 / y0
    with pytest.raises(tms.IntegrationError, match="blows up"):
        tms.simulate(system, torch.tensor([[2.0]], dtype=torch.float64), torch.linspace(0, 1, 5))


def test_system_rejects_bad_indices_and_names():
    field = tms.systems.LinearField(torch.eye(3))
    with pytest.raises(tms.InputError, match=r"correction_inputs: expected indices in \[0, 2\], got 3"):
        MisspecifiedSystem(field, 3, correction_inputs=[0, 3])
    with pytest.raises(tms.InputError, match="correction_outputs: expected distinct indices, got repeats"):
        MisspecifiedSystem(field, 3, correction_outputs=[1, 1])
    with pytest.raises(tms.InputError, match="state_dim: expected an integer >= 1, got 0"):
        MisspecifiedSystem(field, 0)
    with pytest.raises(tms.InputError, match="got the unknown name 'nope'"):
        tms.systems.get_system("nope")


def test_gravity_system_structure():
    system = tms.systems.paper_gravity()
    y = torch.tensor([[1.0, -1.0, 0.3, 0.2]], dtype=torch.float64)
    rhs = system.true_rhs(y)
    g = system.known(y)
    torch.testing.assert_close(rhs[:, :2], y[:, 2:])  # positions move with the velocities
    # the correction only changes the accelerations, from the two extra masses
    expected = sum(
        -m
        * (y[0, :2] - torch.tensor(p, dtype=torch.float64))
        / torch.linalg.vector_norm(y[0, :2] - torch.tensor(p, dtype=torch.float64)) ** 3
        for m, p in ((0.1, (0.0, 4.0)), (0.4, (0.5, 3.8)))
    )
    torch.testing.assert_close((rhs - g)[0, 2:], expected)
    torch.testing.assert_close((rhs - g)[0, :2], torch.zeros(2, dtype=torch.float64))


def test_times_the_states_dtype_cannot_resolve_are_not_blamed_on_the_user():
    """Times follow the states' dtype. Increasing float64 times that float32 rounds together raised 'expected
    strictly increasing values' as if the user's times were wrong; large times lost a tenth of a step silently."""
    states = torch.zeros(1, 3, 1, dtype=torch.float32)
    close = torch.tensor([1000.0, 1000.00001, 1000.00002], dtype=torch.float64)
    with pytest.raises(
        tms.InputError,
        match="expected times that float32 \\(the states' dtype\\) can resolve.*pass the states as float64",
    ):
        tms.Trajectories(close, states)
    far = torch.tensor([4e4, 4e4 + 0.05, 4e4 + 0.1], dtype=torch.float64)
    with pytest.warns(tms.NumericalWarning, match="got a rounding of up to"):
        tms.Trajectories(far, states)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tms.Trajectories(torch.linspace(0, 6, 3, dtype=torch.float64), states)  # ordinary times: no word


def test_messages_that_misled_now_say_what_is_wrong():
    """States given as (K, d, T) were blamed on the times; a G returning NumPy said 'returned shape ndarray'; a G
    that is not vectorised raised torch's bare ValueError."""
    import numpy as np

    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    with pytest.raises(tms.ShapeError, match=r"states look like \(K, d, T\); pass states.transpose\(1, 2\)"):
        tms.Trajectories(t, torch.zeros(4, 3, 11, dtype=torch.float64))
    numpy_g = tms.MisspecifiedSystem(lambda y: np.zeros(y.shape), 2)
    with pytest.raises(tms.ShapeError, match=r"G returned a numpy.ndarray .*expected a torch.Tensor of shape \(1, 2\)"):
        tms.simulate(numpy_g, torch.zeros(1, 2, dtype=torch.float64), t)
    scalar_g = tms.MisspecifiedSystem(lambda y: torch.stack([y[..., 1], -torch.tensor(float(y[0]))]), 2)
    with pytest.raises(tms.ShapeError, match=r"G must work on a batch of states.*y\[\.\.\., 0\] instead of float"):
        tms.simulate(scalar_g, torch.zeros(3, 2, dtype=torch.float64), t)
