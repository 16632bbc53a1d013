"""The demo (torchmisspec.paper.demo.linear_demo): paper §5.1 end to end, as ``torchmisspec demo`` runs it."""

import json
from pathlib import Path

import pytest

import torchmisspec as tms
from torchmisspec.paper.demo import DemoResult, linear_demo


def test_demo_runs_paper_5_1_and_saves_what_it_returns(tmp_path):
    result = linear_demo(tmp_path / "demo", n_train=15, n_test=5, seed=3)
    assert isinstance(result, DemoResult)
    assert result.rmse_corrected < result.rmse_misspecified  # the correction helps on new initial conditions
    assert result.integrated_error < result.energy_of_F  # the estimate of F beats the zero estimate over D
    system = tms.systems.paper_linear()
    assert result.energy_of_F == tms.integrated_norm(system.true_correction, system.domain)
    assert result.energy_of_G_plus_F == tms.integrated_norm(system.true_rhs, system.domain)
    assert min(result.lengthscale, result.outputscale, result.noise_variance) > 0 and result.rhs_evaluations > 0
    saved = json.loads((tmp_path / "demo" / "results.json").read_text())
    assert saved == json.loads(json.dumps(result.to_dict()))
    assert saved["rmse_ratio"] == result.rmse_corrected / result.rmse_misspecified
    assert [Path(f).name for f in result.figures] == ["trajectories.png", "error_map.png"]
    for name in result.figures:
        assert Path(name).read_bytes()[:4] == b"\x89PNG"


def test_demo_without_output_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = linear_demo(None, n_train=10, n_test=3)
    assert result.figures == [] and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"n_train": 0}, "n_train: expected an integer >= 1, got 0"),
        ({"n_test": 2.5}, r"n_test: expected an integer >= 1, got 2.5"),
        ({"num_times": 1}, "num_times: expected an integer >= 2, got 1"),
    ],
)
def test_demo_rejects_bad_sizes(kwargs, message):
    with pytest.raises(tms.InputError, match=message):
        linear_demo(None, **kwargs)
