"""The whole loop as a user runs it, with defaults only, on data the package does not simulate for its own studies:
a lab's CSV of a system written here (not shipped), columns in the lab's order, ragged times, multiplicative noise,
states of very different sizes (cells per mL ~1e4, nitrate ~1e-4 mol/L); through the Python API and the command
line; beside the classical answer (G's uncertain parameter fitted by least squares, F = 0); predictions beyond the
data's time span. And a public data set (R's Orange trees) with its model, leaving one tree out."""

from __future__ import annotations

import csv
import math
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec import cli, datasets

DT = torch.float64
K_N, MORTALITY, Q, DILUTION, N_IN = 2e-4, 0.1, 4e-8, 0.05, 1.5e-3

SYSTEM_FILE = textwrap.dedent(
    f"""
    import torch
    import torchmisspec as tms


    def culture(t, y, u, theta):  # phytoplankton P (cells/mL), nitrate N (mol/L), light L set by the lab
        P, N, L = y[..., 0], y[..., 1], u[..., 0]
        growth = theta[..., 0] * L * N / ({K_N} + N) * P
        return torch.stack([growth - {MORTALITY} * P, -{Q} * growth + {DILUTION} * ({N_IN} - N)], dim=-1)


    def plankton():
        return tms.MisspecifiedSystem(
            culture, 2, num_controls=1, control_names=["light"], state_names=["phyto", "nitrate"],
            parameters={{"mu": (1.0, 0.3)}}, correction_inputs=["phyto"], correction_outputs=["nitrate"],
            name="plankton",
        )
    """
)


def culture(t, y, u, theta):
    P, N, L = y[..., 0], y[..., 1], u[..., 0]
    growth = theta[..., 0] * L * N / (K_N + N) * P
    return torch.stack([growth - MORTALITY * P, -Q * growth + DILUTION * (N_IN - N)], dim=-1)


def _truth():
    theta = torch.tensor([0.8], dtype=DT)  # the lab's cells grow slower than the prior says ...
    return tms.MisspecifiedSystem(
        lambda t, y, u: culture(t, y, u, theta),
        2,
        num_controls=1,
        control_names=["light"],
        correction=lambda x: 2e-9 * x,  # ... and the cells recycle nitrate, which the model lacks
        correction_inputs=[0],
        correction_outputs=[1],
    )


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """The lab's CSV (columns culture, day, nitrate, light, phyto: not the model's order) and the system file."""
    folder = tmp_path_factory.mktemp("lab")
    g = torch.Generator().manual_seed(7)
    rows = []
    for k in range(7):
        days = torch.sort(torch.rand(8 + k % 4, generator=g, dtype=DT) * 20).values
        days[0] = 0.0
        y0 = torch.stack(
            [2e3 + 6e3 * torch.rand(1, generator=g, dtype=DT), 5e-4 + 1e-3 * torch.rand(1, generator=g)], -1
        )
        light = 0.4 + 0.6 * torch.rand(1, 1, 1, generator=g, dtype=DT)
        controls = tms.Controls(torch.zeros(1, dtype=DT), light, names=["light"])
        y = tms.simulate(_truth(), y0, days, controls=controls).states[0]
        y = y * torch.exp(0.03 * torch.randn(y.shape, generator=g, dtype=DT))
        for t, (P, N) in zip(days.tolist(), y.tolist(), strict=True):
            rows.append([f"C{k + 1}", repr(t), repr(N), repr(float(light)), repr(P)])
    path = folder / "lab.csv"
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows([["culture", "day", "nitrate", "light", "phyto"], *rows])
    (folder / "plankton.py").write_text(SYSTEM_FILE)
    return folder


def _system(folder):
    return tms.systems.load_system(f"{folder / 'plankton.py'}:plankton")


def _load(folder, **columns):
    return tms.Trajectories.load(
        folder / "lab.csv", time_column="day", experiment_column="culture", control_columns=["light"], **columns
    )


def _classical_mu(system, train) -> float:
    """The classical answer: mu by least squares on log values, F = 0, each culture from its first measurement."""
    from scipy.optimize import least_squares

    def residuals(p):
        s = system.at(torch.tensor(p, dtype=DT))
        out = []
        for k, (t, y) in enumerate(train.experiments()):
            sim = tms.simulate(s, y[:1], t, controls=train.controls[[k]], known_only=True).states[0]
            out.append((sim.log() - y.log()).flatten().numpy())
        return np.concatenate(out)

    return float(least_squares(residuals, [1.0]).x[0])


