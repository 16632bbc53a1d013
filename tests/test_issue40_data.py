"""Issue 40, files, columns and readouts read silently wrong (items 1, 2, 3 and the data / command-line part of 6).

Every column, readout and saved field is matched by name, or a mismatch is refused naming both orders; every field of
a Trajectories survives every file format, or the format is refused; the data's raw errors become package errors.
"""

from __future__ import annotations

import argparse
import math
import zipfile

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.cli import main
from torchmisspec.cli._common import read_observations
from torchmisspec.signals import Controls

DT = torch.float64

CHEMO = """
import torch
import torchmisspec as tms


def known(t, y, u):
    x, s, d = y[..., 0], y[..., 1], u[..., 0]
    return torch.stack([0.8 * x * s - d * x, d * (1.0 - s) - 0.8 * x * s], dim=-1)


def chemostat():
    return tms.MisspecifiedSystem(
        known, 2, state_names=["X", "S"], num_controls=1, control_names=["D"], name="chemostat"
    )


def unnamed():
    return tms.MisspecifiedSystem(known, 2, num_controls=1, name="unnamed")


def two_inputs():
    return tms.MisspecifiedSystem(
        lambda t, y, u: -u[..., :1] * y, 2, state_names=["X", "S"], num_controls=2, control_names=["D", "T"]
    )
"""


def chemostat():
    namespace: dict = {}
    exec(CHEMO, namespace)
    return namespace["chemostat"]()


def chemo_data(K: int = 3, T: int = 11) -> tms.Trajectories:
    """Chemostat runs under piecewise-constant dilution, states named (X, S) and the control D."""
    system = chemostat()
    g = torch.Generator().manual_seed(3)
    y0 = torch.stack([0.2 + 0.3 * torch.rand(K, generator=g, dtype=DT), 0.5 + 0.4 * torch.rand(K, generator=g)], -1)
    knots = torch.tensor([0.0, 3.0, 6.0], dtype=DT)
    controls = Controls(knots, 0.1 + 0.2 * torch.rand(K, 3, 1, generator=g, dtype=DT), names=["D"])
    return tms.simulate(system, y0.to(DT), torch.linspace(0, 10, T, dtype=DT), controls=controls)


def write_lab(path, data: tms.Trajectories, columns: list[str]) -> None:
    """A lab's table of ``data`` with the columns ``run, hour`` and the states / control in the order ``columns``."""
    lines = [",".join(["run", "hour", *columns])]
    for k, (t, y) in enumerate(data.experiments()):
        u = data.control_values()[k]
        cell = {"X": y[:, 0], "S": y[:, 1], "D": u[:, 0]}
        for i in range(len(t)):
            lines.append(",".join([f"r{k}", repr(float(t[i]))] + [repr(float(cell[c][i])) for c in columns]))
    path.write_text("\n".join(lines) + "\n")


def args_for(data, **options) -> argparse.Namespace:
    values = dict(
        data=str(data),
        time_column="hour",
        experiment_column="run",
        state_columns=None,
        input_columns="D",
        input_kind="previous",
        readout=None,
    )
    values.update(options)
    return argparse.Namespace(**values)


@pytest.fixture(scope="module")
def lab_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("chemo")
    data = chemo_data()
    (folder / "chemo.py").write_text(CHEMO)
    write_lab(folder / "xs.csv", data, ["X", "S", "D"])
    write_lab(folder / "sx.csv", data, ["S", "X", "D"])
    return folder, data


# ---------------------------------------------------------------------------------------- 1. columns read by name
def test_the_cli_reads_state_columns_by_name_whatever_their_order(lab_files):
    folder, data = lab_files
    system = chemostat()
    for name in ("xs.csv", "sx.csv"):
        observed = read_observations(args_for(folder / name), system)
        assert observed.state_names == ("X", "S")
        torch.testing.assert_close(observed.states, data.states, rtol=0, atol=0)  # S was fitted as X before
        assert observed.controls.names == ("D",)


