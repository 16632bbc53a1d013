"""``scripts/study_real_data.py`` (issue 41's real-data suite): its smoke run, the classical answer, the folds."""

import math
from pathlib import Path

import pytest
import torch

import torchmisspec as tms
from torchmisspec import datasets
from torchmisspec.paper import real_data, study_real_data

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_smoke_run_records_every_fold(study_smoke):
    saved, proc = study_smoke("study_real_data.py")
    assert saved["smoke"] is True and list(saved["runs"]) == ["orange", "hare_lynx"]
    for runs in saved["runs"].values():
        (run,) = runs
        assert isinstance(run["exceptions"], list)
        for e in run["exceptions"]:  # recorded with their type and message, never hidden
            assert e["type"] and e["message"]
        if not run["exceptions"]:
            assert math.isfinite(run["default_log_rmse"]) and math.isfinite(run["classical_log_rmse"])
            assert 0 <= run["covered"] <= run["scored"] == 6
    assert "| orange | 1 |" in proc.stdout and "| hare_lynx | 1 |" in proc.stdout


def test_classical_fit_recovers_the_parameters_of_simulated_growth():
    system = datasets.load("orange").system
    truth = torch.tensor([2.5e-3, 180.0], dtype=torch.float64)
    t = torch.tensor([118.0, 484, 664, 1004, 1231, 1372, 1582], dtype=torch.float64)
    y0 = torch.tensor([[30.0], [25.0], [35.0]], dtype=torch.float64)
    trajs = tms.simulate(system.at(truth), y0, t)
    theta, start = real_data.classical_fit(system, trajs, "relative")
    assert torch.allclose(theta, truth, rtol=1e-3)
    assert torch.equal(start, y0)  # the first rows give every initial state


def test_classical_fit_estimates_initial_states_the_data_do_not_give():
    system = datasets.load("lynx").system
    truth = torch.tensor([0.5, 4e-4, 0.9], dtype=torch.float64)
    t = torch.arange(20, dtype=torch.float64)
    y = tms.simulate(system.at(truth), torch.tensor([[700.0, 1500.0]], dtype=torch.float64), t).states.clone()
    y[..., 0] = float("nan")  # the hares are never measured
    theta, start = real_data.classical_fit(system, tms.Trajectories(t, y), "counts")
    assert torch.allclose(theta, truth, rtol=1e-2) and abs(float(start[0, 0]) - 700.0) < 7.0


def test_folds_follow_the_protocols():
    flu = real_data.folds(datasets.load("influenza"), study_real_data.PROTOCOLS["influenza"])
    assert [f["label"] for f in flu] == [f"origin {d}" for d in range(6, 12)]
    first = flu[0]  # S and R not measured: forecast from day 0, the last 3 times scored
    assert first["train"].num_times == 7 and first["times"].tolist() == list(range(10))
    assert first["held_out"][:, 1].tolist() == [258, 233, 189]
    pelts = real_data.folds(datasets.load("hare_lynx"), study_real_data.PROTOCOLS["hare_lynx"])
    assert pelts[0]["times"].tolist() == [1909, 1910, 1911, 1912]  # both measured: from the origin's measurement
    orange = real_data.folds(datasets.load("orange"), {})
    assert len(orange) == 5 and orange[2]["train"].num_experiments == 4 and orange[2]["held_out"].shape == (6, 1)


def test_log_rmse_scores_counts_with_log1p_and_a_failed_prediction_as_nan():
    data = torch.tensor([[0.0], [9.0]], dtype=torch.float64)
    assert real_data.log_rmse(data.clone(), data, "counts") == 0.0
    assert math.isclose(
        real_data.log_rmse(torch.tensor([[0.0], [99.0]]).double(), data, "counts"), math.log(10) / 2**0.5
    )
    assert math.isnan(real_data.log_rmse(torch.tensor([[1.0], [float("nan")]]).double(), data + 1, "relative"))


def test_sindy_runs_where_every_state_is_measured_and_says_where_it_does_not():
    """The suite's SINDy column (issue 41, item 1): a forecast on the Orange trees (every state measured), 'does not
    apply' on the influenza outbreak (only I measured)."""
    from torchmisspec import datasets
    from torchmisspec.paper import real_data
    from torchmisspec.paper.study_real_data import PROTOCOLS

    for name, applies in (("orange", True), ("influenza", False)):
        data = datasets.load(name)
        out: dict = {}
        real_data.run_sindy(data, real_data.folds(data, PROTOCOLS[name])[0], out.update)
        assert out["sindy_applies"] is applies
        if applies:
            assert "sindy_error" not in out and 0.0 < out["sindy_log_rmse"] < 1.0
