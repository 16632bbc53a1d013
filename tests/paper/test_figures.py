"""The paper's figures (torchmisspec.paper.figures) and their command line: smoke run of every figure,
results.json contents, what the figures draw, the shared Session, argument errors."""

import importlib.util
import json
import math
import warnings
from pathlib import Path

import pytest
import torch

from torchmisspec import InputError, correction_error
from torchmisspec.paper import _layout
from torchmisspec.paper import figures as rep

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "reproduce_paper.py"
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
        ("bands", "coverage_of_true_paths", "0.9"),
        ("bands", "mean_band_width_90"),
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
        ("bands", "coverage_of_true_paths", "0.9"),
        ("bands", "mean_band_width_90"),
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
    """The smoke reproduction of every figure through the script's main (a few seconds); any DeprecationWarning
    the paper's code raises (from torch or gpytorch) fails it."""
    out = tmp_path_factory.mktemp("repro")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", category=DeprecationWarning, module=r"torchmisspec\.paper")
        code = _load_script().main(["--all", "--smoke", "--quiet", "--out", str(out)])
    return code, out, json.loads((out / "results.json").read_text())


def test_smoke_writes_every_figure(smoke_run):
    code, out, _ = smoke_run
    assert code == 0
    for n in range(1, 9):
        png = out / f"fig{n}.png"
        assert png.is_file(), f"missing {png.name}"
        assert png.read_bytes()[:8] == PNG_MAGIC
    for extra in ("fig3_design.png", "fig6_design.png", "fig1_bands.png", "fig6_bands.png"):
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
    for fig in ("fig1", "fig6"):  # the bands: nested, and wider bands cover more
        cover = f[fig]["bands"]["coverage_of_true_paths"]
        assert 0 <= cover["0.5"] <= cover["0.9"] <= cover["0.95"] <= 1 and f[fig]["bands"]["mean_band_width_90"] > 0
    # Fig 6/7 use the candidates and designs of the Fig 8 study (same seed)
    designs = f["fig8"]["meta"]["designs"]
    assert designs["agnostic"] == f["fig6"]["agnostic"]["indices"]
    assert designs["misspecified-aided"] == f["fig6"]["misspecified-aided"]["indices"]


def test_a_figure_runs_alone_and_its_session_holds_the_shared_fit(tmp_path):
    session = rep.Session(0)
    assert repr(session) == "Session(seed=0, built=[])"
    numbers = rep.figure_2(tmp_path, smoke=True, session=session)
    assert (tmp_path / "fig2.png").read_bytes()[:8] == PNG_MAGIC
    assert numbers["files"] == ["fig2.png"]
    assert not (tmp_path / "results.json").exists()
    json.dumps(numbers)  # JSON-serialisable as returned
    assert repr(session) == "Session(seed=0, built=['linear_fit'])"
    fit = session.linear_fit
    assert session.linear_fit is fit  # built once, reused by the next figure given this session
    # the figure's number is the error of the fit the session holds (the one Fig 1 plots)
    assert numbers["integrated_error"]["paper_prior"] == correction_error(fit.gp_paper, fit.system)
    # no fitted model is cached in the module: no lru_cache, no module-level Session
    caches = [n for n, v in vars(rep).items() if hasattr(v, "cache_info") or isinstance(v, rep.Session)]
    assert caches == []


def test_session_seed_must_match(tmp_path):
    with pytest.raises(InputError, match=r"session: expected a Session for seed=1 \(the seed argument\), got seed=0"):
        rep.figure_2(tmp_path, smoke=True, seed=1, session=rep.Session(0))
    with pytest.raises(InputError, match="session: expected a Session or None, got dict"):
        rep.figure_2(tmp_path, smoke=True, session={})
    with pytest.raises(InputError, match="seed: expected an integer, got 1.5"):
        rep.Session(1.5)


def test_figure_3_draws_both_designs_and_both_corrected_models(tmp_path, monkeypatch):
    """Fig 3 is composed from the generic plotting functions with the paper's explicit styles."""
    saved = {}
    monkeypatch.setattr(
        _layout, "save", lambda fig, path, files: (saved.__setitem__(path.name, fig), files.append(path.name))
    )
    numbers = rep.figure_3(tmp_path, smoke=True)
    assert numbers["files"] == ["fig3_design.png", "fig3.png"]
    left, right = saved["fig3.png"].axes
    markers = {c.get_label(): c for c in left.collections}
    design, random = markers["design (K=9)"], markers["random (K=9)"]
    assert tuple(design.get_edgecolor()[0]) == (0.0, 0.0, 0.0, 1.0)  # black squares
    assert design.get_sizes()[0] == 90.0 and random.get_sizes()[0] == 45.0
    labels = [t.get_text() for t in right.get_legend().get_texts()]
    assert labels == [
        "true (G + F)",
        "misspecified (G)",
        "corrected, design-trained",
        "corrected, random-trained",
        "initial conditions",
    ]
    n_plot = numbers["setup"]["n_plotted"]
    assert len(right.lines) == 4 * n_plot + 1  # four sets of trajectories and the initial conditions
    assert saved["fig3_design.png"].axes[0].get_title() == left.get_title()


def test_quiet_prints_nothing_selected_figures_only_and_threads_are_restored(tmp_path, capsys):
    before = torch.get_num_threads()
    argv = [
        "--figure",
        "2",
        "--figure",
        "4",
        "--smoke",
        "--quiet",
        "--threads",
        str(before + 1),
        "--out",
        str(tmp_path),
    ]
    assert _load_script().main(argv) == 0
    assert capsys.readouterr().out == ""
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["figures"]) == {"fig2", "fig4"}
    assert not (tmp_path / "fig1.png").exists()
    assert results["torch_threads"] == before + 1  # the run used the threads asked for ...
    assert torch.get_num_threads() == before  # ... and gave the previous setting back


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
    with pytest.raises(InputError, match="threads: expected an integer >= 1"):
        rep.reproduce([2], tmp_path, threads=threads)
