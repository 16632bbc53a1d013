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


PRIOR = ("--lengthscale", "1.0", "--outputscale", "4e-5", "--noise-variance", "1e-4")


def _design_args(candidates, out, *extra, budget=2, prior=PRIOR):
    return [
        "design", "--candidates", str(candidates), "--system", "paper_linear", "--times", "0:6:11",
        "--budget", str(budget), "--out", str(out), "--quiet", *prior, *extra,
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
    # the command's picks are those of the library call with the same candidates, times and (stated) prior
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
        assert list(data["points"][0]) == ["y0", "y1"]  # the candidates file's column names
    else:
        lines = out.read_text().splitlines()
        assert lines[0] == "order,index,gain,y0,y1"
        assert [int(row.split(",")[1]) for row in lines[1:]] == expected.indices.tolist()


def test_design_command_stochastic_is_the_library_call_with_the_seed(tmp_path, candidates_csv):
    out = tmp_path / "picks.json"
    assert main(_design_args(candidates_csv, out, "--method", "stochastic", "--seed", "3", budget=4)) == 0
    expected = tms.design.greedy(
        grid(((-1, 1), (-1, 1)), 7), 4, system=tms.systems.paper_linear(),
        times=torch.linspace(0, 6, 11, dtype=torch.float64),
        gp=tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4), method="stochastic",
        engine=tms.design.Engine(generator=torch.Generator().manual_seed(3)), )  # fmt: skip
    assert json.loads(out.read_text())["indices"] == expected.indices.tolist()


def test_design_has_no_hidden_prior(tmp_path, candidates_csv, capsys):
    """Without a model, data or a stated prior the design refuses (it applied paper_linear's prior to any system),
    naming the three ways; a partial prior names what is missing."""
    assert main(_design_args(candidates_csv, tmp_path / "x.csv", prior=())) == 2
    err = capsys.readouterr().err.strip()
    assert "no model to design with" in err and "--model" in err and "--data" in err and "\n" not in err
    assert main(_design_args(candidates_csv, tmp_path / "x.csv", prior=("--lengthscale", "1"))) == 2
    assert "missing --outputscale, --noise-variance" in capsys.readouterr().err


def test_design_command_with_partition(tmp_path, candidates_csv):
    labels = tmp_path / "labels.csv"
    np.savetxt(labels, (np.arange(49) % 2)[:, None], fmt="%d")
    out = tmp_path / "p.json"
    assert main(_design_args(candidates_csv, out, "--partition", str(labels), "--capacities", "0=1,1=2", budget=3)) == 0
    picks = json.loads(out.read_text())["indices"]
    assert sum(1 for i in picks if i % 2 == 0) <= 1


def test_design_command_conditions_a_stated_prior_on_data(tmp_path, candidates_csv):
    """``design --data`` with a stated prior: the library's greedy design of that prior conditioned on the data."""
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


