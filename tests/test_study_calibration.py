"""The calibration study script (issue 10) runs in its smoke mode and reports coverages in [0, 1]."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_smoke_run_writes_coverages(study_smoke):
    result, _ = study_smoke("study_calibration.py")
    assert result["smoke"] is True and len(result["settings"]) == 4
    for setting in result["settings"]:
        assert len(setting["runs"]) == result["config"]["realizations"]
        for method in ("fixed", "laplace"):
            means = [setting["coverage"][method][k][0] for k in ("0.5", "0.9", "0.95")]
            assert all(0.0 <= m <= 1.0 for m in means) and means == sorted(means)  # wider bands cover more
        for run in setting["runs"]:  # the two halves of the output times: their mean is the whole span's coverage
            for method in ("fixed", "laplace"):
                first, second = run[method]["coverage_halves_90"]
                assert 0.0 <= first <= 1.0 and 0.0 <= second <= 1.0
                assert abs(0.5 * (first + second) - run[method]["coverage"]["0.9"]) < 1e-12
