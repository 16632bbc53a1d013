import json
import subprocess
import sys

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec.cli import main
from torchmisspec.design.candidates import grid


@pytest.fixture
def candidates_csv(tmp_path):
    path = tmp_path / "cands.csv"
    np.savetxt(path, grid(((-1, 1), (-1, 1)), 7).numpy(), delimiter=",", header="y0,y1", comments="")
    return path


def _design_args(candidates, out, *extra, budget=2):
    return [
        "design", "--candidates", str(candidates), "--system", "paper_linear", "--times", "0:6:11",
        "--budget", str(budget), "--out", str(out), "--quiet", *extra,
    ]  # fmt: skip


def test_demo_runs_end_to_end(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--quiet", "--n-train", "15", "--n-test", "5"]) == 0
    out = capsys.readouterr().out
    assert "integrated error of the correction over D" in out and "trajectory RMSE" in out
    results = json.loads((tmp_path / "demo" / "results.json").read_text())
    assert results["rmse_corrected"] < results["rmse_misspecified"]
    assert f"ratio {results['rmse_ratio']:.3f}" in out  # what it prints is what it saved
    assert results["n_train"] == 15 and results["n_test"] == 5 and results["seed"] == 0
    for name in ("trajectories.png", "error_map.png"):
        assert (tmp_path / "demo" / name).read_bytes()[:4] == b"\x89PNG"


def test_demo_reports_bad_sizes_as_an_error(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--quiet", "--n-train", "0"]) == 2
    assert "torchmisspec demo: error: n_train: expected an integer >= 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_design_command_writes_picks(tmp_path, candidates_csv, suffix):
    out = tmp_path / f"picks{suffix}"
    assert main(_design_args(candidates_csv, out, budget=4)) == 0
    # the command's picks are those of the library call with the same candidates, times and prior
    expected = tms.design.greedy(
        grid(((-1, 1), (-1, 1)), 7),
        4,
        system=tms.systems.paper_linear(),
        times=torch.linspace(0, 6, 11, dtype=torch.float64),
        gp=tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4),
    )
    if suffix == ".json":
        data = json.loads(out.read_text())
        assert data["indices"] == expected.indices.tolist()
        assert data["gains"] == pytest.approx(expected.gains.tolist(), rel=1e-12)
        assert data["information_gain"] == pytest.approx(expected.information_gain, rel=1e-12)
    else:
        lines = out.read_text().splitlines()
        assert lines[0] == "order,index,gain,y0,y1"
        assert [int(row.split(",")[1]) for row in lines[1:]] == expected.indices.tolist()


def test_design_command_with_partition(tmp_path, candidates_csv):
    labels = tmp_path / "labels.csv"
    np.savetxt(labels, (np.arange(49) % 2)[:, None], fmt="%d")
    out = tmp_path / "p.json"
    assert main(_design_args(candidates_csv, out, "--partition", str(labels), "--capacities", "0=1,1=2", budget=3)) == 0
    picks = json.loads(out.read_text())["indices"]
    assert sum(1 for i in picks if i % 2 == 0) <= 1


def test_design_command_conditions_on_data(tmp_path, candidates_csv):
    """``design --data``: the picks are the library's greedy design conditioned on the measured experiments."""
    system = tms.systems.paper_linear()
    times = torch.linspace(0, 6, 11, dtype=torch.float64)
    measured = tms.simulate(system, grid(((-1, 1), (-1, 1)), 7)[[0, 6, 42, 48]], times)
    data = tmp_path / "observed.npz"
    measured.save(data)
    out = tmp_path / "next.json"
    extra = ("--data", str(data), "--derivative", "central", "--criterion", "domain")
    assert main(_design_args(candidates_csv, out, *extra, budget=3)) == 0
    got = json.loads(out.read_text())
    samples = tms.correction_samples(measured, system, derivative="central")
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4).fit(samples)
    expected = tms.design.greedy(grid(((-1, 1), (-1, 1)), 7), 3, system=system, times=times, gp=gp, criterion="domain")
    assert got["indices"] == expected.indices.tolist()
    assert got["conditioned_on_samples"] == 44 and got["proxy"] == "corrected" and got["criterion"] == "domain"
    assert not {0, 6, 42, 48} & set(got["indices"])


