"""``torchmisspec population`` on a lab's table: a subject column, a covariate column, the next subject's design."""

from __future__ import annotations

import csv

import pytest
import torch

from torchmisspec.cli import main

DT = torch.float64
SYSTEM = """
import torch
import torchmisspec as tms


def slope(y, theta):
    return theta[0] * torch.ones_like(y)


def system():
    return tms.MisspecifiedSystem(slope, 1, state_names=["y"], parameters={"c": (1.0, 0.5)})
"""


@pytest.fixture
def lab(tmp_path):
    """12 subjects, y = 2 + c_i t with c_i = 1 + 0.02 (weight - 70) + 0.1 z, columns in the lab's order."""
    g = torch.Generator().manual_seed(0)
    rows = []
    for subject in range(1, 13):
        weight = float(60 + 20 * torch.rand(1, generator=g, dtype=DT))
        c = 1.0 + 0.02 * (weight - 70) + 0.1 * float(torch.randn(1, generator=g, dtype=DT))
        for t in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0):
            y = 2.0 + c * t + (0.05 * float(torch.randn(1, generator=g, dtype=DT)) if t else 0.0)
            rows.append([f"{y:.6f}", subject, f"{t:g}", f"{weight:.2f}"])
    path = tmp_path / "lab.csv"
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows([["y", "subject", "time", "weight"], *rows])
    (tmp_path / "model.py").write_text(SYSTEM)
    return tmp_path


def _run(lab, *extra):
    data, system = str(lab / "lab.csv"), f"{lab / 'model.py'}:system"
    return main(["population", "--data", data, "--system", system, "--experiment-column", "subject", "--vary", "c",
                 "--distribution", "normal", "--quiet", *extra])  # fmt: skip


def test_population_from_a_lab_table_with_a_covariate(lab, capsys):
    out = lab / "subjects.csv"
    code = _run(lab, "--covariate", "c=weight", "--out", str(out), "--next-times", "0,0.25,0.5,0.75,1",
                "--budget", "2", "--next-initial", "2", "--next-covariate", "weight=70")  # fmt: skip
    printed = capsys.readouterr().out
    assert code == 0
    assert "fitted a population of 12 experiments" in printed and "c ~ weight" in printed
    assert "next subject: sample at 0.75, 1 from the initial state (2) at 0; expected to remove " in printed
    assert "of the variance its parameters have before any sample (the population's spread)" in printed
    rows = list(csv.reader(out.open()))
    assert rows[0] == ["subject", "c"] and [r[0] for r in rows[1:]] == [str(k) for k in range(1, 13)]
    effect = float(printed.split("c ~ weight: ")[1].split()[0])
    assert effect == pytest.approx(0.02, abs=0.01)
    lo, hi = (float(v) for v in printed.split("95% [")[1].split("]")[0].split(","))
    assert lo < 0.02 < hi  # the effect's interval holds the truth
    assert "95% interval" in printed


def test_next_times_take_the_forms_predict_times_takes(lab, capsys):
    """``--next-times 0:1:5`` designs as the comma list of the same times does (a newcomer wrote the form
    ``--predict-times`` takes, and was refused)."""
    said = []
    for times in ("0,0.25,0.5,0.75,1", "0:1:5"):
        assert _run(lab, "--next-times", times, "--budget", "2", "--next-initial", "2") == 0
        said.append([line for line in capsys.readouterr().out.splitlines() if line.startswith("next subject:")])
    assert said[0] == said[1] and said[0]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--vary", "k"], "--vary: expected names among"),
        (["--covariate", "c"], "expected PARAMETER=COLUMN"),
        (["--covariate", "c=age"], "expected covariate column(s) ['age']"),
        (["--next-times", "0,1"], "--budget: expected the number of samples"),
        (["--next-times", "0,1", "--budget", "1"], "--next-initial: expected the next subject's initial state"),
        (["--first", "lab.csv"], "--first: expected --predict-times with it"),
        (["--predict-times", "0,1"], "--next-initial: expected the next subject's initial state"),
        (["--predict-times", "1,0.5", "--next-initial", "2"], "--predict-times: expected finite, strictly increasing"),
        (["--predict-times", "0:1", "--next-initial", "2"], "--predict-times: expected 'start:stop:count'"),
        (["--predict-times", "0,1", "--next-initial", "2", "--level", "90"], "--level: expected a band's coverage"),
    ],
)
def test_population_errors_are_one_line(lab, capsys, extra, message):
    assert _run(lab, *extra) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err


