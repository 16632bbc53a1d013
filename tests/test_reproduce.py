"""The paper-reproduction command: smoke run of every figure, results.json contents, argument errors."""

import importlib.util
import json
import math
from pathlib import Path

import pytest
import torch

from torchmisspec import InputError
from torchmisspec import reproduce as rep

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "reproduce_paper.py"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# figure -> paths (into its numbers) of the key numbers that must be finite
KEY_NUMBERS = {
    "fig1": [
        ("fits", "paper_prior", "rmse_ratio"),
        ("fits", "marginal_likelihood", "rmse_ratio"),
        ("fits", "paper_prior", "rmse_corrected"),
        ("fits", "marginal_likelihood", "hyperparameters", "lengthscale"),
        ("rmse_ratio_over_realizations", "paper_prior", "mean"),
        ("rmse_ratio_over_realizations", "paper_prior", "stderr"),
    ],
    "fig2": [
        ("integrated_error", "paper_prior"),
        ("energy_of_F",),
        ("energy_of_G_plus_F",),
        ("near_vs_far", "far_over_near"),
    ],
    "fig3": [
        ("design", "information_gain_nats"),
        ("random", "information_gain_nats"),
        ("design", "gains_nats"),
        ("design", "test_rmse_corrected"),
        ("random", "test_rmse_corrected"),
        ("design", "integrated_error"),
        ("random", "integrated_error"),
        ("misspecified_test_rmse",),
    ],
    "fig4": [("design", "integrated_abs_error"), ("random", "integrated_abs_error"), ("design_over_random",)],
    "fig5": [
        ("summary", "design", "mean"),
        ("summary", "random", "mean"),
        ("summary", "data-driven", "mean"),
        ("ratios", "design/random", "mean"),
        ("ratios", "design/random", "stderr"),
        ("ratios", "data-driven/design", "mean"),
        ("references", "energy of F"),
        ("references", "energy of G + F"),
    ],
    "fig6": [
        ("agnostic", "test_rmse_corrected"),
        ("misspecified-aided", "test_rmse_corrected"),
        ("misspecified_test_rmse",),
        ("agnostic", "gains_nats_own_criterion"),
        ("misspecified-aided", "exact_information_gain_nats"),
    ],
    "fig7": [("agnostic", "mse_over_D"), ("misspecified-aided", "mse_over_D"), ("mean_energy_of_F_over_D",)],
    "fig8": [
        ("summary", "agnostic", "mean"),
        ("summary", "misspecified-aided", "mean"),
        ("ratios", "misspecified-aided/agnostic", "mean"),
        ("ratios", "misspecified-aided/agnostic", "stderr"),
        ("references", "mean energy of F"),
    ],
}


