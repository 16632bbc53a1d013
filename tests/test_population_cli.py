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
    assert "next subject: sample at 0.75, 1 from the initial state (2); expected to remove " in printed
    assert "of its parameters' variance in the population" in printed
    rows = list(csv.reader(out.open()))
    assert rows[0] == ["subject", "c"] and [r[0] for r in rows[1:]] == [str(k) for k in range(1, 13)]
    effect = float(printed.split("c ~ weight: ")[1].split()[0])
    assert effect == pytest.approx(0.02, abs=0.01)
    lo, hi = (float(v) for v in printed.split("95% [")[1].split("]")[0].split(","))
    assert lo < 0.02 < hi  # the effect's interval holds the truth
    assert "95% interval" in printed


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--vary", "k"], "expected names among"),
        (["--covariate", "c"], "expected PARAMETER=COLUMN"),
        (["--covariate", "c=age"], "expected covariate column(s) ['age']"),
        (["--next-times", "0,1"], "--budget: expected the number of samples"),
        (["--next-times", "0,1", "--budget", "1"], "--next-initial: expected the next subject's initial state"),
    ],
)
def test_population_errors_are_one_line(lab, capsys, extra, message):
    assert _run(lab, *extra) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err
