"""scripts/benchmark_posterior.py runs in its smoke mode and renders every figure it measured."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_smoke_run_prints_the_block():
    out = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "benchmark_posterior.py"), "--smoke"],
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    ).stdout
    assert "<!-- study:costs:start -->" in out and "<!-- study:costs:end -->" in out
    assert "posterior / predict: **" in out and "nan" not in out
