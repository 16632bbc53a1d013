"""Fuzz of the command line: each case changes ONE option of a valid command on a lab's files to a bad value.

The promise checked (issue 25): the command either succeeds and writes a complete output (finite numbers), or exits
2 with one line on stderr that starts with ``torchmisspec <command>:``, no traceback, and no output file written.
The commands that only read (predict, design) run in the default tests; fit and calibrate (a fit each) in the slow
ones (every other case; all with ``TORCHMISSPEC_FUZZ_EXAMPLES`` set above 1500, the long profile).
"""

from __future__ import annotations

import math
import os

import pytest
from test_cli import _lab, lab, lab_model  # noqa: F401  (fixtures: the lab's files and a model fitted on them)

from torchmisspec.cli import main

NUMBERS = ["nan", "inf", "-1", "0", "1e400", "abc", "", "1.5", "99999999999999999999999"]
TIMES = ["nan", "0:20", "5:0:3", "a:b:c", "0:20:1", "0:1e400:5", "", "0:20:100000000000", "0:inf:3", "3"]
COLUMNS = ["", "nope", "hour,hour", "biomass,biomass", ",", "biomass,,substrate"]
READOUTS = ["total", "total = nope", "= biomass", "t = 1e999*biomass", "t = biomass + + substrate", "hour = biomass"]
SYSTEMS = ["", "x:", ":y", "nope", "os:getcwd", "paper_linear"]


def _files(folder) -> dict[str, str]:
    """Bad files of every kind a lab may pass by mistake."""
    (folder / "binary.bin").write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe" * 8)
    (folder / "empty.csv").write_text("")
    (folder / "header.csv").write_text("run,hour,biomass,substrate\n")
    (folder / "words.csv").write_text("run,hour,biomass,substrate\nr0,0,a,b\n")
    (folder / "nan.csv").write_text("run,hour,biomass,substrate\nr0,0,nan,0.3\nr0,1,0.2,inf\n")
    (folder / "text.pt").write_text("not a model\n")
    names = ["binary.bin", "empty.csv", "header.csv", "words.csv", "nan.csv", "text.pt"]
    return {name: str(folder / name) for name in names} | {
        "missing": str(folder / "missing.csv"),
        "folder": str(folder),
        "out.xyz": str(folder / "out.xyz"),
        "f.pdf": str(folder / "f.pdf"),
    }


def _cases(command: str):
    """(option, bad value) pairs of ``command``: every option it has, each with the bad values of its kind."""
    numbers = {"predict": ["--level", "--samples", "--seed"], "design": ["--budget", "--seed", "--lengthscale",
               "--samples-per-experiment"], "fit": ["--level", "--state-noise"],
               "calibrate": ["--level", "--state-noise"]}[command]  # fmt: skip
    files = {"predict": ["--model", "--initial", "--controls"], "design": ["--candidates", "--model"],
             "fit": ["--data"], "calibrate": ["--model", "--data"]}[command]  # fmt: skip
    cases = [(option, value) for option in numbers for value in NUMBERS]
    cases += [(option, f"<{name}>") for option in files for name in ("binary.bin", "empty.csv", "header.csv",
              "words.csv", "nan.csv", "text.pt", "missing", "folder")]  # fmt: skip
    if command in ("predict", "design"):
        cases += [("--times", value) for value in TIMES]
    cases += [("--state-columns", value) for value in COLUMNS]
    cases += [("--time-column", value) for value in ("", "nope", "biomass")]
    cases += [("--readout", value) for value in READOUTS]
    cases += [("--system", value) for value in SYSTEMS]
    cases += [("--out", value) for value in ("/proc/x.csv", "<folder>", "<out.xyz>", "")]
    if command == "design":
        cases += [(o, v) for o in ("--partition", "--capacities") for v in ("a,b", "1.5", "-1", "", "nan", "0,0,0")]
    if command == "predict":
        cases += [("--figure", value) for value in ("/proc/x.png", "<f.pdf>", "<folder>")]
    return cases


def _args(command: str, folder, model, tmp_path) -> list[str]:
    times = ("--times", "0:20:5")
    out = str(tmp_path / ("out.pt" if command in ("fit", "calibrate") else "out.csv"))
    return {
        "fit": _lab(folder, "fit", "--no-calibrate", "--out", out),
        "calibrate": _lab(folder, "calibrate", "--model", str(model), "--out", out),
        "predict": _lab(folder, "predict", "--model", str(model), "--initial", str(folder / "initial.csv"), *times,
                        "--out", out, "--samples", "4"),
        "design": _lab(folder, "design", "--model", str(model), "--candidates", str(folder / "candidates.csv"),
                       *times, "--budget", "2", "--out", out),
    }[command]  # fmt: skip


def _with(args: list[str], option: str, value: str, files: dict[str, str]) -> list[str]:
    value = files.get(value.strip("<>"), value) if value.startswith("<") else value
    args = list(args)
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    return args


def _finite_table(path) -> None:
    """Every number in a written CSV is finite (a complete output, not one with NaN holes)."""
    lines = path.read_text().splitlines()
    assert len(lines) >= 2, "an output with no rows"
    for line in lines[1:]:
        for cell in line.split(","):
            try:
                value = float(cell)
            except ValueError:
                continue
            assert math.isfinite(value), line


def _run(command, option, value, lab, lab_model, tmp_path, capsys):  # noqa: F811
    files = _files(tmp_path)
    args = _with(_args(command, lab, lab_model, tmp_path), option, value, files)
    capsys.readouterr()
    code = main(args)
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert "Traceback" not in captured.err + captured.out
    outputs = [p for p in tmp_path.rglob("out*") if p.is_file()]
    if code == 2:
        assert err.startswith(f"torchmisspec {command}: ") and "\n" not in err, err
        assert not outputs, f"{command} failed but wrote {outputs}"
    else:
        assert code == 0, (code, err)
        if option != "--out":
            assert outputs, f"{command} succeeded without writing its output"
        for path in outputs:
            if path.suffix == ".csv":
                _finite_table(path)


def _params(commands):
    return [pytest.param(c, o, v, id=f"{c}{o}={v!r}") for c in commands for o, v in _cases(c)]


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize(("command", "option", "value"), _params(["predict", "design"]))
def test_one_bad_option(command, option, value, lab, lab_model, tmp_path, capsys):  # noqa: F811
    _run(command, option, value, lab, lab_model, tmp_path, capsys)


#: the fits' cases: every other one in CI's slow run, all of them in the long profile (TORCHMISSPEC_FUZZ_EXAMPLES
#: above its default, as tests/test_fuzz.py's long run)
LONG = int(os.environ.get("TORCHMISSPEC_FUZZ_EXAMPLES", "1500")) > 1500
FITS = _params(["fit", "calibrate"])


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize(("command", "option", "value"), FITS if LONG else FITS[::2])
def test_one_bad_option_of_the_fits(command, option, value, lab, lab_model, tmp_path, capsys):  # noqa: F811
    _run(command, option, value, lab, lab_model, tmp_path, capsys)
