"""``scripts/benchmark.py --smoke`` runs end to end and its peers agree with ours (no timing is asserted)."""

import importlib.util
import json
import math
import re
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "benchmark.py"


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    pytest.importorskip("sklearn")
    spec = importlib.util.spec_from_file_location("benchmark_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path_factory.mktemp("benchmark")
    threads = torch.get_num_threads()
    try:
        code = module.main(
            ["--smoke", "--threads", "1", "--json", str(out / "r.json"), "--markdown", str(out / "B.md")]
        )
    finally:
        torch.set_num_threads(threads)  # the script sets it for its process; leave the test session as it was
    assert code == 0
    return json.loads((out / "r.json").read_text()), (out / "B.md").read_text()


def test_every_benchmark_ran(smoke):
    results, page = smoke
    for name in ("fit", "gradient", "predict", "design", "naive", "contention", "realdata"):
        assert name in results
        assert f"--only {name}" in page
    assert results["machine"]["torch_threads"] == 1
    assert not re.search(r"\bnan\b", page, re.IGNORECASE)  # every figure was measured


def test_fit_peers_reach_our_likelihood(smoke):
    fit = smoke[0]["fit"]
    for peer in ("gpytorch_default", "gpytorch_cholesky", "sklearn"):
        assert math.isfinite(fit[peer]["lml"])
        assert fit[peer]["evaluations"] > 0
    # the same model, optimiser and start as ours: the exact-Cholesky GPyTorch fit must land on our optimum
    assert fit["gpytorch_cholesky"]["lml"] == pytest.approx(fit["ours"]["lml"], rel=1e-6)
    assert fit["gpytorch_cholesky"]["own_lml"] == pytest.approx(fit["gpytorch_cholesky"]["lml"], rel=1e-8)


def test_gradient_ablation_agrees_with_autograd(smoke):
    gradient = smoke[0]["gradient"]
    for row in gradient["sizes"]:
        assert row["gradient_max_relative_difference"] < 1e-8
        assert row["value_relative_difference"] < 1e-12
    fits = gradient["fit"]
    assert fits["analytic"]["lml"] == pytest.approx(fits["autograd"]["lml"], rel=1e-8)


def test_prediction_peers_match(smoke):
    predict = smoke[0]["predict"]
    for peer in ("gpytorch", "gpytorch_fast"):
        assert predict[peer]["max_abs_difference"] < 1e-8


def test_design_picks_agree(smoke):
    for case in smoke[0]["naive"].values():
        assert case["identical_picks"]


def test_the_page_keeps_every_other_scripts_block(smoke, tmp_path):
    """benchmark.py rewrites its own part of BENCHMARKS.md and keeps the blocks the study and benchmark scripts
    maintain there (``study:*`` and ``bench:*``: a rerun once dropped the campaign and features blocks)."""
    from torchmisspec.benchmarks.suite import write_page

    results, _ = smoke
    page = tmp_path / "B.md"
    kept = "<!-- study:x:start -->\nS\n<!-- study:x:end -->\n\n<!-- bench:y-z:start -->\nB\n<!-- bench:y-z:end -->"
    page.write_text("old\n\n" + kept + "\n")
    write_page(results, str(page))
    text = page.read_text()
    assert kept in text and "old\n" not in text