@pytest.mark.slow
def test_the_fit_command_on_columns_in_another_order_is_the_same_fit(lab_files, tmp_path):
    folder, _ = lab_files
    common = ["--time-column", "hour", "--experiment-column", "run", "--input-columns", "D", "--quiet"]
    common += ["--system", f"{folder / 'chemo.py'}:chemostat", "--derivative", "central", "--no-calibrate"]
    models = []
    for name in ("xs.csv", "sx.csv"):
        out = tmp_path / f"{name}.pt"
        assert main(["fit", "--data", str(folder / name), *common, "--out", str(out)]) == 0
        models.append(tms.CorrectionGP.load(out))
    assert models[0].input_names_ == models[1].input_names_ == ("X", "S", "D")[: models[0].input_dim]
    x = torch.rand(10, models[0].input_dim, generator=torch.Generator().manual_seed(0), dtype=DT)
    torch.testing.assert_close(models[0].predict_mean(x), models[1].predict_mean(x))


def test_a_time_or_other_column_named_as_a_state_is_refused(lab_files, tmp_path, capsys):
    folder, _ = lab_files
    base = ["fit", "--data", str(folder / "sx.csv"), "--system", f"{folder / 'chemo.py'}:chemostat", "--quiet"]
    base += ["--out", str(tmp_path / "m.pt")]
    cases = {
        ("--time-column", "X", "--experiment-column", "run", "--input-columns", "D"): "--time-column: expected",
        ("--time-column", "hour", "--experiment-column", "S", "--input-columns", "D"): "--experiment-column: expected",
        ("--time-column", "hour", "--experiment-column", "run", "--input-columns", "X"): "--input-columns: expected",
    }
    for options, message in cases.items():
        assert main([*base, *options]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "a state of system 'chemostat' (X, S)" in err and "\n" not in err, err
    assert not (tmp_path / "m.pt").exists()


def test_state_columns_name_the_columns_in_the_systems_order(lab_files, tmp_path, capsys):
    folder, data = lab_files
    system = chemostat()
    renamed = tmp_path / "renamed.csv"
    renamed.write_text((folder / "sx.csv").read_text().replace("run,hour,S,X,D", "run,hour,substrate,biomass,D", 1))
    observed = read_observations(args_for(renamed, state_columns="biomass,substrate"), system)
    assert observed.state_names == ("X", "S")  # the system's states, read from the columns named for them
    torch.testing.assert_close(observed.states, data.states, rtol=0, atol=0)
    with pytest.raises(
        tms.InputError,
        match=r"--state-columns: expected state dimension 2 of system 'chemostat' \(one column name per state: X, S",
    ):
        read_observations(args_for(renamed, state_columns="biomass"), system)
    with pytest.raises(tms.InputError, match=r"names the system's states in another order: 'S' is its state 2"):
        read_observations(args_for(folder / "sx.csv", state_columns="S,X"), system)
    read = read_observations(args_for(folder / "sx.csv", state_columns="X,S"), system)
    torch.testing.assert_close(read.states, data.states, rtol=0, atol=0)


def test_input_columns_naming_the_systems_inputs_in_another_order_are_refused(lab_files):
    folder, _ = lab_files
    namespace: dict = {}
    exec(CHEMO, namespace)
    with pytest.raises(tms.InputError, match=r"--input-columns: T,D names the system's inputs in another order"):
        read_observations(args_for(folder / "xs.csv", input_columns="T,D"), namespace["two_inputs"]())


def test_a_table_without_the_systems_inputs_says_how_to_name_them(lab_files):
    folder, _ = lab_files
    with pytest.raises(tms.InputError, match=r"the system also takes 1 input\(s\) \['D'\]: name their columns"):
        read_observations(args_for(folder / "xs.csv", input_columns=None), chemostat())


def test_initial_states_are_the_systems_states_named_by_it(tmp_path):
    from torchmisspec.cli._common import read_states

    system = chemostat()
    lab = tmp_path / "initial.csv"
    lab.write_text("run,biomass,substrate\na,0.2,0.8\nb,0.5,0.4\n")
    y0, names, labels = read_states(str(lab), "--initial", args_for(lab, state_columns="biomass,substrate"), system)
    assert names == ["X", "S"] and labels == ["a", "b"]  # what the model fitted with --state-columns is named
    torch.testing.assert_close(y0, torch.tensor([[0.2, 0.8], [0.5, 0.4]], dtype=DT))
    with pytest.raises(tms.InputError, match=r"--initial: expected columns named as the states of system 'chemostat'"):
        read_states(str(lab), "--initial", args_for(lab), system)  # not taken in file order
    (tmp_path / "sx.csv").write_text("run,S,X\na,0.8,0.2\n")
    y0, names, _ = read_states(str(tmp_path / "sx.csv"), "--initial", args_for(lab), system)
    assert names == ["X", "S"] and y0.tolist() == [[0.2, 0.8]]


def test_no_state_column_named_as_the_systems_states_is_refused(lab_files, tmp_path):
    folder, _ = lab_files
    lower = tmp_path / "lower.csv"
    lower.write_text((folder / "xs.csv").read_text().replace("run,hour,X,S,D", "run,hour,x,s,D", 1))
    with pytest.raises(tms.InputError, match=r"expected state columns named as the states of system 'chemostat'"):
        read_observations(args_for(lower), chemostat())


def test_an_archive_with_the_states_in_another_order_is_read_by_name(lab_files, tmp_path):
    _, data = lab_files
    swapped = tms.Trajectories(data.times, data.states[..., [1, 0]], state_names=["S", "X"], controls=data.controls)
    swapped.save(tmp_path / "sx.npz")
    observed = read_observations(args_for(tmp_path / "sx.npz", input_columns=None), chemostat())
    assert observed.state_names == ("X", "S")
    torch.testing.assert_close(observed.states, data.states, rtol=0, atol=0)


def test_a_system_naming_no_states_reads_the_other_columns_in_file_order(lab_files):
    folder, _ = lab_files
    namespace: dict = {}
    exec(CHEMO, namespace)
    observed = read_observations(args_for(folder / "sx.csv"), namespace["unnamed"]())
    assert observed.state_names == ("S", "X")  # the columns' names go with them: later commands match by them


def test_the_python_api_refuses_states_named_in_another_order():
    data = chemo_data()
    system = chemostat()
    swapped = tms.Trajectories(data.times, data.states[..., [1, 0]], state_names=["S", "X"], controls=data.controls)
    for call in (
        lambda t: tms.correction_samples(t, system, derivative="central"),
        lambda t: tms.fit_correction(t, system, progress=False),
    ):
        with pytest.raises(tms.InputError, match=r"in the order of system 'chemostat' \['X', 'S'\], got \['S', 'X'\]"):
            call(swapped)
    with pytest.raises(tms.InputError, match=r"trajectories.reordered\(\['X', 'S'\]\)"):
        tms.correction_samples(swapped, system, derivative="central")
    x = torch.rand(10, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-2, noise_variance=1e-4).fit(x, torch.zeros(10, 2, dtype=DT))
    model = tms.CorrectedODE(system, gp)
    camp = tms.design.Campaign(system, x[:5], data.times, gp, controls=data.controls[[0] * 5], derivative="central")
    for call in (model.complete, model.initial_states, lambda t: camp.tell(t, asked=[-1, -1, -1])):
        with pytest.raises(tms.InputError, match=r"in the order of system 'chemostat'"):
            call(swapped)
    back = swapped.reordered(system.state_names)
    assert back.state_names == ("X", "S")
    torch.testing.assert_close(back.states, data.states, rtol=0, atol=0)
    reference = tms.correction_samples(data, system, derivative="central")
    torch.testing.assert_close(tms.correction_samples(back, system, derivative="central").targets, reference.targets)
    other = tms.Trajectories(data.times, data.states, state_names=["biomass", "S"], controls=data.controls)
    with pytest.raises(tms.InputError, match=r"named as the states of system 'chemostat' \['X', 'S'\], got"):
        tms.correction_samples(other, system, derivative="central")
    # states named by default (y0, y1: no names given) are the system's, in its order
    plain = tms.Trajectories(data.times, data.states, controls=data.controls)
    torch.testing.assert_close(tms.correction_samples(plain, system, derivative="central").targets, reference.targets)


def test_reordered_and_renamed_trajectories():
    t = torch.linspace(0, 1, 4, dtype=DT)
    y = torch.arange(24, dtype=DT).reshape(3, 4, 2)
    traj = tms.Trajectories(t, y, state_names=["a", "b"], initial_states=y[:, 0])
    back = traj.reordered(["b", "a"])
    torch.testing.assert_close(back.states, y[..., [1, 0]])
    torch.testing.assert_close(back.initial_states, y[:, 0, [1, 0]])
    with pytest.raises(
        tms.InputError, match=r"expected a reordering of the state names \['a', 'b'\], got \['a', 'c'\]"
    ):
        traj.reordered(["a", "c"])
    assert traj.with_state_names(["x", "z"]).state_names == ("x", "z")
    ragged = tms.Trajectories([t, t[:3]], [y[0], y[1, :3]], state_names=["a", "b"])
    torch.testing.assert_close(ragged.reordered(["b", "a"]).states[1], y[1, :3, [1, 0]])


# ---------------------------------------------------------------------------------------- 2. readouts by name
def test_a_readout_is_attached_to_the_states_by_name():
    R = tms.Readout.parse(["x = 2*free"], ["free", "bound"])
    t = torch.linspace(0, 1, 5, dtype=DT)
    y = torch.rand(2, 5, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    traj = tms.Trajectories(t, y, state_names=["bound", "free"], readout=R, readings=2 * y[..., 1:])
    assert traj.readout.describe(traj.state_names) == ["x = 2*free"]  # read 2*bound before
    torch.testing.assert_close(traj.observe(y)[..., 2:], 2 * y[..., 1:])
    read = tms.Trajectories(t, y, state_names=["bound", "free"]).with_readout(R)  # the readings of the states
    torch.testing.assert_close(read.readings, 2 * y[..., 1:])
    assert read.readout.describe(read.state_names) == ["x = 2*free"]
    with pytest.raises(tms.InputError, match=r"readout: expected weights over the states \['bound', 'other'\]"):
        tms.Trajectories(t, y, state_names=["bound", "other"], readout=R, readings=2 * y[..., 1:])
    # a readout that names no states is read in the trajectories' order; so are trajectories that name none
    plain = tms.Readout(torch.tensor([[2.0, 0.0]], dtype=DT), ["x"])
    assert tms.Trajectories(t, y, state_names=["bound", "free"], readout=plain, readings=y[..., :1]).readout == plain
    assert tms.Trajectories(t, y, readout=R, readings=y[..., :1]).readout == R


def test_a_posterior_reads_a_named_readout_by_name():
    from torchmisspec.prediction._bands import TrajectoryPosterior

    samples = torch.rand(3, 1, 4, 2, dtype=DT, generator=torch.Generator().manual_seed(1))
    post = TrajectoryPosterior(
        torch.zeros(1, 4, dtype=DT), samples, samples[0], torch.zeros(1, 4), torch.zeros(1, dtype=torch.bool), 0.5,
        state_names=("bound", "free"),
    )  # fmt: skip
    read = post.read(tms.Readout.parse(["x = 2*free"], ["free", "bound"]))
    torch.testing.assert_close(read.samples, 2 * samples[..., 1:])


# ---------------------------------------------------------------------------------------- 3. every field saved
def rich(ragged: bool, kind: str = "previous", dtype=DT) -> tms.Trajectories:
    """Trajectories with every field: names, controls (ragged knots), a readout with its readings, NaN entries."""
    g = torch.Generator().manual_seed(2)
    lengths = (6, 4) if ragged else (5, 5)
    times = [torch.linspace(0, 2, n, dtype=DT) for n in lengths]
    states = [torch.rand(n, 2, generator=g, dtype=DT) for n in lengths]
    states[0][1, 0] = math.nan
    knots = [torch.tensor([0.0, 0.7, 1.3], dtype=DT), torch.tensor([0.0, 1.1], dtype=DT)]
    values = [torch.rand(3, 2, generator=g, dtype=DT), torch.rand(2, 2, generator=g, dtype=DT)]
    controls = Controls(knots, values, kind=kind, names=["feed", "heat"])
    R = tms.Readout.parse(["total = free + 0.5 bound"], ["free", "bound"])
    readings = [R(y.nan_to_num()) for y in states]
    if not ragged:
        times, states, readings = times[0], torch.stack(states), torch.stack(readings)
    traj = tms.Trajectories(
        times, states, state_names=["free", "bound"], controls=controls, readout=R, readings=readings
    )
    return traj.to(dtype)


def assert_same(back: tms.Trajectories, traj: tms.Trajectories, *, exact_knots: bool = True) -> None:
    assert back.state_names == traj.state_names and back.is_ragged == traj.is_ragged and back.lengths == traj.lengths
    for a, b in zip(back.experiments(), traj.experiments(), strict=True):
        torch.testing.assert_close(a[0], b[0].to(a[0]), rtol=0, atol=0)
        torch.testing.assert_close(a[1], b[1].to(a[1]), rtol=0, atol=0, equal_nan=True)
    assert back.readout == traj.readout and back.readout.names == traj.readout.names
    for a, b in zip(back.readings, traj.readings, strict=True):
        torch.testing.assert_close(a, b.to(a), rtol=0, atol=0)
    c, d = back.controls, traj.controls
    assert c.names == d.names and c.kind == d.kind and c.num_experiments == d.num_experiments
    grid = torch.linspace(-0.5, 3, 71, dtype=d.values.dtype).expand(d.num_experiments, -1)  # times d can hold
    torch.testing.assert_close(c.at(grid.to(c.values)), d.at(grid).to(c.values), rtol=0, atol=0)
    if exact_knots:
        for (k1, v1), (k2, v2) in zip(c.profiles(), d.profiles(), strict=True):
            torch.testing.assert_close(k1, k2, rtol=0, atol=0)
            torch.testing.assert_close(v1, v2, rtol=0, atol=0)


@pytest.mark.parametrize("ragged", [False, True])
@pytest.mark.parametrize("kind", ["previous", "linear"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_an_archive_keeps_every_field(tmp_path, ragged, kind, dtype):
    traj = rich(ragged, kind, dtype).with_initial_states(torch.ones(2, 2, dtype=dtype))
    back = tms.Trajectories.load(traj.save(tmp_path / "x.npz"))
    assert back.dtype == dtype
    assert_same(back, traj)
    torch.testing.assert_close(back.initial_states, traj.initial_states, rtol=0, atol=0)


@pytest.mark.parametrize("suffix", [".csv", ".tsv", ".txt"])
@pytest.mark.parametrize("ragged", [False, True])
def test_a_table_keeps_every_field_it_is_told_the_columns_of(tmp_path, suffix, ragged):
    traj = rich(ragged)
    back = tms.Trajectories.load(
        traj.save(tmp_path / f"x{suffix}"), control_columns=["feed", "heat"], readout=traj.readout
    )
    assert back.dtype == torch.float64  # a table is read as float64, the values exactly as written
    assert_same(back, traj, exact_knots=False)  # the same profiles: knots at every row
    traj32 = rich(ragged, dtype=torch.float32)
    back = tms.Trajectories.load(
        traj32.save(tmp_path / f"y{suffix}"), control_columns=["feed", "heat"], readout=traj.readout
    )
    assert_same(back, traj32, exact_knots=False)


@pytest.mark.parametrize("suffix", [".csv", ".tsv", ".txt"])
def test_a_table_refuses_what_it_cannot_hold(tmp_path, suffix):
    with pytest.raises(tms.InputError, match=r"a table records the profiles' samples, not how they run between"):
        rich(False, "linear").save(tmp_path / f"x{suffix}")
    with pytest.raises(tms.InputError, match=r"a table holds observations, not the initial_states"):
        rich(False).with_initial_states(torch.ones(2, 2, dtype=DT)).save(tmp_path / f"x{suffix}")
    assert not (tmp_path / f"x{suffix}").exists()


@pytest.mark.parametrize("suffix", [".npz", ".csv", ".tsv", ".txt"])
def test_controls_given_as_a_function_cannot_be_saved(tmp_path, suffix):
    t = torch.linspace(0, 1, 5, dtype=DT)
    u = Controls.from_function(lambda s: torch.sin(s).unsqueeze(-1), 2, 1)
    traj = tms.Trajectories(t, torch.ones(2, 5, 1, dtype=DT), controls=u)
    with pytest.raises(tms.InputError, match=r"controls: a profile given as a function u\(t\) cannot be saved"):
        traj.save(tmp_path / f"x{suffix}")
    assert not (tmp_path / f"x{suffix}").exists()


def test_names_shared_by_a_state_a_control_or_a_reading_are_refused():
    t = torch.linspace(0, 1, 5, dtype=DT)
    y = torch.ones(2, 5, 2, dtype=DT)
    clash = Controls(t, torch.ones(2, 5, 1, dtype=DT), names=["X"])
    with pytest.raises(tms.InputError, match=r"expected controls named apart from the states, got \['X'\] in both"):
        tms.Trajectories(t, y, state_names=["X", "S"], controls=clash)
    R = tms.Readout(torch.ones(1, 2, dtype=DT), ["X"])
    with pytest.raises(tms.InputError, match=r"expected readings named apart from the states, got \['X'\] in both"):
        tms.Trajectories(t, y, state_names=["X", "S"], readout=R, readings=y[..., :1])
    R = tms.Readout(torch.ones(1, 2, dtype=DT), ["feed"])
    feed = Controls(t, torch.ones(2, 5, 1, dtype=DT), names=["feed"])
    with pytest.raises(tms.InputError, match=r"expected readings named apart from the controls, got \['feed'\]"):
        tms.Trajectories(t, y, controls=feed, readout=R, readings=y[..., :1])


# ---------------------------------------------------------------------------------------- 6. raw errors
def corrupt_archives(folder) -> dict:
    np.savez(folder / "good.npz", candidates=np.ones((4, 2)))
    np.save(folder / "plain.npy", np.ones((4, 2)))
    (folder / "plain.npz").write_bytes((folder / "plain.npy").read_bytes())  # np.save'd content under an .npz name
    with zipfile.ZipFile(folder / "text_member.npz", "w") as z:
        z.writestr("candidates.npy", "hello")
        z.writestr("times.npy", "hello")
        z.writestr("states.npy", "hello")
    np.savez_compressed(folder / "compressed.npz", candidates=np.ones((400, 2)), times=np.ones(3), states=np.ones(3))
    raw = bytearray((folder / "compressed.npz").read_bytes())
    raw[60] ^= 0xFF
    raw[80] ^= 0xFF
    (folder / "inflated.npz").write_bytes(bytes(raw))
    return {"plain.npz": "not an .npz archive", "text_member.npz": "could not be read", "inflated.npz": "could not"}


def test_loading_a_plain_array_or_a_corrupt_archive_is_an_input_error(tmp_path):
    for name, message in corrupt_archives(tmp_path).items():
        with pytest.raises(tms.InputError, match=message):
            tms.Trajectories.load(tmp_path / name)
    with pytest.raises(tms.InputError, match=r"expected a \.npz, \.csv, \.tsv or \.txt file name"):
        tms.Trajectories.load(tmp_path / "plain.npy")


def test_design_candidates_from_a_corrupt_archive_is_one_line_and_exit_2(tmp_path, capsys):
    for name, message in corrupt_archives(tmp_path).items():
        args = ["design", "--candidates", str(tmp_path / name), "--system", "paper_linear", "--times", "0:6:11"]
        args += ["--budget", "1", "--out", str(tmp_path / "out.csv"), "--quiet"]
        args += ["--lengthscale", "1.0", "--outputscale", "4e-5", "--noise-variance", "1e-4"]
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("torchmisspec design: error: --candidates: ") and message in err, err
        assert "internal error" not in err and "\n" not in err


@pytest.mark.parametrize(
    ("states", "error", "message"),
    [
        (np.ones((3, 2)), tms.InputError, r"expected a torch tensor of states \(\.\.\., 2\), got ndarray"),
        ([[1.0, 2.0]], tms.InputError, r"expected a torch tensor of states \(\.\.\., 2\), got list"),
        (torch.ones(3, 2, dtype=torch.bool), tms.InputError, r"expected real floating states, got dtype torch.bool"),
        (torch.ones(3, 2, dtype=torch.int64), tms.InputError, r"expected real floating states, got dtype torch.int64"),
        (torch.ones(3, 2, dtype=torch.complex128), tms.InputError, r"got dtype torch.complex128"),
        (
            torch.ones(3, 3, dtype=DT),
            tms.ShapeError,
            r"expected states \(\.\.\., 2\) \(free, bound\), got shape \(3, 3\)",
        ),
        (torch.ones((), dtype=DT), tms.ShapeError, r"got shape \(\)"),
    ],
)
def test_a_readout_called_on_what_it_cannot_read_says_what_it_expects(states, error, message):
    R = tms.Readout.parse(["total = free + bound"], ["free", "bound"])
    with pytest.raises(error, match=message):
        R(states)
    torch.testing.assert_close(R(torch.ones(4, 2, dtype=torch.float32)), torch.full((4, 1), 2.0))