def _log_rmse(pred, y) -> float:
    return float((pred.log() - y.log()).pow(2).mean().sqrt())


@pytest.mark.slow
def test_a_lab_csv_with_columns_in_its_own_order_beats_the_classical_answer_and_forecasts(lab):
    system = _system(lab)
    observed = _load(lab, state_columns=["phyto", "nitrate"])  # by name: the file's order is nitrate, light, phyto
    with pytest.raises(tms.InputError, match=r"same names in another order"):
        tms.fit_correction(_load(lab, state_columns=["nitrate", "phyto"]), system, progress=False)
    experiments = observed.experiments()
    held_out = [0, 3]
    ratios = []
    for k in held_out:
        keep = [j for j in range(observed.num_experiments) if j != k]
        train = tms.Trajectories(
            [experiments[j][0] for j in keep],
            [experiments[j][1] for j in keep],
            state_names=observed.state_names,
            controls=observed.controls[keep],
        )
        gp = tms.fit_correction(train, system, progress=False)
        model = tms.CorrectedODE(system, gp)
        t, y = experiments[k]
        controls = observed.controls[[k]]
        default = _log_rmse(model.predict(y[:1], t, controls=controls)[0], y)
        mu = _classical_mu(system, train)
        classical = _log_rmse(tms.simulate(system.at(torch.tensor([mu])), y[:1], t, controls=controls).states[0], y)
        ratios.append(default / classical)
        beyond = torch.linspace(0.0, 2 * float(t[-1]), 21, dtype=DT)  # twice the data's time span
        forecast = model.predict(y[:1], beyond, controls=controls)
        assert bool(torch.isfinite(forecast).all()) and bool((forecast > 0).all())
    assert math.exp(np.mean(np.log(ratios))) <= 1.05, ratios


