"""`scripts/study_one_trajectory.py` (issue 41, one-trajectory protocols): the systems, the summary, the smoke run."""

import json
import math
from pathlib import Path

import pytest
import torch

from torchmisspec.paper import study_one_trajectory as study

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", list(study.PROTOCOLS))
def test_known_model_plus_correction_is_the_literature_system(name):
    system = study.PROTOCOLS[name]["system"]()
    y = torch.tensor([[0.7, 1.9], [-1.2, 0.4]], dtype=torch.float64)
    x, v = y[:, 0], y[:, 1]
    if name == "ude_lotka_volterra":
        p = study.LV
        expected = torch.stack([p["a"] * x - p["b"] * x * v, p["c"] * x * v - p["d"] * v], dim=-1)
    else:
        expected = torch.stack([v, study.MU * (1 - x**2) * v - x], dim=-1)
    assert torch.allclose(system.true_rhs(y), expected)


def test_data_follow_the_protocol():
    data = study.make_data("ude_lotka_volterra", 0)
    assert data["times"].shape == (31,) and float(data["times"][-1]) == 3.0
    assert float(data["long"][-1]) == pytest.approx(10.0) and float(data["ahead"][0]) == pytest.approx(3.0)
    again = study.make_data("ude_lotka_volterra", 0)["noisy"]
    assert torch.equal(data["noisy"], again) and not torch.equal(data["noisy"], data["truth"])
    vdp = study.make_data("gpode_van_der_pol", 1)
    assert vdp["times"].shape == (25,) and float(vdp["long"][-1]) == pytest.approx(21.0)


def test_summary_counts_a_failed_realization():
    good = {"fit_seconds": 1.0, "f_relative_error": 0.5, "known_model": False, "kernel_name": "rbf", "exceptions": []}
    failed = {"exceptions": [{"stage": "fit_correction", "type": "FittingError", "message": "m", "where": ""}]}
    s = study.summary([good, failed])
    assert s["fit s"] == {"median": 1.0, "min": 1.0, "max": 1.0, "count": 1, "missing": 1}
    assert s["exceptions"] == 1 and s["kernels"] == {"rbf": 1, "fit failed": 1}


@pytest.mark.slow
def test_smoke_run_records_every_stage(study_smoke):
    saved, proc = study_smoke("study_one_trajectory.py")
    assert saved["smoke"] is True and list(saved["runs"]) == list(study.PROTOCOLS)
    for runs in saved["runs"].values():
        (run,) = runs
        for e in run["exceptions"]:  # recorded with their type and message, never hidden
            assert e["type"] and e["stage"]
        if not run["exceptions"]:
            assert run["fit_seconds"] > 0 and math.isfinite(run["f_relative_error"])
            assert run["span_failures"] == 0 and run["new_conditions"]["known_rmse"] > 0
    assert "| F rel. error (box) |" in proc.stdout


def test_the_docs_page_and_block_are_written_from_a_run(tmp_path):
    """--markdown's page and BENCHMARKS block come from the run's records (a saved run's too: its summaries are
    recomputed from its realizations, so quantities added since are shown as missing, not refused)."""

    from torchmisspec.paper import study_one_trajectory as study

    saved = json.loads((study.ROOT / "benchmarks" / "study_one_trajectory.json").read_text())
    page, block = study.render_page(saved), study.render_block(saved)
    assert page.startswith("# Study: one trajectory") and "## Results" in page
    assert block.startswith(study.MARK_START) and block.rstrip().endswith(study.MARK_END)
    f_row = next(line for line in page.splitlines() if line.startswith("| F rel. error (box)"))
    runs = saved["runs"]["ude_lotka_volterra"]
    values = sorted(r["f_relative_error"] for r in runs if r.get("f_relative_error") is not None)
    assert f"[{values[0]:.3g}, {values[-1]:.3g}]" in f_row  # the realizations' own extremes