def test_design_command_with_the_default_derivative(tmp_path, candidates_csv):
    """``design --data`` with the default ``--derivative auto``: on noisy data auto picks the GP in time, whose
    noise differs between the outputs, and the design (one kernel shared by the outputs) refused the samples with
    an option the command line does not have. Each sample now counts as noisy as its noisiest output, and the
    command says so."""
    system = tms.systems.paper_linear()
    times = torch.linspace(0, 6, 11, dtype=torch.float64)
    measured = tms.simulate(system, grid(((-1, 1), (-1, 1)), 7)[[0, 6, 42, 48]], times)
    noisy = tms.Trajectories(
        measured.times,
        measured.states
        + 1e-3 * torch.randn(measured.states.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64),
    )
    samples = tms.correction_samples(noisy, system)
    assert samples.noise is not None and not bool((samples.noise == samples.noise[:, :1]).all())  # the case
    data = tmp_path / "observed.npz"
    noisy.save(data)
    out = tmp_path / "next.json"
    with pytest.warns(tms.TorchMisspecWarning, match="noisiest output"):
        assert main(_design_args(candidates_csv, out, "--data", str(data), budget=3)) == 0
    got = json.loads(out.read_text())
    assert len(got["indices"]) == 3 and got["conditioned_on_samples"] == 44


def test_design_command_data_errors(tmp_path, candidates_csv, capsys):
    out = tmp_path / "x.json"
    assert main(_design_args(candidates_csv, out, "--learn-hyperparameters")) == 2
    assert "learning needs data" in capsys.readouterr().err
    assert main(_design_args(candidates_csv, out, "--data", str(tmp_path / "missing.csv"))) == 2
    assert "missing.csv" in capsys.readouterr().err
    assert main(_design_args(candidates_csv, out, "--criterion", "domain", "--method", "random")) == 2
    assert "only the greedy methods" in capsys.readouterr().err


def test_design_command_errors(tmp_path, candidates_csv, capsys):
    base = [
        "design",
        "--candidates",
        str(candidates_csv),
        "--times",
        "0:6:11",
        "--quiet",
        "--out",
        str(tmp_path / "x.csv"),
    ]
    assert main(base + ["--system", "nope", "--budget", "2"]) == 2
    assert "unknown system name 'nope'" in capsys.readouterr().err
    assert main(base + ["--system", "paper_linear", "--budget", "100"]) == 2
    assert "expected at most the number of candidates (49), got budget = 100" in capsys.readouterr().err
    assert main(base + ["--system", "paper_gravity", "--budget", "2"]) == 2
    assert r"expected shape (N, 4)" in capsys.readouterr().err


def test_console_script_help():
    proc = subprocess.run(
        [sys.executable, "-m", "torchmisspec.cli", "design", "--help"], capture_output=True, text=True, check=True
    )
    for option in ("--candidates", "--system", "--times", "--budget", "--partition", "--capacities", "--out"):
        assert option in proc.stdout


@pytest.mark.parametrize(
    ("content", "suffix", "message"),
    [
        (b"\xff\xfe\x00binary", ".csv", "UnicodeDecodeError"),
        ("y\xe9\n1,2\n".encode("latin-1"), ".csv", "UnicodeDecodeError"),
        (b"a,b\n1,x\n", ".csv", "could not be read"),
        (b"", ".csv", "expected a non-empty array of real numbers"),
        (b"\x93NUMPY garbage", ".npy", "could not be read"),
    ],
)
def test_unreadable_candidate_files_exit_2_with_one_line(tmp_path, capsys, content, suffix, message):
    path = tmp_path / f"cands{suffix}"
    path.write_bytes(content)
    assert main(_design_args(path, tmp_path / "out.csv")) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchmisspec design: error: candidates:") and message in err and "\n" not in err


def test_object_arrays_are_not_unpickled(tmp_path, capsys):
    np.save(tmp_path / "obj.npy", np.array([object()], dtype=object), allow_pickle=True)
    assert main(_design_args(tmp_path / "obj.npy", tmp_path / "out.csv")) == 2
    assert "Object arrays cannot be loaded when allow_pickle=False" in capsys.readouterr().err