@pytest.mark.slow
def test_the_same_lab_csv_through_the_command_line(lab, capsys):
    folder = lab
    model = folder / "model.pt"
    code = cli.main(
        [
            "fit", "--data", str(folder / "lab.csv"), "--time-column", "day", "--experiment-column", "culture",
            "--input-columns", "light", "--system", f"{folder / 'plankton.py'}:plankton", "--out", str(model),
            "--no-calibrate", "--quiet",
        ]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    gp = tms.CorrectionGP.load(model)
    reference = tms.fit_correction(_load(folder, state_columns=["phyto", "nitrate"]), _system(folder), progress=False)
    x = torch.tensor([[5e3], [2e4]], dtype=DT)
    assert torch.allclose(gp.predict_mean(x), reference.predict_mean(x), rtol=1e-6, atol=0)
    (folder / "y0.csv").write_text("culture,nitrate,phyto\nnew,0.0009,4000\n")
    (folder / "light.csv").write_text("culture,day,light\nnew,0,0.7\n")
    out = folder / "pred.csv"
    code = cli.main(
        [
            "predict", "--model", str(model), "--system", f"{folder / 'plankton.py'}:plankton",
            "--initial", str(folder / "y0.csv"), "--controls", str(folder / "light.csv"), "--time-column", "day",
            "--experiment-column", "culture", "--times", "0:40:9", "--out", str(out), "--quiet",
        ]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    with out.open() as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 9 and table[0]["phyto_mean"] == "4000.0" and table[0]["nitrate_mean"] == "0.0009"
    values = np.array([[float(v) for k, v in row.items() if k.endswith(("mean", "lower", "upper"))] for row in table])
    assert np.isfinite(values).all() and (values > 0).all()


@pytest.fixture(scope="module")
def orange_folds():
    """R's Orange trees (Draper & Smith 1981), logistic growth with r and K uncertain: the defaults against r, K
    fitted by least squares on log values (F = 0), each predicting a held-out tree from its first measurement, and
    the defaults' forecast to three times the last age. ``(log-RMSE ratios default / classical, forecasts)``."""
    from torchmisspec.paper.real_data import classical_fit, classical_predict, log_rmse

    data = datasets.load("orange")
    experiments = data.trajectories.experiments()
    ratios, forecasts = [], []
    for k in (0, 4):
        keep = [j for j in range(len(experiments)) if j != k]
        train = tms.Trajectories([experiments[j][0] for j in keep], [experiments[j][1] for j in keep])
        train = train.with_state_names(data.trajectories.state_names)
        model = tms.CorrectedODE(data.system, tms.fit_correction(train, data.system, progress=False))
        t, y = experiments[k]
        theta, _ = classical_fit(data.system, train, data.noise)
        default, classical = model.predict(y[:1], t)[0], classical_predict(data.system, theta, y[0], t)
        ratios.append(log_rmse(default[1:], y[1:], data.noise) / log_rmse(classical[1:], y[1:], data.noise))
        forecasts.append(model.predict(y[:1], torch.linspace(float(t[0]), 3 * float(t[-1]), 16, dtype=DT)))
    return ratios, forecasts


@pytest.mark.slow
def test_a_public_data_set_fits_and_forecasts_with_the_defaults(orange_folds):
    ratios, forecasts = orange_folds
    assert all(math.isfinite(r) for r in ratios)
    assert all(bool(torch.isfinite(f).all()) and bool((f > 0).all()) for f in forecasts)


@pytest.mark.slow
def test_a_public_data_set_is_no_worse_than_the_classical_answer(orange_folds):
    """Issue 41, do no harm: 1.06x and 1.09x the classical log-RMSE on these two trees before the known model with
    its parameters fitted became a candidate of the default fit."""
    ratios, _ = orange_folds
    assert math.exp(np.mean(np.log(ratios))) <= 1.05, ratios


#: a one-compartment model a pharmacologist might write for indomethacin after an IV bolus (not shipped): the
#: distribution phase is what it misses
INDOMETH_SYSTEM = textwrap.dedent(
    """
    import torchmisspec as tms


    def elimination(y, theta):
        return -theta[0] * y


    def one_compartment():
        return tms.MisspecifiedSystem(
            elimination, 1, parameters={"k": (1.0, 1.0)}, state_names=["conc"], name="one compartment"
        )
    """
)


@pytest.mark.slow
def test_r_indometh_as_a_labs_csv_through_the_cli_and_leaving_one_subject_out(tmp_path, capsys):
    """R's Indometh (Kwan, Breault, Umbenhauer, McMahon and Duggan 1976: plasma indomethacin, mcg/mL, in 6 subjects
    at 11 times over 8 h after an IV bolus; tests/data/indometh.csv, columns subject, hours, conc) with a
    one-compartment model written here. The command line fits it with defaults and says why its bands are left as
    the model gives them (the noise alone covers the held-out data: narrowed to the floor, they were 16 times too
    narrow); the forecast to 12 h (the data end at 8) is finite with a band that widens. Leaving each subject out
    (fit on the other 5, forecast from its first measurement), the defaults beat the classical answer (k fitted
    through the ODE, F = 0) on the log-RMSE: measured 0.43 of it (geometric mean, 6 of 6 better)."""
    from torchmisspec.paper.oracle import fitted_through_ode

    (tmp_path / "indo.py").write_text(INDOMETH_SYSTEM)
    data_file = Path(__file__).parent / "data" / "indometh.csv"
    system_arg = f"{tmp_path / 'indo.py'}:one_compartment"
    model = tmp_path / "indo.pt"
    code = cli.main(["fit", "--data", str(data_file), "--time-column", "hours", "--experiment-column", "subject",
                     "--system", system_arg, "--out", str(model), "--quiet"])  # fmt: skip
    said = capsys.readouterr()
    err = said.err
    assert code == 0, err
    assert "the measurement noise alone covers" in err and "k: " in err  # bands as given; k not determined
    assert "then refined through the ODE" in said.out  # 11 sparse times: the estimator's advice taken
    (tmp_path / "start.csv").write_text("conc\n2.0\n")
    out = tmp_path / "pred.csv"
    code = cli.main(["predict", "--model", str(model), "--system", system_arg, "--initial", str(tmp_path / "start.csv"),
                     "--times", "0.25:12:24", "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    with out.open() as fh:
        rows = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]
    assert all(math.isfinite(v) for row in rows for v in row.values())
    width = [row["conc_upper"] - row["conc_lower"] for row in rows]
    assert width[-1] > width[len(width) // 2] > 0  # beyond the data the band widens
    data = tms.Trajectories.load(data_file, time_column="hours", experiment_column="subject")
    system = tms.systems.load_system(system_arg)
    ratios = []
    for k in range(data.num_experiments):
        train = data[[i for i in range(data.num_experiments) if i != k]]
        t, y = data[[k]].experiments()[0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", tms.TorchMisspecWarning)
            gp = tms.fit_correction(train, system, progress=False)
            classical = fitted_through_ode(system, train, "relative")
        default = tms.CorrectedODE(system, gp).predict(y[:1], t)[0]
        known = tms.simulate(classical, y[:1], t, known_only=True).states[0]
        error = [float((p.log() - y.log())[1:].pow(2).mean().sqrt()) for p in (default, known)]
        ratios.append(error[0] / error[1])
    assert math.exp(np.mean(np.log(ratios))) < 1.0 and sum(r < 1 for r in ratios) >= 5, ratios


@pytest.mark.slow
def test_r_indometh_as_a_population_through_the_cli_and_leaving_one_subject_out(tmp_path, capsys):
    """The same lab's CSV as a population (issue 43): every subject its own elimination rate k, log-normal. The
    command line fits it with defaults and writes every subject's k, and predicts a next subject (subject 1's first
    2 rows as its first measurements) to 12 h with the band of its new measurements, saying that 12 h is past the
    data; the fit saved (``--save``) and read back (``--fit``) predicts the same table; leaving subjects 1 and 4 out
    in turn (the population fitted on the other 5; each fit about a minute on 2 cores, so two of the six), the
    subject is predicted from its first 2 measurements and forecast to 12 h (the data end at 8): finite, positive,
    with a band, and never worse than the classical answer (the same population with F = 0) beyond 5 % on the
    geometric mean of the log-RMSE; its band of new measurements, calibrated on the other subjects held out, holds at
    least 80 % of its later measurements."""
    from torchmisspec.population import Population
    from torchmisspec.population.fit import fit_population
    from torchmisspec.population.predict import predict_subject

    (tmp_path / "indo.py").write_text(INDOMETH_SYSTEM)
    data_file = Path(__file__).parent / "data" / "indometh.csv"
    system_arg = f"{tmp_path / 'indo.py'}:one_compartment"
    out, nxt = tmp_path / "subjects.csv", tmp_path / "next.csv"
    with data_file.open() as fh:
        rows = [r for r in csv.DictReader(fh) if r["subject"] == "1"][:2]
    (tmp_path / "first.csv").write_text("hours,conc\n" + "".join(f"{r['hours']},{r['conc']}\n" for r in rows))
    code = cli.main(["population", "--data", str(data_file), "--time-column", "hours", "--experiment-column",
                     "subject", "--system", system_arg, "--vary", "k", "--out", str(out), "--quiet",
                     "--predict-times", "0.25:12:48", "--first", str(tmp_path / "first.csv"), "--predict-out",
                     str(nxt), "--measurements", "--save", str(tmp_path / "indometh.pt")])  # fmt: skip
    said = capsys.readouterr()
    assert code == 0, said.err
    # the saved population, read back later, predicts the same next subject without the data or a refit
    code = cli.main(["population", "--fit", str(tmp_path / "indometh.pt"), "--system", system_arg, "--time-column",
                     "hours", "--experiment-column", "subject", "--quiet", "--predict-times", "0.25:12:48",
                     "--first", str(tmp_path / "first.csv"), "--predict-out", str(tmp_path / "again.csv"),
                     "--measurements"])  # fmt: skip
    assert code == 0 and "loaded a population of 6 experiments" in capsys.readouterr().out
    assert (tmp_path / "again.csv").read_text() == nxt.read_text()
    assert "fitted a population of 6 experiments" in said.out and "95% interval" in said.out
    assert "a new subject's 90% band from its first 2 measurements" in said.out  # calibrated on held-out subjects
    assert "next subject from its first 2 measurements: k = " in said.out and "past the data's last time 8" in said.out
    with nxt.open() as fh:
        path = [{k: float(v) for k, v in row.items() if k != "subject"} for row in csv.DictReader(fh)]
    assert len(path) == 48 and all(math.isfinite(v) and v >= 0 for row in path for v in row.values())
    assert all(r["conc_lower"] < r["conc_mean"] < r["conc_upper"] for r in path[1:])
    with out.open() as fh:
        ks = [float(row["k"]) for row in csv.DictReader(fh)]
    assert len(ks) == 6 and all(0 < k < 10 for k in ks) and len(set(ks)) == 6
    data = tms.Trajectories.load(data_file, time_column="hours", experiment_column="subject")
    system = tms.systems.load_system(system_arg)
    ratios, inside, later = [], 0, 0
    for k in (0, 3):
        train = data[[i for i in range(data.num_experiments) if i != k]]
        t, y = data[[k]].experiments()[0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", tms.TorchMisspecWarning)
            fit = fit_population(train, system, Population(["k"]), progress=False)
        first = tms.Trajectories(t[:2], y[:2][None], state_names=["conc"])
        beyond = torch.cat([t, torch.tensor([10.0, 12.0], dtype=t.dtype)])
        errors = []
        for model in (fit, fit.as_classical()):
            g = torch.Generator().manual_seed(0)
            pred = predict_subject(model, None, beyond, first=first, num_samples=16, generator=g)
            path = pred.posterior.mean_path[0, :, 0]
            assert bool(torch.isfinite(path).all()) and bool((path > 0).all())
            lo, hi = pred.posterior.interval(0.9)
            assert bool((hi[0, -1] > lo[0, -1]).all())
            errors.append(float((path[2 : len(t)].log() - y[2:, 0].log()).pow(2).mean().sqrt()))
            if model is fit:  # the band of new measurements, calibrated on the other subjects held out in turn
                lo, hi = pred.posterior.measured(fit.noise, fit.nlme.modes.scale, generator=g).interval(0.9)
                inside += int(((y[2:, 0] >= lo[0, 2 : len(t), 0]) & (y[2:, 0] <= hi[0, 2 : len(t), 0])).sum())
                later += len(t) - 2
                assert fit.calibration is not None and pred.band_scale == fit.calibration.scale
        ratios.append(errors[0] / errors[1])
    assert math.exp(np.mean(np.log(ratios))) <= 1.05, ratios
    # measured: 18 of 18 (before narrowing needed 8 held-out subjects, its bands narrowed to 0.70-0.81 of their
    # spread held them too; over all six subjects 48 of 54, as without); on 5 subjects a band is not narrowed
    assert inside >= 0.8 * later, (inside, later)
    assert fit.calibration.scale >= 1.0 and fit.calibration.subjects == 5


REMIFENTANIL_SYSTEM = textwrap.dedent(
    """
    import torchmisspec as tms


    def infusion(t, y, u, theta):  # dC/dt = Rate / V - k C: C ng/mL, Rate ug/min, V L, k 1/min
        return u / theta[1] - theta[0] * y


    def one_compartment():
        return tms.MisspecifiedSystem(
            infusion, 1, num_controls=1, control_names=["Rate"], state_names=["conc"],
            parameters={"k": (0.3, 0.2), "V": (10.0, 5.0)}, name="remifentanil, one compartment",
        )
    """
)


@pytest.mark.slow
def test_r_remifentanil_infusions_as_a_population_through_the_cli_with_the_next_subject_s_profile(tmp_path, capsys):
    """nlme's Remifentanil (Minto, Schnider, Egan et al. 1997, Anesthesiology 86, 10-23: arterial remifentanil,
    ng/mL, during and after a 20-minute infusion at a rate of the subject's own, ug/min; R's ``nlme::Remifentanil``,
    subjects 1-9 in tests/data/remifentanil.csv as the file holds them: ID, Time in minutes, conc, Rate, Wt; the
    infusion's start row has no measurement) with a one-compartment infusion model written here, k and V varying
    (the truth has three compartments). Subjects 1-8 fit the population with defaults through the command line
    (the integrated start's F, judged on held-out subjects before the population is refitted under it: that EM took
    a minute a round; the whole fit took 171 s on 2 cores, and 52 s with the prediction once F's derivative samples
    were estimated in log space, held-out misfit 64.6 against 357 for F = 0); subject 9, given 9 times the dose of
    subject 1 (its
    concentrations far above the training subjects'), is predicted from its first 2 measurements under its own
    profile (--controls) to 240 minutes, past the data's last time: finite, its mean positive, with a band (whose
    lower edge, where F's draws take it below 0, is said to be; where the band leaves the mean path, F's draws
    holding the concentration at a level where F's mean lets it fall, that is said), and no worse than the
    classical answer (the same population with F = 0) beyond 5 % on the log-RMSE of its later measurements
    (measured: 0.70 against 1.51, F kept; 0.91 against 1.51 with F's samples in log space, its band at 220 minutes
    [0.07, 0.22] ng/mL around 0.12, where before one run's was [1.75, 180] around 0.18; the classical answer's path
    falls to 0.05 ng/mL at 140 minutes where 0.56 was measured)."""
    from torchmisspec.population.fit import PopulationFit
    from torchmisspec.population.predict import predict_subject

    (tmp_path / "remi.py").write_text(REMIFENTANIL_SYSTEM)
    system_arg = f"{tmp_path / 'remi.py'}:one_compartment"
    with (Path(__file__).parent / "data" / "remifentanil.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    header = list(rows[0])
    with (tmp_path / "lab.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([header] + [[r[c] for c in header] for r in rows if r["ID"] != "9"])
    nine = [r for r in rows if r["ID"] == "9"]
    measured = [r for r in nine if r["conc"]]
    with (tmp_path / "first.csv").open("w", newline="") as fh:  # its rows up to its second measurement
        early = [[r["Time"], r["conc"], r["Rate"]] for r in nine if float(r["Time"]) <= float(measured[1]["Time"])]
        csv.writer(fh).writerows([["Time", "conc", "Rate"], *early])
    with (tmp_path / "profile.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([["Time", "Rate"], ["0", nine[0]["Rate"]], ["20", "0"]])
    out, nxt, saved = tmp_path / "subjects.csv", tmp_path / "next.csv", tmp_path / "remi.pt"
    code = cli.main(["population", "--data", str(tmp_path / "lab.csv"), "--time-column", "Time", "--experiment-column",
                     "ID", "--state-columns", "conc", "--input-columns", "Rate", "--system", system_arg, "--vary",
                     "k,V", "--out", str(out), "--quiet", "--predict-times", f"{measured[0]['Time']}:240:60",
                     "--first", str(tmp_path / "first.csv"), "--controls", str(tmp_path / "profile.csv"),
                     "--predict-out", str(nxt), "--save", str(saved)])  # fmt: skip
    said = capsys.readouterr()
    assert code == 0, said.err
    assert "measure nothing in their first row(s) but give inputs there" in said.err  # the start rows, said
    assert "fitted a population of 8 experiments" in said.out and "past the data's last time" in said.out
    with nxt.open() as fh:
        path = [{k: float(v) for k, v in row.items() if k != "ID"} for row in csv.DictReader(fh)]
    assert len(path) == 60 and all(math.isfinite(v) for row in path for v in row.values())
    assert all(0 < r["conc_mean"] and r["conc_lower"] < r["conc_upper"] for r in path[1:])
    assert path[0]["conc_lower"] == path[0]["conc_mean"] == path[0]["conc_upper"]  # its fitted first state, exactly
    if not all(r["conc_lower"] <= r["conc_mean"] <= r["conc_upper"] for r in path):  # F's draws hold the path up
        assert "lies outside the central 95 % of its paths drawn" in said.err
    if any(r["conc_lower"] < 0 for r in path):  # F's draws near 0 pull some paths below it: said, not hidden
        assert "drawn paths go below 0, where its measurements are positive (noise 'relative')" in said.err
    with out.open() as fh:
        assert len([row for row in csv.DictReader(fh)]) == 8
    # the package against the classical answer on subject 9's later measurements, from the saved fit
    system = tms.systems.load_system(system_arg)
    fit = PopulationFit.load(saved, system)
    t = torch.tensor([float(r["Time"]) for r in measured], dtype=torch.float64)
    y = torch.tensor([float(r["conc"]) for r in measured], dtype=torch.float64)
    rate = torch.tensor([[[float(nine[0]["Rate"])], [0.0]]], dtype=torch.float64)
    profile = tms.Controls(torch.tensor([0.0, 20.0], dtype=torch.float64), rate, names=["Rate"])
    first = tms.Trajectories(t[:2], y[:2, None][None], state_names=["conc"], controls=profile)
    errors = []
    for model in (fit, fit.as_classical()):
        pred = predict_subject(model, None, t, first=first, controls=profile, num_samples=16)
        mean = pred.posterior.mean_path[0, :, 0]
        assert bool(torch.isfinite(mean).all()) and bool((mean > 0).all())
        errors.append(float((mean[2:].log() - y[2:].log()).pow(2).mean().sqrt()))
    assert errors[0] <= 1.05 * errors[1], errors