def test_next_subject_predicted_from_its_first_measurements(lab, capsys):
    """Subject 3's own rows as the next subject's first measurements: its parameter is the one the population fit
    gave subject 3, its band holds its samples and is narrower than the population alone's, written past the data's
    last time."""
    rows = list(csv.reader((lab / "lab.csv").open()))
    own = [r for r in rows[1:] if r[1] == "3"]
    with (lab / "first.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([["time", "y", "weight"], *([r[2], r[0], r[3]] for r in own)])
    weight = f"weight={own[0][3]}"
    common = ["--covariate", "c=weight", "--out", str(lab / "s.csv"), "--predict-times", "0:2:11", "--next-covariate",
              weight]  # fmt: skip
    assert _run(lab, *common, "--first", str(lab / "first.csv"), "--predict-out", str(lab / "updated.csv")) == 0
    printed = capsys.readouterr().out
    assert "next subject from its first 6 measurements: c = " in printed and "past the data's last time 1" in printed
    assert "band not calibrated: no held-out subject could be checked from its first 6" in printed  # all they have
    fitted = {r[0]: float(r[1]) for r in list(csv.reader((lab / "s.csv").open()))[1:]}
    # within its posterior sd (0.05 noise at 5 times up to 1: about 0.03); the weights differ (the new subject's
    # samples are weighed by the population's residual scale at their times)
    assert float(printed.split("c = ")[1].split(";")[0]) == pytest.approx(fitted["3"], abs=0.03)
    with (lab / "first2.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([["time", "y", "weight"], *([r[2], r[0], r[3]] for r in own[:2])])
    assert _run(lab, *common, "--first", str(lab / "first2.csv"), "--predict-out", str(lab / "two.csv")) == 0
    assert "times its spread, as held-out subjects needed from their first 2" in capsys.readouterr().out
    assert _run(lab, *common, "--next-initial", "2", "--predict-out", str(lab / "alone.csv")) == 0
    printed = capsys.readouterr().out
    assert "next subject from the population alone" in printed
    assert "times its spread, as held-out subjects needed from the population alone" in printed
    assert _run(lab, *common, "--next-initial", "2", "--predict-out", str(lab / "noisy.csv"), "--measurements") == 0
    assert "band of new measurements written" in capsys.readouterr().out
    updated, alone = (
        [list(map(float, r[1:])) for r in list(csv.reader((lab / n).open()))[1:]] for n in ("updated.csv", "alone.csv")
    )
    table = list(csv.reader((lab / "updated.csv").open()))
    assert table[0] == ["subject", "time", "y_mean", "y_lower", "y_upper"]  # as `predict` writes its table
    assert {r[0] for r in table[1:]} == {"next"}
    assert [r[0] for r in updated] == pytest.approx([0.2 * i for i in range(11)])
    assert updated[-1][3] - updated[-1][2] < 0.8 * (alone[-1][3] - alone[-1][2])  # narrower at t = 2
    noisy = [list(map(float, r[1:])) for r in list(csv.reader((lab / "noisy.csv").open()))[1:]]
    assert all(n[3] - n[2] > a[3] - a[2] for n, a in zip(noisy[1:], alone[1:], strict=True))  # the noise widens it
    for t, y in ((float(r[2]), float(r[0])) for r in own[1:]):
        row = updated[round(t / 0.2)]
        assert row[2] - 0.15 < y < row[3] + 0.15  # its samples (noise 0.05) near its band


@pytest.mark.parametrize("labelled", [True, False])
def test_first_measurements_of_two_subjects_are_refused_with_the_fix(lab, capsys, labelled):
    """A --first table holding two subjects' rows (the lab's table cut short): one line that says so, whether its
    subject column labels them (it was not read: "no column 'experiment'" advised --experiment-column, given) or not
    (the same times twice)."""
    rows = list(csv.reader((lab / "lab.csv").open()))
    two = [r for r in rows[1:] if r[1] in ("3", "4") and float(r[2]) <= 0.2]
    with (lab / "two.csv").open("w", newline="") as fh:
        if labelled:
            csv.writer(fh).writerows([["time", "y", "subject"], *([r[2], r[0], r[1]] for r in two)])
        else:
            csv.writer(fh).writerows([["time", "y"], *([r[2], r[0]] for r in two)])
    assert _run(lab, "--predict-times", "0:2:11", "--first", str(lab / "two.csv")) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and "--experiment-column subject on" not in err, err
    if labelled:
        assert "--first: expected the next subject's first measurements (one subject's rows), got 2 subjects" in err
    else:
        assert "expected one row per experiment and time, got time 0.0 more than once" in err, err


def test_next_subject_times_before_its_first_measurement_are_refused_before_the_work(lab, capsys, monkeypatch):
    """A path from the subject's first measurement cannot be drawn at earlier times: refused, not shifted."""
    import torchmisspec.population.fit as fit_module

    monkeypatch.setattr(fit_module, "fit_population", None)  # the fit is never reached
    with (lab / "late.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([["time", "y", "weight"], ["0.5", "2.4", "70"], ["0.75", "2.6", "70"]])
    code = _run(lab, "--predict-times", "0:2:11", "--first", str(lab / "late.csv"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert "--predict-times: expected times from the subject's first measurement at t = 0.5 on" in err


def test_the_next_subject_of_a_system_with_inputs_is_predicted_and_designed_under_its_profile(lab, capsys, monkeypatch):
    """dy/dt = c u(t) with the lab's u = 1 (a column of the table): the next subject's input profile comes from
    ``--controls`` (refused, before the work, where it is missing); under u = 1 the design is the system without
    inputs' (its last two times) and the prediction runs; under u = 1 on [0, 0.5) and -1 after, y's sensitivity to
    c is min(t, 1 - t), so the best times are 0.5 and the next largest."""
    from torchmisspec.population import fit as fit_module

    (lab / "driven.py").write_text(
        SYSTEM.replace("def slope(y, theta):", "def driven(t, y, u, theta):").replace("torch.ones_like(y)", "u")
        + "\n\ndef with_input():\n    return tms.MisspecifiedSystem(driven, 1, state_names=['y'], num_controls=1, "
        "control_names=['u'], time_dependent=True, parameters={'c': (1.0, 0.5)})\n"
    )
    rows = list(csv.reader((lab / "lab.csv").open()))
    with (lab / "driven.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([[*rows[0], "u"]] + [[*r, "1"] for r in rows[1:]])
    for name, profile in (
        ("one.csv", [["time", "u"], ["0", "1"]]),
        ("step.csv", [["time", "u"], ["0", "1"], ["0.5", "-1"]]),
    ):
        with (lab / name).open("w", newline="") as fh:
            csv.writer(fh).writerows(profile)
    args = ["population", "--data", str(lab / "driven.csv"), "--system", f"{lab / 'driven.py'}:with_input",
            "--experiment-column", "subject", "--vary", "c", "--distribution", "normal", "--input-columns", "u",
            "--quiet", "--out", str(lab / "s.csv"), "--next-times", "0,0.25,0.5,0.75,1", "--budget", "2",
            "--next-initial", "2", "--predict-times", "0:1:5", "--predict-out", str(lab / "next.csv")]  # fmt: skip
    real = fit_module.fit_population
    monkeypatch.setattr(fit_module, "fit_population", None)  # the fit is never reached
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "--controls: expected the next subject's input profile for --next-times" in err and "\n" not in err
    monkeypatch.setattr(fit_module, "fit_population", real)
    assert main([*args, "--controls", str(lab / "one.csv"), "--save", str(lab / "p.pt")]) == 0
    said = capsys.readouterr().out
    assert "next subject: sample at 0.75, 1 from the initial state (2) at 0" in said
    with (lab / "next.csv").open() as fh:
        path = [float(r["y_mean"]) for r in csv.DictReader(fh)]
    assert len(path) == 5 and path[-1] > path[0] + 0.5  # y = 2 + c t under u = 1, c about 1
    later = ["population", "--fit", str(lab / "p.pt"), "--system", f"{lab / 'driven.py'}:with_input", "--quiet",
             "--next-times", "0,0.25,0.5,0.75,1", "--budget", "1", "--next-initial", "2", "--controls",
             str(lab / "step.csv")]  # fmt: skip
    assert main(later) == 0
    assert "next subject: sample at 0.5 from the initial state (2) at 0" in capsys.readouterr().out


def test_a_population_saved_once_designs_and_predicts_later_without_the_data(lab, capsys):
    """``--save`` writes the fitted population; ``--fit`` reads it back instead of fitting ``--data``: the same
    design and the same next subject's table as the run that fitted it."""
    saved = lab / "population.pt"
    common = ["--next-times", "0,0.25,0.5,0.75,1", "--budget", "2", "--next-initial", "2", "--next-covariate",
              "weight=70", "--predict-times", "0:2:5"]  # fmt: skip
    fitted = ["--covariate", "c=weight", "--out", str(lab / "s.csv"), "--save", str(saved)]
    assert _run(lab, *fitted, *common, "--predict-out", str(lab / "a.csv")) == 0
    first = capsys.readouterr().out
    assert f"the fitted population saved to {saved} (design or predict the next subject from it with --fit" in first
    system = f"{lab / 'model.py'}:system"
    args = ["population", "--fit", str(saved), "--system", system, "--quiet", *common, "--predict-out"]
    assert main([*args, str(lab / "b.csv")]) == 0
    later = capsys.readouterr().out
    assert "loaded a population of 12 experiments of 'system'" in later and "c ~ weight" in later
    design = [line for line in first.splitlines() if line.startswith("next subject: sample at")]
    assert design and design == [line for line in later.splitlines() if line.startswith("next subject: sample at")]
    # the same rows (the first column's name is --experiment-column's, not given to the second run)
    assert (lab / "a.csv").read_text().splitlines()[1:] == (lab / "b.csv").read_text().splitlines()[1:]
    assert main(["population", "--system", system, "--quiet"]) == 2
    assert (
        "--data / --fit: expected a table to fit (--data) or a population saved with --save (--fit), got neither"
        in (capsys.readouterr().err)
    )
    assert main([*args, str(lab / "c.csv"), "--data", str(lab / "lab.csv")]) == 2
    assert "got both" in capsys.readouterr().err
    assert main(["population", "--fit", str(lab / "lab.csv"), "--system", system]) == 2
    err = capsys.readouterr().err.strip()
    assert "expected a PopulationFit file written by PopulationFit.save" in err and "\n" not in err


def test_the_population_fit_says_which_stage_it_is_in(lab, capfd):
    """A user trial on nlme's Remifentanil saw nothing for 14 minutes after EM's bar: each stage now names itself."""
    data, system = str(lab / "lab.csv"), f"{lab / 'model.py'}:system"
    code = main(["population", "--data", data, "--system", system, "--experiment-column", "subject", "--vary", "c",
                 "--distribution", "normal", "--out", str(lab / "s.csv")])  # fmt: skip
    err = capfd.readouterr().err
    assert code == 0
    for stage in ("population: the classical fit (F = 0, EM)", "population: F with every experiment's parameters"):
        assert stage in err
    quiet = _run(lab, "--out", str(lab / "s.csv"))
    assert quiet == 0 and "population: the classical fit" not in capfd.readouterr().err
