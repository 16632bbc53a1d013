"""``scripts/study_observations.py`` (issue 9's study: ``torchmisspec.paper.study_observations`` and
``study_observations_report``): its smoke run, its JSON, and the BENCHMARKS.md blocks."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

from torchmisspec.benchmarks import reporting, suite
from torchmisspec.paper import study_observations, study_observations_report

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"_script_{name}", SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    try:
        spec.loader.exec_module(module)
    finally:
        sys.modules.pop(spec.name, None)
    return module


@pytest.fixture(scope="module")
def study():
    return load("study_observations")


def finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.mark.slow
def test_smoke_run_writes_the_expected_json(study, tmp_path, monkeypatch):
    # smoke mode must never touch the docs or BENCHMARKS.md: point them at files that must stay absent
    monkeypatch.setattr(study_observations_report, "DOC_PAGE", tmp_path / "docs" / "page.md")
    monkeypatch.setattr(study_observations_report, "BENCHMARKS_MD", tmp_path / "B.md")
    threads = torch.get_num_threads()
    try:
        assert study.main(["--smoke", "--json", str(tmp_path / "s.json")]) == 0
    finally:
        torch.set_num_threads(threads)
    assert not (tmp_path / "docs").exists() and not (tmp_path / "B.md").exists()
    result = json.loads((tmp_path / "s.json").read_text())
    assert result["smoke"] is True
    assert set(result) >= {"command", "machine", "config", "raw", "summary", "wall_seconds"}
    assert result["machine"]["torch"] == torch.__version__
    names = [c.name for c in study_observations.CASES]
    runs = result["raw"]["runs"]
    assert sorted(r["system"] for r in runs) == sorted(names)  # every system, one cell each
    for r in runs:
        assert r["K"] == 5 and isinstance(r["warning"], bool)
        assert r["estimator"]["name"] in ("central", "smooth", "gp")
        assert finite(r["estimator_ratio"])
        for method in ("auto", "fit_trajectories"):
            assert r[method]["status"] == "ok", r[method]
            assert finite(r[method]["ratio"]) and r[method]["ratio"] > 0
            assert finite(r[method]["relative_rmse"])
        assert r["fit_trajectories"]["iterations"] >= 1
    cells = result["summary"]["cells"]
    assert len(cells) == len(names)
    for c in cells:
        for method in ("auto", "fit_trajectories"):
            assert finite(c[method]["ratio_mean"]) and finite(c[method]["ratio_se"])
    ie = result["summary"]["integrated_error"]
    assert finite(ie["oracle"]["mean"]) and ie["oracle"]["mean"] > 0
    for method in ("auto", "fit_trajectories"):
        assert finite(ie[method]["mean"]) and finite(ie[method]["ratio_to_oracle"])
    goals = result["summary"]["goals"]
    assert goals and all(isinstance(g["pass"], bool) and g["goal"] for g in goals)
    # the pages render from the smoke result without a missing number
    page = study_observations_report.render_page(result)
    assert "nan" not in page.lower().replace("n/a", "")


def test_smoke_refuses_markdown(study):
    with pytest.raises(SystemExit):
        study.main(["--smoke", "--markdown"])


def test_replace_block_appends_then_replaces():
    start, end = study_observations_report.MARK_START, study_observations_report.MARK_END
    block1 = f"{start}\nfirst\n{end}\n"
    block2 = f"{start}\nsecond\n{end}\n"
    text = reporting.replace_marked("# Benchmarks\n\nbody\n", block1, start, end)
    assert text == "# Benchmarks\n\nbody\n\n" + block1
    again = reporting.replace_marked(text + "\ntail\n", block2, start, end)
    assert "first" not in again and again.count(start) == 1
    assert again.startswith("# Benchmarks\n\nbody\n\n" + block2) and again.endswith("tail\n")


def test_benchmark_markdown_keeps_study_blocks(tmp_path, monkeypatch):
    bench = load("benchmark")
    monkeypatch.setattr(suite, "BENCHMARKS", {})  # nothing to run: only the page writing is under test
    monkeypatch.setattr(suite, "render_markdown", lambda results: "# Benchmarks\n\nfresh\n")
    path = tmp_path / "B.md"
    block = "<!-- study:observations:start -->\nkept\n<!-- study:observations:end -->"
    path.write_text(f"# Benchmarks\n\nstale\n\n{block}\n")
    threads = torch.get_num_threads()
    try:
        assert bench.main(["--markdown", str(path)]) == 0
    finally:
        torch.set_num_threads(threads)
    assert path.read_text() == f"# Benchmarks\n\nfresh\n\n{block}\n"
    path.unlink()
    assert bench.main(["--markdown", str(path)]) == 0  # no previous page: just the benchmark's own
    assert path.read_text() == "# Benchmarks\n\nfresh\n"