def _load_script():
    spec = importlib.util.spec_from_file_location("reproduce_paper", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _get(data: dict, path: tuple):
    for key in path:
        data = data[key]
    return data


def _all_finite(value) -> bool:
    if isinstance(value, list):
        return len(value) > 0 and all(_all_finite(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    """The smoke reproduction of every figure through the script's main (a few seconds)."""
    out = tmp_path_factory.mktemp("repro")
    code = _load_script().main(["--all", "--smoke", "--quiet", "--out", str(out)])
    return code, out, json.loads((out / "results.json").read_text())


def test_smoke_writes_every_figure(smoke_run):
    code, out, _ = smoke_run
    assert code == 0
    for n in range(1, 9):
        png = out / f"fig{n}.png"
        assert png.is_file(), f"missing {png.name}"
        assert png.read_bytes()[:8] == PNG_MAGIC
    for extra in ("fig3_design.png", "fig6_design.png"):
        assert (out / extra).read_bytes()[:8] == PNG_MAGIC


def test_smoke_results_json_has_every_figure_with_finite_numbers(smoke_run):
    _, out, results = smoke_run
    assert results["smoke"] is True
    assert results["seed"] == 0
    assert set(results["figures"]) == {f"fig{n}" for n in range(1, 9)}
    for key, paths in KEY_NUMBERS.items():
        numbers = results["figures"][key]
        for path in paths:
            assert _all_finite(_get(numbers, path)), f"{key}: {'/'.join(path)} = {_get(numbers, path)!r}"
        assert results["seconds"][key] >= 0
        for name in numbers["files"]:
            assert (out / name).is_file()
    assert results["seconds"]["total"] >= max(v for k, v in results["seconds"].items() if k != "total")
    # the smoke sizes are recorded, so a reader can tell a smoke run from a full one
    assert results["realizations"] == {"fig1": 3, "fig5": 2, "fig8": 3}
    assert results["figures"]["fig5"]["ks"] == [1, 2, 4, 9]


def test_smoke_numbers_tell_the_papers_story(smoke_run):
    """Robust, seeded checks of what the figures show (not of the fine statistics)."""
    f = smoke_run[2]["figures"]
    assert f["fig1"]["fits"]["paper_prior"]["rmse_ratio"] < 1  # the correction helps
    assert f["fig1"]["fits"]["paper_prior"]["hyperparameters"]["outputscale"] == pytest.approx(4e-5)
    assert f["fig2"]["integrated_error"]["paper_prior"] < f["fig2"]["energy_of_F"]
    assert f["fig3"]["design"]["information_gain_nats"] > f["fig3"]["random"]["information_gain_nats"]
    assert f["fig3"]["design"]["information_gain_nats"] == pytest.approx(sum(f["fig3"]["design"]["gains_nats"]))
    assert len(f["fig3"]["design"]["indices"]) == 9
    assert f["fig5"]["ratios"]["data-driven/design"]["mean"][0] > 1  # data-driven worst at K = 1
    assert len(f["fig6"]["agnostic"]["indices"]) == len(f["fig6"]["misspecified-aided"]["indices"]) == 7
    assert not set(f["fig6"]["test_indices"]) & set(f["fig6"]["agnostic"]["indices"])
    # Fig 6/7 use the candidates and designs of the Fig 8 study (same seed)
    designs = f["fig8"]["meta"]["designs"]
    assert designs["agnostic"] == f["fig6"]["agnostic"]["indices"]
    assert designs["misspecified-aided"] == f["fig6"]["misspecified-aided"]["indices"]


def test_a_figure_runs_alone(tmp_path):
    numbers = rep.figure_2(tmp_path, smoke=True)
    assert (tmp_path / "fig2.png").read_bytes()[:8] == PNG_MAGIC
    assert numbers["files"] == ["fig2.png"]
    assert not (tmp_path / "results.json").exists()
    json.dumps(numbers)  # JSON-serialisable as returned


def test_quiet_prints_nothing_and_selected_figures_only(tmp_path, capsys):
    assert _load_script().main(["--figure", "2", "--figure", "4", "--smoke", "--quiet", "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out == ""
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["figures"]) == {"fig2", "fig4"}
    assert not (tmp_path / "fig1.png").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "one of the arguments --figure --all is required"),
        (["--smoke"], "one of the arguments --figure --all is required"),
        (["--all", "--figure", "1"], "not allowed with argument"),
        (["--figure", "9"], "invalid choice: 9"),
        (["--figure", "one"], "invalid int value"),
    ],
)
def test_argument_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        _load_script().main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_negative_threads_is_an_argument_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        _load_script().main(["--figure", "2", "--threads", "-1", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "--threads: expected an integer >= 0" in capsys.readouterr().err


@pytest.mark.parametrize("figures", [[], [0], [9], ["x"]])
def test_reproduce_rejects_bad_figure_lists(figures, tmp_path):
    with pytest.raises(InputError, match="figures: expected"):
        rep.reproduce(figures, tmp_path)


@pytest.mark.parametrize("threads", [0, -2, 1.5, True])
def test_reproduce_rejects_bad_threads(threads, tmp_path):
    with pytest.raises(InputError, match="threads: expected a positive integer or None"):
        rep.reproduce([2], tmp_path, threads=threads)


def test_reproduce_restores_the_thread_count(tmp_path):
    before = torch.get_num_threads()
    results = rep.reproduce([2], tmp_path, smoke=True, threads=1)
    assert results["torch_threads"] == 1
    assert torch.get_num_threads() == before