def test_design_command_with_data_and_defaults(tmp_path, candidates_csv):
    """``design --data`` alone: a model fitted with fit_correction's defaults (on noisy data the derivative is the GP
    in time's, whose noise differs between outputs: the design conditions each output on its own data)."""
    system = tms.systems.paper_linear()
    times = torch.linspace(0, 6, 11, dtype=torch.float64)
    measured = tms.simulate(system, grid(((-1, 1), (-1, 1)), 7)[[0, 6, 24, 42, 48]], times)
    noise = 1e-3 * torch.randn(measured.states.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    data = tmp_path / "observed.npz"
    tms.Trajectories(measured.times, measured.states + noise).save(data)
    out = tmp_path / "next.json"
    assert main(_design_args(candidates_csv, out, "--data", str(data), budget=3, prior=())) == 0
    got = json.loads(out.read_text())
    assert len(got["indices"]) == 3 and got["conditioned_on_samples"] == 55 and "fitted on" in got["model"]


def test_design_command_errors(tmp_path, candidates_csv, capsys):
    base = ["design", "--candidates", str(candidates_csv), "--times", "0:6:11", "--quiet", *PRIOR]
    base += ["--out", str(tmp_path / "x.csv")]
    assert main(base + ["--system", "nope", "--budget", "2"]) == 2
    assert "unknown system name 'nope'" in capsys.readouterr().err
    assert main(base + ["--system", "paper_linear", "--budget", "100"]) == 2
    assert "expected at most the number of candidates (49), got budget = 100" in capsys.readouterr().err
    assert main(base + ["--system", "paper_gravity", "--budget", "2"]) == 2
    assert "--candidates: expected 4 states per row (system 'paper_gravity'), got 2" in capsys.readouterr().err
    assert (
        main(base + ["--system", "paper_linear", "--budget", "2", "--criterion", "domain", "--method", "random"]) == 2
    )
    assert "expected a greedy --method" in capsys.readouterr().err


def test_console_script_help():
    proc = subprocess.run(
        [sys.executable, "-m", "torchmisspec.cli", "design", "--help"], capture_output=True, text=True, check=True
    )
    for option in ("--candidates", "--system", "--times", "--budget", "--model", "--data", "--time-column", "--out"):
        assert option in proc.stdout


@pytest.mark.parametrize(
    ("content", "suffix", "message"),
    [
        (b"\xff\xfe\x00binary", ".csv", "UnicodeDecodeError"),
        ("y\xe9\n1,2\n".encode("latin-1"), ".csv", "UnicodeDecodeError"),
        (b"a,b\n1,x\n", ".csv", "expected a number in every state column of line 2"),
        (b"", ".csv", "expected at least one row of states"),
        (b"y0,y1\n", ".csv", "expected at least one row of states"),
        (b"y0,y1\n1,\n", ".csv", "expected a number in every state column of line 2"),
        (b"y0,y1\n1,nan\n", ".csv", "expected finite states"),
        (b"\x93NUMPY garbage", ".npy", "could not be read"),
    ],
)
def test_unreadable_candidate_files_exit_2_with_one_line(tmp_path, capsys, content, suffix, message):
    path = tmp_path / f"cands{suffix}"
    path.write_bytes(content)
    assert main(_design_args(path, tmp_path / "out.csv")) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchmisspec design: error: --candidates:") and message in err and "\n" not in err


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


def test_fit_command_saves_the_calibrated_model_a_direct_fit_gives(tmp_path, observed_csv, capsys):
    out = tmp_path / "model.pt"
    assert main(_fit_args(observed_csv, out, "--state-columns", "x1,x2", "--derivative", "central")) == 0
    printed = capsys.readouterr().out
    loaded = tms.CorrectionGP.load(out)
    trajs = tms.Trajectories.load(observed_csv, time_column="t")
    direct = tms.fit_correction(trajs, tms.systems.paper_linear(), derivative="central")
    x = torch.rand(20, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 2 - 1
    torch.testing.assert_close(loaded.predict_mean(x), direct.predict_mean(x), rtol=1e-7, atol=1e-10)
    assert "on 55 samples (5 experiments x 11 times, derivative 'central', noise 'additive')" in printed
    assert f"chose {direct.cross_validation_.best}" in printed and str(out) in printed
    assert loaded.calibration_ is not None and f"scale={loaded.calibration_.scale:.3g}" in printed
    if loaded.weights is not None:  # a feature kernel: its terms in the data's names, and the ones it may have missed
        terms = loaded.terms(["x1", "x2"], all_terms=True)
        for o, name in enumerate(["x1", "x2"]):
            (line,) = [row for row in printed.splitlines() if row.startswith(f"correction of d{name}/dt: ")]
            assert all(str(t) in line for t in terms if t.output == o and t.weight > 0)
            for t in terms:
                if t.output == o and t.weight == 0:
                    assert (f"{t.name} (chance {t.inclusion:.2f})" in line) == (t.inclusion >= 0.05)
    assert main(_fit_args(observed_csv, tmp_path / "raw.pt", "--derivative", "central", "--no-calibrate")) == 0
    assert tms.CorrectionGP.load(tmp_path / "raw.pt").calibration_ is None


def test_fit_command_takes_the_noise_model_and_refuses_one_the_data_cannot_have(tmp_path, observed_csv, capsys):
    """Issue 41: --noise relative on states that cross 0 is one line naming the fix (exit 2), and nothing written;
    a name the CLI does not know is argparse's own refusal."""
    out = tmp_path / "model.pt"
    assert main(_fit_args(observed_csv, out, "--noise", "relative")) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "expected positive measurements for relative" in err
    assert "--noise counts" in err and "--noise additive" in err and "noise=" not in err  # the CLI's own flags
    assert not out.exists()
    assert main(_fit_args(observed_csv, out, "--noise", "poisson")) == 2  # counts cannot be negative
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "expected counts (0 or more) for --noise poisson" in err
    assert main(_fit_args(observed_csv, out, "--noise", "gaussian")) == 2
    assert "invalid choice: 'gaussian'" in capsys.readouterr().err


def test_fit_command_with_a_user_system(tmp_path, observed_csv, monkeypatch, capsys, request):
    module = tmp_path / "my_lab_model.py"
    module.write_text("import torchmisspec as tms\n\ndef known():\n    return tms.systems.paper_linear()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    request.addfinalizer(lambda: sys.modules.pop("my_lab_model", None))
    out = tmp_path / "m.pt"
    assert (
        main(_fit_args(observed_csv, out, "--derivative", "smooth", "--no-calibrate", system="my_lab_model:known")) == 0
    )
    assert "derivative 'smooth'" in capsys.readouterr().out and tms.CorrectionGP.load(out).is_fitted
    # design accepts the same spec, and the model
    cands = tmp_path / "c.csv"
    np.savetxt(cands, grid(((-1, 1), (-1, 1)), 4).numpy(), delimiter=",")
    args = _design_args(cands, tmp_path / "picks.json", "--model", str(out), prior=())
    args[args.index("paper_linear")] = str(module) + ":known"
    assert main(args) == 0 and len(json.loads((tmp_path / "picks.json").read_text())["indices"]) == 2


@pytest.mark.parametrize(
    ("extra", "replace", "message"),
    [
        ((), {"--system": "nope"}, "unknown system name 'nope'"),
        ((), {"--system": "no_such_module_xyz:f"}, "expected an importable module 'no_such_module_xyz'"),
        (("--state-columns", "x1,speed"), {}, "expected state columns ['x1', 'speed'], got columns"),
        ((), {"--time-column": "time"}, "expected a time column 'time', got columns ['experiment', 't', 'x1', 'x2']"),
        (("--experiment-column", "run"), {}, "expected an experiment column 'run'"),
        (("--derivative", "psychic"), {}, "derivative: expected one of"),
        (("--state-columns", "x1"), {}, "expected state dimension 2 of system 'paper_linear'"),
        (("--state-noise", "loud"), {}, "--state-noise: expected auto, a percentage"),
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
    assert "on 58 samples (4 experiments x 11-21 times" in capsys.readouterr().out
    assert tms.CorrectionGP.load(out).is_fitted


# ------------------------------------------------------------------------------------------ the loop on a lab's file
LAB_SYSTEM = """
import torch
import torchmisspec as tms


def known(y):  # logistic growth of a culture, with the dilution known and the growth's saturation missing
    x, s = y[..., 0], y[..., 1]
    return torch.stack([0.8 * x * s - 0.1 * x, -0.8 * x * s + 0.1 * (1.0 - s)], dim=-1)


def truth(x):  # Monod saturation of the uptake: 0.8 x s / (0.5 + s) instead of 0.8 x s
    xx, s = x[..., 0], x[..., 1]
    d = 0.8 * xx * s * (1.0 / (0.5 + s) - 1.0)
    return torch.stack([d, -d], dim=-1)


def chemostat(with_truth=False):
    return tms.MisspecifiedSystem(known, 2, correction=truth if with_truth else None, name="chemostat")


def three_states():  # not the system the model was fitted with
    return tms.MisspecifiedSystem(lambda y: -y, 3, name="decay3")
"""


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A lab's CSV (columns run, hour, biomass, substrate; ragged, irregular hours, 2 % noise) of a chemostat the
    package does not ship, the file that declares its known model, initial conditions and candidates."""
    import importlib.util

    folder = tmp_path_factory.mktemp("lab")
    (folder / "chemostat.py").write_text(LAB_SYSTEM)
    spec = importlib.util.spec_from_file_location("chemostat_truth", folder / "chemostat.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    truth = module.chemostat(True)
    g = torch.Generator().manual_seed(5)
    lines = ["run,hour,biomass,substrate"]
    for k in range(6):
        n = int(torch.randint(8, 16, (1,), generator=g))
        hours = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 20).values
        hours[0] = 0.0
        y0 = torch.tensor([0.1, 0.3], dtype=torch.float64) + 0.6 * torch.rand(2, generator=g, dtype=torch.float64)
        states = tms.simulate(truth, y0[None], hours).states[0]
        states = states * (1 + 0.02 * torch.randn(states.shape, generator=g, dtype=torch.float64))
        lines += [f"r{k},{t:.3f},{a:.5g},{b:.5g}" for t, (a, b) in zip(hours.tolist(), states.tolist(), strict=True)]
    (folder / "lab.csv").write_text("\n".join(lines) + "\n")
    (folder / "initial.csv").write_text("run,biomass,substrate\nlean,0.2,0.8\nrich,0.5,0.4\n")
    (folder / "candidates.csv").write_text(  # the columns in another order: read by name
        "substrate,biomass\n" + "\n".join(f"{b:.2f},{a:.2f}" for a in (0.1, 0.4, 0.7) for b in (0.2, 0.5, 0.9)) + "\n"
    )
    return folder


def _lab(folder, command, *extra):
    """A command on the lab's files, with the lab's column names (the same options for every command)."""
    columns = ("--time-column", "hour", "--experiment-column", "run")
    data = ("--data", str(folder / "lab.csv")) if command in ("fit", "calibrate") else ()
    return [command, "--system", f"{folder / 'chemostat.py'}:chemostat", "--quiet", *data, *columns, *extra]


@pytest.fixture(scope="module")
def lab_model(lab):
    """A model of the lab's data, fitted without calibration (the error tests need a model, not its bands)."""
    path = lab / "uncalibrated.pt"
    assert main(_lab(lab, "fit", "--no-calibrate", "--out", str(path))) == 0
    return path


def _table(path):
    lines = path.read_text().splitlines()
    return lines[0].split(","), [line.split(",") for line in lines[1:]]


def test_the_loop_on_a_lab_file(lab, tmp_path, capsys):
    """fit -> calibrate -> predict -> design --model, with the defaults, on a lab's file and a user's system: the
    files a spreadsheet opens (columns in the lab's names, bands ordered), the figure, the calibration carried."""
    model = tmp_path / "model.pt"
    assert main(_lab(lab, "fit", "--out", str(model))) == 0
    out = capsys.readouterr().out
    assert "cross-validation" in out and "calibrated bands: BandCalibration(" in out and str(model) in out
    saved = tms.CorrectionGP.load(model)
    assert saved.input_names_ == ("biomass", "substrate")
    assert saved.system_ == {
        "name": "chemostat",
        "state_dim": 2,
        "correction_inputs": [0, 1],
        "correction_outputs": [0, 1],
    }
    recalibrated = tmp_path / "recalibrated.pt"
    args = ("--model", str(model), "--state-noise", "2%", "--level", "0.8", "--out", str(recalibrated))
    assert main(_lab(lab, "calibrate", *args)) == 0
    assert "calibrated bands: BandCalibration(" in capsys.readouterr().out
    calibration = tms.CorrectionGP.load(recalibrated).calibration_
    assert calibration is not None and calibration.level == pytest.approx(0.8)

    pred, figure = tmp_path / "pred.csv", tmp_path / "pred.png"
    args = ("--model", str(recalibrated), "--initial", str(lab / "initial.csv"), "--times", "0:20:11")
    assert main(_lab(lab, "predict", *args, "--out", str(pred), "--figure", str(figure))) == 0
    captured = capsys.readouterr()
    assert f"calibrated (scale {calibration.scale:.3g}" in captured.out and "NOT calibrated" not in captured.out
    assert all(line.startswith("torchmisspec predict: warning: ") for line in captured.err.splitlines())
    assert "not calibrated" not in captured.err
    header, rows = _table(pred)
    assert header == ["run", "hour"] + [
        f"{s}_{k}" for s in ("biomass", "substrate") for k in ("mean", "lower", "upper")
    ]
    assert len(rows) == 22 and [r[0] for r in rows[::11]] == ["lean", "rich"]  # the initial file's labels
    values = np.array([[float(v) for v in r[1:]] for r in rows])
    assert values[:11, 0].tolist() == pytest.approx(np.linspace(0, 20, 11).tolist())
    assert values[[0, 11], 1].tolist() == [0.2, 0.5] and values[[0, 11], 4].tolist() == [0.8, 0.4]  # from y0
    for j in (1, 4):  # lower <= mean <= upper, and the band opens after t = 0
        assert (values[:, j + 1] <= values[:, j] + 1e-12).all() and (values[:, j] <= values[:, j + 2] + 1e-12).all()
        assert (values[1:, j + 2] - values[1:, j + 1]).max() > 0
    assert figure.read_bytes()[:4] == b"\x89PNG"

    picks = tmp_path / "next.csv"
    args = ("--candidates", str(lab / "candidates.csv"), "--times", "0:20:11", "--budget", "2")
    assert main(_lab(lab, "design", *args, "--model", str(recalibrated), "--out", str(picks))) == 0
    header, rows = _table(picks)
    assert header == ["order", "index", "gain", "biomass", "substrate"] and len(rows) == 2
    candidates = np.loadtxt(lab / "candidates.csv", delimiter=",", skiprows=1)
    for row in rows:  # the picked points are the candidates, in the system's order
        assert [float(row[3]), float(row[4])] == candidates[int(row[1])][::-1].tolist()


def test_predict_without_calibration_says_so_on_stderr(lab, lab_model, tmp_path, capsys):
    pred = tmp_path / "p.csv"
    args = ("--model", str(lab_model), "--initial", str(lab / "initial.csv"), "--times", "0,5,10", "--samples", "8")
    assert main(_lab(lab, "predict", *args, "--out", str(pred))) == 0
    captured = capsys.readouterr()
    assert "NOT calibrated" in captured.out
    lines = captured.err.strip().splitlines()  # one line per warning (the library's may come first)
    assert all(line.startswith("torchmisspec predict: warning: ") for line in lines)
    assert lines[-1].startswith("torchmisspec predict: warning: the model's bands are not calibrated")
    assert len(_table(pred)[1]) == 6


def test_predict_and_design_refuse_states_named_otherwise_than_the_model(lab, lab_model, tmp_path, capsys):
    """A model fitted on (biomass, substrate) and an initial file whose columns are other names: refused, not
    silently taken in file order; --state-columns picks the right columns by name."""
    (tmp_path / "renamed.csv").write_text("a,b\n0.2,0.8\n")
    (tmp_path / "extra.csv").write_text("note,substrate,biomass,ph\n1,0.8,0.2,7\n")
    base = ("--model", str(lab_model), "--times", "0:10:3", "--samples", "8")
    assert (
        main(_lab(lab, "predict", *base, "--initial", str(tmp_path / "renamed.csv"), "--out", str(tmp_path / "p.csv")))
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "fitted on states named ['biomass', 'substrate'], but the columns give ['a', 'b']" in err and "\n" not in err
    extra = ("--initial", str(tmp_path / "extra.csv"), "--state-columns", "biomass,substrate")
    assert main(_lab(lab, "predict", *base, *extra, "--out", str(tmp_path / "p.csv"))) == 0
    header, rows = _table(tmp_path / "p.csv")
    assert header[2] == "biomass_mean" and float(rows[0][2]) == 0.2 and float(rows[0][5]) == 0.8
    # every state by its name: the other columns are not states; one of them (a lab's sample IDs) labels the rows
    (tmp_path / "ids.csv").write_text("culture,substrate,biomass\nA7,0.8,0.2\n")
    assert (
        main(_lab(lab, "predict", *base, "--initial", str(tmp_path / "ids.csv"), "--out", str(tmp_path / "q.csv"))) == 0
    )
    header, rows = _table(tmp_path / "q.csv")
    assert rows[0][0] == "A7" and float(rows[0][2]) == 0.2 and float(rows[0][5]) == 0.8
    # other extra columns are refused, not silently left out (a data file given by mistake, time column named otherwise)
    (tmp_path / "data.csv").write_text("sample,minute,substrate,biomass\nA7,0.0,0.8,0.2\nA7,1.5,0.7,0.3\n")
    capsys.readouterr()
    said = {"extra.csv": "expected 2 states per row", "data.csv": "expected a number in every state column"}
    for wrong, message in said.items():
        args = ("--initial", str(tmp_path / wrong), "--out", str(tmp_path / "r.csv"))
        assert main(_lab(lab, "predict", *base, *args)) == 2
        assert message in capsys.readouterr().err
    design = ("--candidates", str(tmp_path / "renamed.csv"), "--times", "0:10:3", "--budget", "1")
    assert main(_lab(lab, "design", "--model", str(lab_model), *design, "--out", str(tmp_path / "d.csv"))) == 2
    assert "the columns give ['a', 'b']" in capsys.readouterr().err


def test_times_from_a_file(lab, lab_model, tmp_path):
    (tmp_path / "hours.csv").write_text("hour\n0\n2.5\n7\n")
    args = ("--model", str(lab_model), "--initial", str(lab / "initial.csv"), "--samples", "8")
    assert (
        main(_lab(lab, "predict", *args, "--times", str(tmp_path / "hours.csv"), "--out", str(tmp_path / "p.csv"))) == 0
    )
    assert [float(r[1]) for r in _table(tmp_path / "p.csv")[1]][:3] == [0.0, 2.5, 7.0]


COMMANDS = ["fit", "calibrate", "predict", "design", "demo"]
PROBLEMS = {  # problem -> the message's telling part (per command where it differs)
    "missing column": "missing ['oxygen']",
    "ragged data, missing column": "missing ['oxygen']",
    "binary data": "could not be read",
    "bad system": "expected an importable module",
    "system file raises": "got ZeroDivisionError: division by zero when importing it",
    "mismatched system and model": {
        "fit": "expected state dimension 3 of system 'decay3'",
        "calibrate": "pass the system it was fitted with",
        "predict": "pass the system it was fitted with",
        "design": "pass the system it was fitted with",
    },
    "another system of the same shape": "corrects system 'chemostat' (2 states), but 'paper_linear' (2 states)",
    "unwritable output": "cannot write '/proc/x",
    "not a model": "expected a CorrectionGP file",
    "a CSV as the model": "expected a CorrectionGP file",
    "interrupted": "interrupted; nothing more was written",
    "usage": {c: "the following arguments are required" for c in COMMANDS} | {"demo": "unrecognized arguments"},
}


def _args_with(problem, command, lab, model, tmp_path):
    """The command on the lab's files, with ``problem`` in its inputs; None where the command has no such input."""
    (tmp_path / "binary.csv").write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe" * 8)
    (tmp_path / "text.pt").write_text("not a model\n")
    (tmp_path / "raises.py").write_text("1 / 0\n")
    model = {"not a model": tmp_path / "text.pt", "a CSV as the model": lab / "lab.csv"}.get(problem, model)
    out = "/proc/x" if problem == "unwritable output" else str(tmp_path / "out")
    times = ("--times", "0:20:5")
    args = {
        "fit": _lab(lab, "fit", "--no-calibrate", "--out", out + ".pt"),
        "calibrate": _lab(lab, "calibrate", "--model", str(model), "--out", out + ".pt"),
        "predict": _lab(lab, "predict", "--model", str(model), "--initial", str(lab / "initial.csv"), *times,
                        "--out", out + ".csv", "--samples", "4"),
        "design": _lab(lab, "design", "--model", str(model), "--candidates", str(lab / "candidates.csv"), *times,
                       "--budget", "1", "--out", out + ".csv"),
        "demo": ["demo", "--quiet", "--n-train", "3", "--n-test", "2", "--out", out],
    }[command]  # fmt: skip
    if command == "demo" and problem not in ("unwritable output", "interrupted", "usage"):
        return None  # the demo reads nothing
    if problem in ("missing column", "ragged data, missing column"):  # lab.csv is ragged
        if problem == "ragged data, missing column" and command not in ("fit", "calibrate"):
            return None
        args += ["--state-columns", "biomass,oxygen"]
    elif problem == "binary data":
        key = {"predict": "--initial", "design": "--candidates"}.get(command, "--data")
        args[args.index(key) + 1] = str(tmp_path / "binary.csv")
    elif problem == "bad system":
        args[args.index("--system") + 1] = "no_such_lab_module:chemostat"
    elif problem == "system file raises":
        args[args.index("--system") + 1] = f"{tmp_path / 'raises.py'}:chemostat"
    elif problem == "mismatched system and model":
        args[args.index("--system") + 1] = f"{lab / 'chemostat.py'}:three_states"
    elif problem == "another system of the same shape":  # the model file records the system it corrects
        if command == "fit":
            return None
        args[args.index("--system") + 1] = "paper_linear"
    elif problem in ("not a model", "a CSV as the model") and command == "fit":
        return None  # reads no model
    elif problem == "usage":
        args = [command, "--no-such-option"] if command == "demo" else [command, "--quiet"]
    return args


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("problem", list(PROBLEMS))
def test_every_command_fails_with_one_line_and_exit_2(lab, lab_model, tmp_path, capsys, monkeypatch, command, problem):
    """No traceback reaches the user: each class of error, for every command, is one line on stderr, exit 2."""
    args = _args_with(problem, command, lab, lab_model, tmp_path)
    if args is None:
        pytest.skip(f"{command} has no such input")
    if problem == "interrupted":  # Ctrl-C in the middle of the work

        def interrupt(*a, **k):
            raise KeyboardInterrupt

        monkeypatch.setattr(tms.systems, "load_system", interrupt)
        monkeypatch.setattr("torchmisspec.paper.demo.linear_demo", interrupt)
    capsys.readouterr()
    assert main(args) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    message = PROBLEMS[problem] if isinstance(PROBLEMS[problem], str) else PROBLEMS[problem][command]
    assert err.startswith(f"torchmisspec {command}: ") and message in err, err
    assert "\n" not in err and "Traceback" not in err + captured.out
    assert not [p for p in tmp_path.rglob("out*") if p.is_file()], "an output was written although the command failed"


@pytest.mark.slow
def test_the_command_line_page_runs_on_the_lab_files(lab, tmp_path, monkeypatch, capsys):
    """docs/tutorials/command-line.md: its commands, run as written on files like the page's (the same columns,
    initial file and system), succeed and write what the page says."""
    import re
    import shlex
    import shutil
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "tutorials" / "command-line.md").read_text()
    commands = [c.replace("\\\n", " ") for c in re.findall(r"^```bash\n(.*?)^```", page, re.S | re.M)]
    assert [shlex.split(c)[1] for c in commands] == ["fit", "calibrate", "predict", "design"]
    for name in ("lab.csv", "chemostat.py", "initial.csv", "candidates.csv"):
        shutil.copy(lab / name, tmp_path / name)
    assert "run,biomass,substrate\nlean,0.2,0.8\nrich,0.5,0.4\n" in page  # the page's initial.csv is the test's
    monkeypatch.chdir(tmp_path)
    for command in commands:
        assert main([*shlex.split(command)[1:], "--quiet"]) == 0, command
    header = (tmp_path / "prediction.csv").read_text().splitlines()[0]
    assert header.startswith("run,hour,biomass_mean,biomass_lower,biomass_upper,substrate_mean,")
    assert (tmp_path / "prediction.png").is_file() and (tmp_path / "next.csv").is_file()
    assert "calibrated (scale" in capsys.readouterr().out


def test_candidates_with_an_unnamed_state_in_another_column_order(tmp_path, capsys):
    """A 3-state system whose correction reads 2 named states (as the trial's SIR): a candidates file with the
    columns R, S, I is read by name, the one column left being the third state."""
    system_file = tmp_path / "sir.py"
    system_file.write_text(
        "import torch\nimport torchmisspec as tms\n\n"
        "def known(y):\n    s, i = y[..., 0], y[..., 1]\n"
        "    return torch.stack([-0.5 * s * i, 0.5 * s * i - 0.1 * i, 0.1 * i], dim=-1)\n\n"
        "def sir():\n    return tms.MisspecifiedSystem(known, 3, correction_inputs=[0, 1], correction_outputs=[0, 1], "
        "name='sir')\n"
    )
    inputs = torch.tensor([[0.5, 0.1], [0.7, 0.2]], dtype=torch.float64)
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=1e-3, noise_variance=1e-6).fit(inputs, torch.zeros_like(inputs))
    gp.input_names_ = ("S", "I")
    gp.save(tmp_path / "m.pt")
    (tmp_path / "c.csv").write_text("R,S,I\n0.1,0.8,0.05\n0.2,0.6,0.3\n")
    args = ["design", "--system", f"{system_file}:sir", "--candidates", str(tmp_path / "c.csv"), "--times", "0:10:5"]
    assert (
        main([*args, "--budget", "2", "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "d.csv"), "--quiet"])
        == 0
    )
    header, rows = _table(tmp_path / "d.csv")
    assert header == ["order", "index", "gain", "S", "I", "R"]
    by_index = {int(r[1]): [float(v) for v in r[-3:]] for r in rows}
    assert by_index == {0: [0.8, 0.05, 0.1], 1: [0.6, 0.3, 0.2]}


def test_design_with_data_reads_the_candidates_by_the_data_names(lab, tmp_path):
    """design --data: the candidates file (columns substrate, biomass) is read by the data's names, before the fit."""
    out = tmp_path / "next.json"
    args = ("--candidates", str(lab / "candidates.csv"), "--times", "0:20:5", "--budget", "1", "--out", str(out))
    assert main(_lab(lab, "design", "--data", str(lab / "lab.csv"), *args)) == 0
    picked = json.loads(out.read_text())
    candidates = np.loadtxt(lab / "candidates.csv", delimiter=",", skiprows=1)
    point = picked["points"][0]
    assert [point["biomass"], point["substrate"]] == candidates[picked["indices"][0]][::-1].tolist()


# ------------------------------------------------------------------- issue 40: the command line's independent sweep
NAMED = """
import sys
import torch
import torchmisspec as tms


def known(y):
    x, s = y[..., 0], y[..., 1]
    return torch.stack([0.8 * x * s - 0.1 * x, -0.8 * x * s + 0.1 * (1.0 - s)], dim=-1)


def named():
    return tms.MisspecifiedSystem(known, 2, state_names=["X", "S"], name="named")


def unnamed():
    return tms.MisspecifiedSystem(known, 2, name="unnamed")


def one_output():  # G returns one column for two states
    return tms.MisspecifiedSystem(lambda y: y[..., :1], 2, state_names=["X", "S"], name="one_output")


def exits():
    sys.exit("run me as python named.py")


def known_u(t, y, u):
    return known(y) - u[..., :1] * y


def dilution():
    return tms.MisspecifiedSystem(known_u, 2, state_names=["X", "S"], num_controls=1, control_names=["D"])
"""


@pytest.fixture(scope="module")
def named_lab(tmp_path_factory):
    """A system naming its states (X, S), a lab table of it (run, hour, X, S, ph), initial states and a model of it
    (conditioned directly: these tests are about reading files, not fitting)."""
    from torchmisspec.cli._common import describe_system

    folder = tmp_path_factory.mktemp("named")
    (folder / "named.py").write_text(NAMED)
    namespace: dict = {}
    exec(NAMED, namespace)
    system = namespace["named"]()
    y0 = torch.tensor([[0.2, 0.8], [0.5, 0.4], [0.35, 0.6], [0.6, 0.2]], dtype=torch.float64)
    data = tms.simulate(system, y0, torch.linspace(0, 5, 6, dtype=torch.float64))
    lines = ["run,hour,X,S,ph"]
    for k, (t, y) in enumerate(data.experiments()):
        lines += [f"r{k},{float(t[i])!r},{float(y[i, 0])!r},{float(y[i, 1])!r},7" for i in range(len(t))]
    (folder / "lab.csv").write_text("\n".join(lines) + "\n")
    inputs = data.states.reshape(-1, 2)
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=1e-3, noise_variance=1e-6).fit(inputs, 0.01 * inputs**2)
    gp.input_names_ = ("X", "S")
    gp.system_ = describe_system(system)
    gp.save(folder / "model.pt")
    (folder / "initial.csv").write_text("run,X,S\nlean,0.2,0.8\nrich,0.5,0.4\n")
    return folder


def _predict(folder, initial, out, *extra):
    return [
        "predict", "--model", str(folder / "model.pt"), "--system", f"{folder / 'named.py'}:named", "--initial",
        str(initial), "--times", "0:5:3", "--samples", "4", "--experiment-column", "run", "--out", str(out),
        "--quiet", *extra,
    ]  # fmt: skip


def _one_error_line(capsys, command: str) -> str:
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if ": warning: " not in line]
    assert len(lines) == 1 and lines[0].startswith(f"torchmisspec {command}: error: "), captured.err
    assert "Traceback" not in captured.out + captured.err and "internal error" not in captured.err
    return lines[0]


INITIAL_FILES = {  # a lab's table of initial states as spreadsheets and editors write it: read as the plain CSV
    "bom.csv": ("\ufeffrun,X,S\nlean,0.2,0.8\nrich,0.5,0.4\n", ["lean", "rich"]),
    "bom_no_header.csv": ("\ufeff0.2,0.8\n0.5,0.4\n", ["0", "1"]),
    "quoted.csv": ('"run","X","S"\n"lean","0.2","0.8"\n"rich","0.5","0.4"\n', ["lean", "rich"]),
    "quoted_comma.csv": ('run,X,S\n"lean, fed",0.2,0.8\nrich,0.5,0.4\n', ["lean, fed", "rich"]),
    "spaces.txt": ("run X S\nlean 0.2 0.8\nrich   0.5 0.4\n", ["lean", "rich"]),
    "spaces_no_header.txt": ("0.2 0.8\n0.5 0.4\n", ["0", "1"]),
    "tabs.tsv": ("run\tS\tX\nlean\t0.8\t0.2\nrich\t0.4\t0.5\n", ["lean", "rich"]),
    "crlf.csv": ("run,X,S\r\nlean,0.2,0.8\r\nrich,0.5,0.4\r\n", ["lean", "rich"]),
    "trailing_comma.csv": ("run,X,S,\nlean,0.2,0.8,\nrich,0.5,0.4,\n", ["lean", "rich"]),
}


@pytest.mark.parametrize("name", list(INITIAL_FILES))
def test_initial_states_in_any_lab_table_format_give_the_same_prediction(named_lab, tmp_path, name):
    """--initial with a byte-order mark, quoted cells, a .txt separated by spaces, a trailing comma: read as the
    plain CSV is (they were refused, or read with the mark in a column name), the same prediction."""
    content, labels = INITIAL_FILES[name]
    (tmp_path / name).write_text(content, encoding="utf-8", newline="")
    assert main(_predict(named_lab, named_lab / "initial.csv", tmp_path / "ref.csv")) == 0
    assert main(_predict(named_lab, tmp_path / name, tmp_path / "got.csv")) == 0
    ref, got = _csv(tmp_path / "ref.csv"), _csv(tmp_path / "got.csv")
    assert got[0] == ref[0] and [r[1:] for r in got[1:]] == [r[1:] for r in ref[1:]]
    assert [r[0] for r in got[1::3]] == labels


def _csv(path) -> list[list[str]]:
    import csv

    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def test_candidates_with_a_byte_order_mark_or_spaces_are_read_by_name(named_lab, tmp_path):
    (tmp_path / "bom.csv").write_text("\ufeffS,X\n0.8,0.2\n0.4,0.5\n0.3,0.3\n", encoding="utf-8")
    (tmp_path / "spaces.txt").write_text("X S\n0.2 0.8\n0.5 0.4\n0.3 0.3\n")
    base = ["design", "--system", f"{named_lab / 'named.py'}:named", "--model", str(named_lab / "model.pt")]
    base += ["--times", "0:5:3", "--budget", "3", "--quiet"]
    for name in ("bom.csv", "spaces.txt"):
        assert main([*base, "--candidates", str(tmp_path / name), "--out", str(tmp_path / "d.csv")]) == 0
        header, rows = _table(tmp_path / "d.csv")
        assert header == ["order", "index", "gain", "X", "S"]
        assert sorted((float(r[3]), float(r[4])) for r in rows) == [(0.2, 0.8), (0.3, 0.3), (0.5, 0.4)]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("run,X,S\nlean,0.2,0.8,9\nrich,0.5,0.4\n", "expected 3 cells in every row (as in the first), got 4 on line 2"),
        ("0.2,0.8\n0.5\n", "expected 2 cells in every row (as in the first), got 1 on line 2"),
    ],
)
def test_initial_rows_of_another_length_than_the_header_are_refused(named_lab, tmp_path, capsys, content, message):
    """A row with a cell more than the header was read with the cell dropped (exit 0)."""
    (tmp_path / "rows.csv").write_text(content)
    assert main(_predict(named_lab, tmp_path / "rows.csv", tmp_path / "p.csv")) == 2
    assert message in _one_error_line(capsys, "predict")
    assert not (tmp_path / "p.csv").exists()


def test_initial_states_of_another_format_are_refused_by_their_suffix(named_lab, tmp_path, capsys):
    """A .json file was read as text: 'expected at least one row of states, got none'."""
    (tmp_path / "initial.json").write_text("[[0.2, 0.8]]")
    assert main(_predict(named_lab, tmp_path / "initial.json", tmp_path / "p.csv")) == 2
    assert "--initial: expected a .csv, .tsv, .txt, .npz or .npy file" in _one_error_line(capsys, "predict")


@pytest.mark.parametrize("spec", ["exits.py:named", "named.py:exits"])
def test_a_system_file_that_calls_exit_is_one_line_and_exit_2(named_lab, tmp_path, capsys, spec):
    """sys.exit() in the --system file (at import or in its function) escaped main as SystemExit."""
    (tmp_path / "exits.py").write_text("import sys\nsys.exit(0)\n")
    (tmp_path / "named.py").write_text(NAMED)
    args = ["fit", "--data", str(named_lab / "lab.csv"), "--system", str(tmp_path / spec), "--time-column", "hour"]
    assert main([*args, "--experiment-column", "run", "--out", str(tmp_path / "m.pt"), "--quiet"]) == 2
    line = _one_error_line(capsys, "fit")
    assert "--system: expected the system's code to return, got SystemExit" in line and "sys.exit" in line


def _fit(folder, *extra, system="named"):
    return [
        "fit", "--data", str(folder / "lab.csv"), "--system", f"{folder / 'named.py'}:{system}", "--time-column",
        "hour", "--experiment-column", "run", "--quiet", "--no-calibrate", "--derivative", "central", *extra,
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("extra", "system", "message"),
    [
        (
            ("--state-columns", "hour,X"),
            "named",
            "--state-columns: expected the columns of the states, got 'hour', the --time-column",
        ),
        (
            ("--state-columns", "X,run"),
            "named",
            "--state-columns: expected the columns of the states, got 'run', the --experiment-column",
        ),
        (
            ("--input-columns", "ph"),
            "named",
            "--input-columns: expected no input columns (system 'named' has no "
            "inputs u(t)), got ['ph']; drop --input-columns",
        ),
        (
            ("--input-columns", "ph,X"),
            "dilution",
            "--input-columns: expected 1 column(s), one per input of system 'system' (D), got ['ph', 'X']",
        ),
        (
            ("--input-columns", "hour"),
            "dilution",
            "--input-columns: expected the columns of the inputs, got 'hour', the --time-column",
        ),
        (
            ("--readout", "hour = X + S"),
            "named",
            "--readout: expected a reading named apart from the table's other columns, got 'hour', the --time-column",
        ),
        (
            ("--readout", "total = y0 + y1"),
            "unnamed",
            "--readout: system 'unnamed' names no states, so its state "
            "columns cannot be found by name: expected --state-columns naming them in the system's order, got columns "
            "['X', 'S', 'ph'] that would be left out",
        ),
        (("--level", "0"), "named", "--level: expected a band's coverage in (0, 1), got 0.0"),
        (("--state-noise", "-1"), "named", "--state-noise: expected standard deviations >= 0 (finite), got -1.0"),
        (
            ("--state-noise", "nan%"),
            "named",
            "--state-noise: expected a percentage >= 0 (finite), such as 2%, got 'nan%'",
        ),
        (
            ("--state-noise", "0.1,0.2,0.3"),
            "named",
            "--state-noise: expected one standard deviation or 2 (one per state of system 'named'), got 3",
        ),
    ],
)
def test_fit_options_are_checked_before_the_fit_naming_the_option(
    named_lab, tmp_path, capsys, monkeypatch, extra, system, message
):
    """Each was refused by a deeper check naming a Python argument or another problem ('hour,X names the system's
    states in another order ... pass them in that order (X)'; 'estimate_initial_states: the right-hand side is not
    finite ... check G and F' for a readout of a system naming no states), or after the fit (--level 0)."""

    def never(*args, **kwargs):
        raise AssertionError("the fit ran although an option is wrong")

    monkeypatch.setattr("torchmisspec.learning.Pipeline.fit", never)
    assert main(_fit(named_lab, *extra, "--out", str(tmp_path / "m.pt"), system=system)) == 2
    assert message in _one_error_line(capsys, "fit")


def test_a_value_starting_with_a_dash_is_given_with_an_equals_sign(named_lab, tmp_path, capsys):
    args = _predict(named_lab, named_lab / "initial.csv", tmp_path / "p.csv")
    args[args.index("0:5:3")] = "-5:0:3"
    assert main(args) == 2
    line = _one_error_line(capsys, "predict")
    assert "argument --times: expected one argument" in line and "write --times=-5:0:3" in line


def test_a_times_file_that_does_not_exist_is_named_so(named_lab, tmp_path, capsys):
    args = _predict(named_lab, named_lab / "initial.csv", tmp_path / "p.csv")
    args[args.index("0:5:3")] = str(tmp_path / "hours.csv")
    assert main(args) == 2
    assert f"--times: expected an existing file of times, got '{tmp_path / 'hours.csv'}'" in _one_error_line(
        capsys, "predict"
    )


def test_capacities_name_each_region_once(tmp_path, candidates_csv, capsys):
    """'0=1,0=2,1=1' silently used 0=2."""
    labels = tmp_path / "labels.csv"
    np.savetxt(labels, (np.arange(49) % 2)[:, None], fmt="%d")
    args = _design_args(candidates_csv, tmp_path / "p.json", "--partition", str(labels), "--capacities", "0=1,0=2,1=1")
    assert main(args) == 2
    assert "--capacities: expected each region label once, got 0 twice in '0=1,0=2,1=1'" in _one_error_line(
        capsys, "design"
    )


def test_the_demo_refuses_an_empty_output_folder(tmp_path, capsys, monkeypatch):
    """--out '' wrote into the working folder and said 'numbers: /results.json'."""
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--out", "", "--quiet", "--n-train", "2", "--n-test", "1"]) == 2
    assert "--out: expected a folder name, got ''" in _one_error_line(capsys, "demo")
    assert not list(tmp_path.iterdir())


def test_a_G_of_the_wrong_shape_is_refused_by_fit(named_lab, tmp_path, capsys):
    """The Python API and 'design' refuse it ('G returned shape (24, 1) ...'); 'fit' on states of order 1e-3 (fitted
    in the data's units) exited 0 with a model."""
    header, rows = _table(named_lab / "lab.csv")
    lines = [",".join(header)] + [",".join([r[0], r[1], *(repr(1e-3 * float(v)) for v in r[2:4]), r[4]]) for r in rows]
    (tmp_path / "lab.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "named.py").write_text(NAMED)
    assert main(_fit(tmp_path, "--out", str(tmp_path / "m.pt"), system="one_output")) == 2
    assert "returned shape" in _one_error_line(capsys, "fit")


@pytest.mark.parametrize("command", ["predict", "design"])
def test_input_columns_for_a_system_without_inputs_are_refused_by_every_command(named_lab, tmp_path, capsys, command):
    """fit refused them; predict and design left the option unread (exit 0)."""
    if command == "predict":
        args = _predict(named_lab, named_lab / "initial.csv", tmp_path / "p.csv", "--input-columns", "ph")
    else:
        args = ["design", "--system", f"{named_lab / 'named.py'}:named", "--model", str(named_lab / "model.pt")]
        args += ["--candidates", str(named_lab / "initial.csv"), "--times", "0:5:3", "--budget", "1", "--quiet"]
        args += ["--input-columns", "ph", "--out", str(tmp_path / "d.csv")]
    assert main(args) == 2
    assert "--input-columns: expected no input columns (system 'named' has no inputs u(t)), got ['ph']" in (
        _one_error_line(capsys, command)
    )


def test_predict_gives_the_band_of_new_measurements_from_the_saved_noise(lab, lab_model, tmp_path, capsys):
    """Issue 41 (noise as measured, in the CLI): the model file keeps the fit's noise model and scale, and
    --measurements writes the band that new measurements fall in (the states' band with that noise added: wider);
    a model file without them is refused with the fix."""
    saved = tms.CorrectionGP.load(lab_model)
    assert saved.noise_ is not None and saved.noise_scale_ is not None and bool((saved.noise_scale_ > 0).all())
    base = ("--model", str(lab_model), "--initial", str(lab / "initial.csv"), "--times", "0,5,10", "--samples", "32")
    states, measured = tmp_path / "states.csv", tmp_path / "measured.csv"
    assert main(_lab(lab, "predict", *base, "--out", str(states))) == 0
    assert main(_lab(lab, "predict", *base, "--measurements", "--out", str(measured))) == 0
    out = capsys.readouterr().out
    assert f"band of new measurements ({saved.noise_.name} noise" in out
    (header, rows), (header2, rows2) = _table(states), _table(measured)
    assert header == header2
    for name in ("biomass", "substrate"):  # wider on average after the initial state (the draws are random)
        hi, lo = header.index(f"{name}_upper"), header.index(f"{name}_lower")
        later = [(r, r2) for r, r2 in zip(rows, rows2, strict=True) if float(r[1]) > 0]
        plain = sum(float(r[hi]) - float(r[lo]) for r, _ in later)
        noisy = sum(float(r2[hi]) - float(r2[lo]) for _, r2 in later)
        assert noisy > 1.05 * plain, (name, noisy, plain)
    bare = tmp_path / "bare.pt"
    tms.CorrectionGP().fit(saved.train_inputs_, saved.train_targets_).save(bare)
    assert main(_lab(lab, "predict", "--model", str(bare), *base[2:], "--measurements", "--out", str(measured))) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--measurements: expected a model file written by 'fit'" in err


def test_a_warning_repeated_by_the_library_reaches_the_user_once(capsys):
    """A population's fits can each give the same warning: the command prints each text once, on one line."""
    import warnings
    from functools import partial

    from torchmisspec.cli import _warning_line

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = partial(_warning_line, "population", set())
        for text in ("EM did not settle", "EM did not settle", "another"):
            warnings.warn(text, UserWarning, stacklevel=1)
    assert capsys.readouterr().err.splitlines() == [
        "torchmisspec population: warning: EM did not settle",
        "torchmisspec population: warning: another",
    ]


def test_predict_says_where_the_band_of_a_positive_state_goes_below_zero():
    """Relative or count noise measures a state as positive: a band's lower edge below 0 is said, with the state and
    its first such time; under additive noise, or with the edge at or above 0, nothing is."""
    from types import SimpleNamespace

    from torchmisspec.cli._predict import below_zero
    from torchmisspec.noise import Additive, Counts, Relative

    times = torch.tensor([0.0, 1.0, 2.0, 4.0], dtype=torch.float64)
    lower = torch.tensor([[[1.0, 3.0], [0.5, 2.0], [-0.01, 1.0], [-0.02, 0.5]]], dtype=torch.float64)
    said = below_zero(SimpleNamespace(noise_=Relative()), lower, times, ["conc", "cells"])
    assert "lower edge goes below 0 (conc from t = 2)" in said and "cells" not in said and "'relative'" in said
    assert "(y1 from t = 2)" in below_zero(SimpleNamespace(noise_=Counts()), lower.flip(-1), times, None)
    assert below_zero(SimpleNamespace(noise_=Additive()), lower, times, ["conc", "cells"]) == ""
    assert below_zero(SimpleNamespace(noise_=Relative()), lower.abs(), times, ["conc", "cells"]) == ""
