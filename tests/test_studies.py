import json

import pytest
import torch

import torchmisspec as tms
from torchmisspec.studies import StudyResult, gravity_study, grid_candidates, linear_study


def test_grid_candidates_is_the_paper_grid():
    grid = grid_candidates(((-1.0, 1.0), (-1.0, 1.0)), 13)
    assert grid.shape == (169, 2)
    assert torch.unique(grid[:, 0]).numel() == 13 and grid.min() == -1 and grid.max() == 1


def test_designed_sets_beat_random_sets_on_paper_linear_fast():
    """Paper 5.1/Fig 5, fast version: over the mid range of K the designed sets have lower mean error."""
    result = linear_study(ks=(8, 12), realizations=6, resolution=41)
    design, random = result.errors["design"].mean(0), result.errors["random"].mean(0)
    assert (design < random).all(), (design, random)
    # the data-driven estimator, which ignores G, is far worse at small K
    assert (result.errors["data-driven"].mean(0) > 2 * design).all()


@pytest.mark.slow
def test_designed_sets_beat_random_sets_on_paper_linear_over_many_realizations():
    result = linear_study(ks=(6, 8, 10, 12, 16), realizations=30, resolution=61)
    mean_ratio, stderr = result.ratio("design", "random")
    assert sum(mean_ratio) / len(mean_ratio) < 0.95
    assert all(m < 1.0 + s for m, s in zip(mean_ratio, stderr, strict=True))


def test_study_result_summary_table_and_files(tmp_path):
    errors = {
        "a": torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=torch.float64),
        "b": torch.tensor([[2.0, 2.0], [2.0, 8.0]], dtype=torch.float64),
    }
    result = StudyResult("toy", [1, 2], errors, {"ref": 5.0}, "error")
    mean, stderr = result.summary()["a"]
    assert mean == [2.0, 3.0] and stderr == pytest.approx([1.0, 1.0])
    ratio, ratio_se = result.ratio("a", "b")
    assert ratio == pytest.approx([(0.5 + 1.5) / 2, (1.0 + 0.5) / 2])
    assert "| 1 | 2 ± 1 |" in result.table([("a", "b")])
    paths = result.save(tmp_path, ratios=[("a", "b")])
    assert json.loads(paths["json"].read_text())["ratios"]["a/b"][0] == pytest.approx(ratio)
    assert paths["figure"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_gravity_study_runs_and_reports_every_strategy():
    result = gravity_study(ks=(1, 3), realizations=2, n_candidates=40, resolution=21)
    assert set(result.errors) == {"misspecified-aided", "agnostic", "random"}
    for err in result.errors.values():
        assert err.shape == (2, 2) and torch.isfinite(err).all() and (err > 0).all()
    assert result.references["mean energy of F"] > 0


def test_study_bad_input():
    with pytest.raises(tms.InputError, match=r"ks: expected numbers of experiments in \[1, 169\], got \[0, 2\]"):
        linear_study(ks=(0, 2), realizations=1)
    with pytest.raises(tms.InputError, match="realizations: expected a positive integer, got 0"):
        linear_study(ks=(2,), realizations=0)


def test_data_driven_view_learns_the_whole_field(linear_system):
    view = tms.systems.data_driven(linear_system)
    y = torch.rand(7, 2, dtype=torch.float64)
    torch.testing.assert_close(view.known(y), torch.zeros_like(y))
    torch.testing.assert_close(view.true_correction(y), linear_system.true_rhs(y))
    with pytest.raises(tms.InputError, match="the data-driven view needs a correction on all components"):
        tms.systems.data_driven(tms.systems.paper_gravity())