def test_bad_times_and_output_paths_fail_before_the_work(tmp_path, candidates_csv, capsys, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("the design ran although its output cannot be written")

    monkeypatch.setattr(tms.design, "greedy", never)
    assert main(_design_args(candidates_csv, tmp_path / "no" / "folder" / "out.csv")) == 2
    assert "--out: cannot write" in capsys.readouterr().err
    assert main(_design_args(candidates_csv, tmp_path / "out.txt")) == 2
    assert "--out: expected a .csv or .json file name" in capsys.readouterr().err
    args = _design_args(candidates_csv, tmp_path / "out.csv")
    args[args.index("0:6:11")] = "0:6:-1"
    assert main(args) == 2
    assert "--times: expected 'start:stop:count' with count >= 1" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------------------ fit
@pytest.fixture(scope="module")
def observed_csv(tmp_path_factory):
    """paper_linear, 5 experiments x 11 times on [0, 6], saved with named columns (t, x1, x2)."""
    y0 = torch.rand(5, 2, generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 2 - 1
    trajs = tms.simulate(tms.systems.paper_linear(), y0, torch.linspace(0, 6, 11, dtype=torch.float64))
    return trajs.save(tmp_path_factory.mktemp("obs") / "obs.csv", time_column="t", state_columns=["x1", "x2"])


def _fit_args(data, out, *extra, system="paper_linear"):
    return ["fit", "--data", str(data), "--system", system, "--time-column", "t", "--out", str(out), "--quiet", *extra]


def test_fit_command_saves_the_model_a_direct_fit_gives(tmp_path, observed_csv, capsys):
    out = tmp_path / "model.pt"
    assert main(_fit_args(observed_csv, out, "--state-columns", "x1,x2", "--derivative", "central")) == 0
    line = capsys.readouterr().out.strip()
    loaded = tms.CorrectionGP.load(out)
    trajs = tms.Trajectories.load(observed_csv, time_column="t")
    direct = tms.fit_correction(trajs, tms.systems.paper_linear(), derivative="central")  # cv lengthscale
    assert direct.cross_validation_ is not None
    x = torch.rand(20, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 2 - 1
    torch.testing.assert_close(loaded.predict_mean(x), direct.predict_mean(x), rtol=1e-7, atol=1e-10)
    assert "\n" not in line and "N = 55 samples (5 experiments x 11 times, derivative 'central')" in line
    assert direct.lengthscale is None or f"lengthscale {direct.lengthscale:.4g}" in line
    assert f"fitted {direct.kernel} correction GP" in line
    assert f"log marginal likelihood {direct.log_marginal_likelihood_:.6g}" in line and str(out) in line


def test_fit_command_lengthscale_options(tmp_path, observed_csv, capsys):
    trajs = tms.Trajectories.load(observed_csv, time_column="t")
    system = tms.systems.paper_linear()
    for option, expected in (
        ("ml", tms.fit_correction(trajs, system, derivative="central", lengthscale="ml")),
        ("1.5", None),
    ):
        out = tmp_path / f"m{option}.pt"
        assert main(_fit_args(observed_csv, out, "--derivative", "central", "--lengthscale", option)) == 0
        loaded = tms.CorrectionGP.load(out)
        want = 1.5 if expected is None else float(expected.lengthscale)
        assert float(loaded.lengthscale) == pytest.approx(want, rel=1e-9)
    refined = tmp_path / "refined.pt"
    assert main(_fit_args(observed_csv, refined, "--derivative", "central", "--lengthscale", "1.5", "--refine")) == 0
    capsys.readouterr()
    # the refinement changes the training targets (the pseudo-targets), not the inputs or the hyperparameters
    plain, refit = tms.CorrectionGP.load(tmp_path / "m1.5.pt"), tms.CorrectionGP.load(refined)
    assert torch.equal(plain.train_inputs_, refit.train_inputs_)
    assert not torch.equal(plain.train_targets_, refit.train_targets_)
    assert main(_fit_args(observed_csv, tmp_path / "x.pt", "--lengthscale", "long")) == 2
    assert "--lengthscale: expected cv, ml or a positive number, got 'long'" in capsys.readouterr().err
    # kernels without a lengthscale: ml (a marginal-likelihood fit) is accepted, a number is refused
    poly = ("--derivative", "central", "--kernel", "polynomial")
    assert main(_fit_args(observed_csv, tmp_path / "p.pt", *poly, "--lengthscale", "ml")) == 0
    assert tms.CorrectionGP.load(tmp_path / "p.pt").kernel == "polynomial"
    capsys.readouterr()
    assert main(_fit_args(observed_csv, tmp_path / "p2.pt", *poly, "--lengthscale", "0.5")) == 2
    assert "the polynomial kernel has no lengthscale, got '0.5'" in capsys.readouterr().err


def test_fit_command_with_a_user_system_and_fixed_hyperparameters(tmp_path, observed_csv, monkeypatch, capsys, request):
    module = tmp_path / "my_lab_model.py"
    module.write_text("import torchmisspec as tms\n\ndef known():\n    return tms.systems.paper_linear()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    request.addfinalizer(lambda: sys.modules.pop("my_lab_model", None))
    out = tmp_path / "m.pt"
    fixed = ("--lengthscale", "0.7", "--outputscale", "1e-4", "--noise-variance", "1e-6", "--derivative", "smooth")
    assert main(_fit_args(observed_csv, out, *fixed, system="my_lab_model:known")) == 0
    gp = tms.CorrectionGP.load(out)
    assert (gp.lengthscale, gp.outputscale, gp.noise_variance) == pytest.approx((0.7, 1e-4, 1e-6), rel=1e-12)
    assert "derivative 'smooth'" in capsys.readouterr().out
    # design accepts the same spec
    cands = tmp_path / "c.csv"
    np.savetxt(cands, grid(((-1, 1), (-1, 1)), 4).numpy(), delimiter=",")
    args = _design_args(cands, tmp_path / "picks.json")
    args[args.index("paper_linear")] = str(module) + ":known"
    assert main(args) == 0 and len(json.loads((tmp_path / "picks.json").read_text())["indices"]) == 2


@pytest.mark.parametrize(
    ("extra", "replace", "message"),
    [
        ((), {"--system": "nope"}, "unknown system name 'nope'"),
        ((), {"--system": "no_such_module_xyz:f"}, "expected an importable module 'no_such_module_xyz'"),
        (("--state-columns", "x1,speed"), {}, "expected state columns ['x1', 'speed'], missing ['speed']"),
        ((), {"--time-column": "time"}, "expected a time column 'time', got columns ['experiment', 't', 'x1', 'x2']"),
        (("--experiment-column", "run"), {}, "expected an experiment column 'run'"),
        (("--derivative", "psychic"), {}, "derivative: expected one of"),
        (("--state-columns", "x1"), {}, "expected state dimension 2 of system 'paper_linear'"),
        (("--lengthscale", "-1"), {}, "lengthscale"),
        ((), {"--data": "missing.csv"}, "path: expected an existing file"),
    ],
)
def test_fit_command_bad_inputs_exit_2_with_one_line(tmp_path, observed_csv, capsys, extra, replace, message):
    args = _fit_args(observed_csv, tmp_path / "m.pt", *extra)
    for option, value in replace.items():
        args[args.index(option) + 1] = value
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchmisspec fit: error: ") and message in err and "\n" not in err
    assert not (tmp_path / "m.pt").exists()


def test_fit_command_checks_the_output_before_the_work(tmp_path, observed_csv, capsys, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("the data were read although the model cannot be written")

    monkeypatch.setattr(tms.Trajectories, "load", never)
    assert main(_fit_args(observed_csv, tmp_path / "no" / "folder" / "m.pt")) == 2
    assert "--out: cannot write" in capsys.readouterr().err
    assert main(_fit_args(observed_csv, tmp_path / "m.json")) == 2
    assert "--out: expected a .pt file name" in capsys.readouterr().err


def test_fit_command_fits_ragged_data(tmp_path, capsys):
    """Experiments of different lengths (ragged) are fitted as they come."""
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(0)
    y0 = torch.rand(4, 2, generator=g, dtype=torch.float64) * 2 - 1
    grids = [torch.linspace(0.0, 6.0, n, dtype=torch.float64) for n in (11, 15, 21, 11)]
    data = tms.simulate(system, y0, grids).save(tmp_path / "ragged.tsv")
    out = tmp_path / "m.pt"
    assert main(["fit", "--data", str(data), "--system", "paper_linear", "--out", str(out), "--quiet"]) == 0
    assert "N = 58 samples (4 experiments x 11-21 times" in capsys.readouterr().out
    assert tms.CorrectionGP.load(out).is_fitted
