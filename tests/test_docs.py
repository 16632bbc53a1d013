"""The documentation's Python code runs as written, and says what it shows.

Each page's ```python blocks run in order in one namespace (later blocks reuse earlier names), as a reader would
run them; then the claims the page's text makes about the results are checked, so neither the code nor the prose
can rot. The API pages are checked to name importable public objects (the docs build itself, ``mkdocs build
--strict``, runs in CI).
"""

from __future__ import annotations

import importlib
import re
import tempfile
from pathlib import Path

import pytest
import torch

import torchmisspec as tms

DOCS = Path(__file__).resolve().parents[1] / "docs"
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def run_page(path: Path) -> dict:
    namespace: dict = {"__name__": f"docs_{path.stem.replace('-', '_')}"}
    blocks = BLOCK.findall(path.read_text())
    assert blocks, f"{path.name}: no ```python blocks"
    for block in blocks:
        exec(compile(block, str(path), "exec"), namespace)
    return namespace


def check_index(ns: dict) -> None:
    assert ns["pred"].shape == (20, 11, 2)
    assert 0 < ns["tms"].correction_error(ns["gp"], ns["system"]) < float("inf")


def check_learn_and_predict(ns: dict) -> None:
    assert ns["trajs"].states.shape == (30, 11, 2)
    assert ns["oracle"].inputs.shape == (330, 2)
    # "noise_variance ... should come out close to the true noise variance 1e-4"
    assert 0.5e-4 < ns["gp"].noise_variance < 2e-4
    # "Both GPs cut the error of the uncorrected model; the one trained on finite differences ... does far better"
    assert ns["error_oracle"] < ns["no_correction"]
    assert ns["error_central"] < 0.1 * ns["error_oracle"]
    assert ns["mse_oracle"] > 0
    assert ns["posterior"].mean.shape == ns["posterior"].stddev.shape == (1, 2)
    # "gp.predict(x) is a shortcut for gp.posterior().predict(x)"; the covariance's diagonal is its variance
    assert ns["post"].covariance(ns["x"]).shape == (1, 1, 1) and ns["post"].weights.shape == (330, 2)
    assert float(ns["post"].covariance(ns["x"])[0, 0, 0]) == pytest.approx(float(ns["posterior"].variance[0, 0]))
    # "The corrected trajectories are closer to the truth than the misspecified ones, by a factor that grows with
    # the quality of the samples"
    assert ns["corrected"].shape == (10, 61, 2)
    # "scaled by the smallest factor c under which the held-out observed states lie in the band 90 % of the time"
    assert ns["calibration"].coverage >= 0.9 and ns["calibration"].folds == 5
    assert ns["calibrated"].samples.shape == (64, 10, 61, 2)
    assert ns["rmse_central"] < ns["rmse_corrected"] < ns["rmse_misspecified"]
    # "Uncertainty bands": shapes as stated, and the band covers a fraction of the true states
    assert ns["bands"].samples.shape == (64, 10, 61, 2) and ns["lower"].shape == (10, 61, 2)
    assert 0.0 <= float(ns["inside"]) <= 1.0


def check_design(ns: dict) -> None:
    plan, plain, constrained = ns["plan"], ns["plain"], ns["constrained"]
    # "at most 4 per experiment ... every experiment keeps its first state ... few samples go late"
    chosen = torch.stack(ns["when"].times)
    assert chosen.shape == (9, 4) and bool((chosen[:, 0] == 0).all())
    assert float((chosen > 3.0).double().mean()) < 0.25
    # "never returns a worse design than it was given"
    assert ns["better"].information_gain >= ns["better"].start_gain
    assert ns["candidates"].shape == (169, 2)
    assert len(plan) == 9
    # "the marginal gains in plan.gains never increase"
    assert bool((plan.gains[1:] <= plan.gains[:-1] + 1e-9).all())
    # "the first four picks are the corners of D and the fifth its centre"
    first = plan.points[:5]
    assert torch.allclose(first[:4].abs(), torch.ones(4, 2, dtype=first.dtype))
    assert torch.allclose(first[4], torch.zeros(2, dtype=first.dtype), atol=1e-12)
    # "pick the same set; lazy greedy needs fewer gain evaluations"
    assert plain.indices.tolist() == plan.indices.tolist()
    assert plan.evaluations < plain.evaluations
    # "each draw is about half of the 169 candidates and the gain a few percent below lazy greedy's"
    quick = ns["quick"]
    assert 60 <= quick.diagnostics["sample_size"] <= 110
    assert 0.95 <= quick.information_gain / plan.information_gain < 1.0
    # "The unconstrained design puts more than 3 experiments on the left, so the capacity binds; the constrained
    # design gives up a little information"
    region = ns["region"]
    assert int((region[plan.indices] == 0).sum()) > 3
    assert int((region[constrained.indices] == 0).sum()) <= 3
    assert constrained.information_gain < plan.information_gain
    # "more information about F than the average random design, and more than the best of these 20 random ones"
    random_gains = ns["random_gains"]
    assert random_gains.shape == (20,)
    assert plan.information_gain > float(random_gains.max()) > float(random_gains.mean())


def check_own_system(ns: dict) -> None:
    data, loaded = ns["data"], ns["loaded"]
    assert data.times.shape == (4, 81) and data.states.shape == (4, 81, 2)
    # "the loaded trajectories are identical"
    assert torch.equal(loaded.states, data.states) and torch.equal(loaded.times, data.times)
    # "Experiments of different lengths": T=51..81
    assert ns["ragged"].is_ragged and ns["ragged"].lengths == (81, 71, 61, 51)
    # "Missing values and names": 4 missing entries, no sample where omega is missing
    assert ns["gappy"].num_missing == 4 and (ns["gappy"].num_samples, len(ns["gappy_samples"])) == (324, 323)
    errors, gps = ns["errors"], ns["gps"]
    central, smooth = "central, order 4", "smooth, window 11, degree 3"
    # "On precise states, fourth-order differences are nearly exact and beat the local fit"
    assert errors[central, "precise"] < errors[smooth, "precise"]
    # "On noisy states ... the local fit wins"
    assert errors[smooth, "noisy"] < errors[central, "noisy"]
    # "gp.noise_variance ... is larger for the noisy finite differences than for the local fit"
    assert gps[central, "noisy"].noise_variance > gps[smooth, "noisy"].noise_variance
    # "The corrected pendulum slows down as the real one does; the frictionless model does not"
    assert ns["rmse_corrected"] < 0.2 * ns["rmse_frictionless"]
    # "One call does all of this": a cross-validated lengthscale that improves on the known model
    assert ns["auto"].cross_validation_.improves
    # "a single term omega" when the feature kernel is chosen
    if ns["auto"].kernel == "features":
        assert [t.name for t in ns["auto"].terms(["omega"])] == ["omega"]


def check_sequential(ns: dict) -> None:
    # "the lengthscale to a fraction of D's width": half of [-1, 1]
    assert ns["prior"].lengthscale == pytest.approx(1.0)
    tells = [h for h in ns["campaign"].history if h["event"] == "tell"]
    assert len(tells) == 4 and [h["samples"] for h in tells] == [33, 66, 99, 132]
    # "learning its hyperparameters ... once the data hold refit_after samples (default 4 T)": 44 samples
    assert [h["learned"] for h in tells] == [False, True, True, True]
    # "It falls from the first round to the last"
    assert tells[-1]["error"] < tells[0]["error"]
    # "pilot=2 makes the first two experiments random"
    assert ns["campaign"].history[0]["pilot"] == 2 and ns["campaign"].history[0]["gains"][:2] == [None, None]
    # "the resumed campaign picks what the uninterrupted one would"
    assert ns["resumed"].asked == ns["campaign"].asked
    # "its first picks are the corners"; the domain design: "the centre first, then no corner"
    corners = {(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)}
    assert {tuple(p) for p in ns["information"].points.tolist()} == corners
    dom = ns["domain"].points
    assert torch.allclose(dom[0], torch.zeros(2, dtype=dom.dtype), atol=1e-12)
    assert not {tuple(p) for p in dom.tolist()} & corners


def check_kernels(ns: dict) -> None:
    gp, g_gp, plain = ns["gp"], ns["g_gp"], ns["plain"]
    score = {r["kernel"]: r["score"] for r in gp.model_selection_}
    # "The feature kernel wins: its score is several nats above the stationary kernels'"
    assert gp.kernel == "features"
    assert score["features"] > max(score["rbf"], score["matern52"]) + 3
    # "The first output keeps y1^2, within two standard deviations of 0.01, and nothing else."
    # "The second output keeps no term."
    (t,) = gp.terms(["y1", "y2"])
    assert (t.output, t.name) == (0, "y1^2") and abs(t.mean - 0.01) < 2 * t.std
    # "y2 stays below 0.85"
    assert float(ns["samples"].inputs[:, 1].abs().max()) < 0.85
    # "a term the data could not decide on (the second output's y2^2 here) widens the bands without moving the mean"
    every = {(t.output, t.name): t for t in gp.terms(["y1", "y2"], all_terms=True)}
    y2 = every[1, "y2^2"]
    assert y2.weight == 0 and 0.05 < y2.inclusion < 0.95
    assert float(gp.covar_module.base_kernel.spread.reshape(2, -1)[1, 5]) > 0  # y2^2 of the second output
    # plain relevance: "It finds y2^2 for the second output, but weak spurious terms survive beside it, with error
    # bars that include 0."
    terms = plain.terms(["y1", "y2"])
    assert (1, "y2^2") in {(t.output, t.name) for t in terms}
    spurious = [t for t in terms if (t.output, t.name) not in ((0, "y1^2"), (1, "y2^2"))]
    assert spurious and all(abs(t.mean) < 2 * t.std for t in spurious)
    # "the library plus an RBF term scores far above the library alone ... library_suffices_ is False ... auto keeps
    # the RBF, unless the Matern kernel outscores it by the margin, even where features+rbf has the higher score"
    g_score = {r["kernel"]: r["score"] for r in g_gp.model_selection_}
    ff = next(r for r in g_gp.model_selection_ if r["kernel"] == "features+rbf")
    assert ff["score"] > ff["library_score"] + 3 and g_gp.library_suffices_ is False  # vs the library it nests
    assert g_gp.kernel == ("matern52" if g_score["matern52"] >= g_score["rbf"] + 3 else "rbf")
    assert not any(r["eligible"] for r in g_gp.model_selection_ if r["kernel"] in ("features", "features+rbf"))
    # "A kernel of your own": registered, fitted, and its paths drawn
    assert ns["rq"].kernel == "rational_quadratic" and ns["rq"].lengthscale > 0
    assert ns["paths"](ns["samples"].inputs[:3]).shape == (4, 3, 2)
    assert tms.CorrectionGP(kernel="rational_quadratic").kernel_spec.alpha == 2.0


def check_overview(ns: dict) -> None:
    assert len(ns["plan"].indices) == 9 and ns["plan"].information_gain > 0
    campaign = ns["campaign"]
    assert campaign.num_experiments == 6 and Path("campaign.pt").is_file()


def check_chemostat(ns: dict) -> None:
    # "Both come back close to the truth ... with standard deviations far inside their priors"
    for name, true, prior_sd in (("kd", 0.05, 0.03), ("q", 2.0, 1.0)):
        mean, sd = ns[name]
        assert abs(mean - true) <= 3 * sd and sd < 0.25 * prior_sd
    assert ns["gp"].parameters_.identified == (True, True)
    # "The corrected model's error is a small fraction of the known model's"
    assert ns["error_corrected"] < 0.3 * ns["error_known"]
    assert ns["bands"].samples.shape == (32, 10, 30, 2)
    # "kd is flagged not identified ... q ... is still determined"
    assert ns["gp_absorbing"].parameters_.identified == (False, True)
    assert any("kd: posterior sd" in str(w.message) for w in ns["caught"])
    # the substrate not measured, the yield uncertain: "seen through X"; "just over two posterior standard deviations";
    # "predicted far better than by the known model"; the posterior is kept by save/load
    found = ns["gp_partly"]
    assert "F on dS/dt: seen through X" in found.identifiability_.summary()
    post = found.parameters_
    assert not post.linear and post.identified == (True, True)
    z = (post.mean - torch.tensor([0.05, 0.5], dtype=torch.float64)).abs() / post.stddev
    assert bool((z <= 2.5).all()) and bool((z > 2).any())
    known_x = tms.trajectory_rmse(ns["known_x"], ns["reference_x"])
    assert tms.trajectory_rmse(ns["predicted_x"], ns["reference_x"]) < 0.3 * known_x
    with tempfile.TemporaryDirectory() as folder:
        found.save(Path(folder) / "m.pt")
        loaded = tms.CorrectionGP.load(Path(folder) / "m.pt").parameters_
    assert torch.equal(loaded.mean, post.mean) and torch.equal(loaded.covariance, post.covariance)


def check_partial_measurements(ns: dict) -> None:
    # "F on dcentral/dt: measured directly"; "the tissue's stay near 0"
    assert ns["gp"].identifiability_.summary().startswith("F on dcentral/dt: measured directly")
    assert float(ns["gp"].initial_states_[:, 1].abs().max()) < 0.05
    # "Both compartments are predicted far better than by the known model, the tissue too"
    for j in range(2):
        known = float(tms.trajectory_rmse(ns["known_only"][..., j : j + 1], ns["reference"][..., j : j + 1]))
        corrected = float(tms.trajectory_rmse(ns["bands"].mean_path[..., j : j + 1], ns["reference"][..., j : j + 1]))
        assert corrected < 0.2 * known
    assert 0.85 <= ns["calibration"].coverage <= 0.95
    # "The message names the component, what is measured, and the fixes"
    assert "acts on y1" in ns["message"] and "measured: y0" in ns["message"] and "correction_outputs" in ns["message"]
    # "F on the bound ligand is seen through the total"; "far better than by the known model"
    assert ns["fit"].identifiability_.summary().startswith("F on dbound/dt: seen through total")
    known = float(tms.trajectory_rmse(ns["ligand_known"], ns["ligand_reference"]))
    assert float(tms.trajectory_rmse(ns["ligand_predicted"], ns["ligand_reference"])) < 0.1 * known


def check_populations(ns: dict) -> None:
    from torchmisspec.population.design import misfit_scale
    from torchmisspec.population.uncertainty import standard_errors

    fit = ns["fit"]
    values, (_, _, se_effects) = fit.nlme.values, fit.nlme.standard_errors
    # "kept a correction F"; "about 0.012 per kg (standard error 0.0045), holds the truth's 0.01 within one SE"
    assert not fit.known_model
    assert abs(float(values.effects[0, 0]) - 0.012) < 0.001 and abs(float(se_effects[0, 0]) - 0.0045) < 0.0005
    # "That standard error counts F's own uncertainty ... here hardly at all"
    without = standard_errors(values, fit.nlme.modes, fit.nlme.covariates)[2]
    assert fit.nlme.shifts is not None and float(without[0, 0]) <= float(se_effects[0, 0]) < 1.05 * float(without[0, 0])
    assert fit.gp.pipeline_.samples.in_noise_space  # "a population's default"
    assert abs(float(values.effects[0, 0]) - 0.01) < float(se_effects[0, 0])
    # "the residuals' scale is about 25 % ... with F = 0"; "with F it is about 3.6 %"
    assert abs(float(fit.classical.modes.scale[0]) - 0.25) < 0.01
    assert abs(float(fit.nlme.modes.scale[0]) - 0.036) < 0.002
    # "the typical k, about 0.54 / h"; "within 6 % of the truth's from 0.5 to 4 mg/L, within about 15 % at 8 mg/L"
    assert abs(float(values.mean[0].exp()) - 0.54) < 0.01
    ratios = ns["fitted"] / ns["truth"]
    assert bool(((ratios[:4] - 1).abs() < 0.06).all()) and abs(float(ratios[4]) - 1.15) < 0.03
    # "the spread ... about 0.18 in log k (interval 0.13-0.28), is below the truth's 0.3, its interval not reaching it"
    low, high = fit.nlme.intervals().spread[0].tolist()
    assert abs(float(values.spread[0]) - 0.18) < 0.01 and abs(low - 0.13) < 0.005 and abs(high - 0.28) < 0.005
    assert high < 0.3
    # "This patient's band from two samples holds 88 % of their samples, the population's 96 %"; "its variance in log k
    # from about 0.042 to 0.0065"; "the spread's square (0.031)"
    inside = []
    for p in (ns["alone"], ns["updated"]):
        lo, hi = p.posterior.measured(fit.noise, fit.nlme.modes.scale).interval(0.9)
        inside.append(float(((ns["samples"] >= lo[0]) & (ns["samples"] <= hi[0])).float().mean()))
    assert inside[0] >= 0.9 and 0.75 <= inside[1] < 0.95
    # "keeps the paths under F's mean (with F's draws ... about as well)"; "narrows their spread to 0.89 times, holding
    # 0.90 of the held-out patients' later samples (0.94 before)"
    cal = fit.calibration
    assert cal.first == 2 and not cal.f_draws and abs(cal.score - cal.other) < 0.05 * cal.score
    assert abs(cal.scale - 0.89) < 0.05 and cal.band.coverage >= 0.9 and abs(cal.band.coverage_at_one - 0.94) < 0.02
    assert ns["updated"].band_scale == cal.scale
    # "the textbook prediction interval held 0.93 of their later samples, and is narrowed to 0.83 times its spread"
    alone = fit.calibration_alone
    assert alone.first == 0 and abs(alone.scale - 0.83) < 0.05 and abs(alone.band.coverage_at_one - 0.93) < 0.02
    assert alone.band.coverage >= 0.9 and ns["alone"].band_scale == alone.scale
    assert abs(float(ns["alone"].eta_covariance[0, 0]) - 0.042) < 0.002
    assert abs(float(values.spread[0]) ** 2 - 0.031) < 0.002
    assert abs(float(ns["updated"].eta_covariance[0, 0]) - 0.0065) < 0.0005
    assert float(ns["alone"].eta_covariance[0, 0]) > float(values.spread[0]) ** 2
    # "between 8 and 10.5 hours"; "about 3.4 % ... and a little more (4 %) at 12 hours"
    assert all(8.0 <= t <= 10.5 for t in ns["design"].times.tolist())
    # "were F known exactly the design would go later, to 10-11 hours"
    import torchmisspec.population.design as design_module

    exact = design_module._correction_deviations
    design_module._correction_deviations = lambda *args: None
    try:
        # a generator of its own: without one the drawn subjects came from torch's global stream, so from whichever
        # tests ran before in the same worker (seed 4 of 0-5 gives 9.75 h, hence "about")
        again = design_module.design_subject(
            fit,
            ns["grid"],
            4,
            initial_states=[[6.0]],
            covariates={"weight": 80.0},
            generator=torch.Generator().manual_seed(0),
        )
    finally:
        design_module._correction_deviations = exact
    assert all(10.0 <= t <= 11.0 for t in again.times.tolist())
    scale = misfit_scale(fit, ns["grid"])[:, 0]
    assert abs(float(scale[4:-4].median()) - 0.034) < 0.002 and abs(float(scale[-1]) - 0.04) < 0.003


PAGES = {
    "index.md": check_index,
    "overview.md": check_overview,
    "tutorials/learn-and-predict.md": check_learn_and_predict,
    "tutorials/design.md": check_design,
    "tutorials/own-system.md": check_own_system,
    "tutorials/chemostat.md": check_chemostat,
    "tutorials/partial-measurements.md": check_partial_measurements,
    "tutorials/populations.md": check_populations,
    "tutorials/sequential.md": check_sequential,
    "tutorials/kernels.md": check_kernels,
}


#: Pages that fit through the ODE several times (a minute or more on 2 cores): run in the slow tier (make test-slow).
SLOW_PAGES = {"tutorials/chemostat.md", "tutorials/partial-measurements.md", "tutorials/populations.md"}


@pytest.mark.parametrize(
    "page", [pytest.param(p, marks=pytest.mark.slow) if p in SLOW_PAGES else p for p in sorted(PAGES)]
)
def test_page_runs_and_its_claims_hold(page, tmp_path, monkeypatch, one_thread):
    monkeypatch.chdir(tmp_path)  # a page that writes files writes them here
    namespace = run_page(DOCS / page)
    PAGES[page](namespace)


def test_every_tutorial_with_code_is_run():
    pages = [DOCS / "index.md", DOCS / "overview.md", *sorted((DOCS / "tutorials").glob("*.md"))]
    with_code = {str(p.relative_to(DOCS)) for p in pages if BLOCK.search(p.read_text())}
    assert with_code == set(PAGES), "add the page (and the claims its text makes) to PAGES"


def test_api_pages_name_public_importable_objects():
    identifiers = []
    for page in sorted((DOCS / "api").glob("*.md")):
        identifiers += re.findall(r"^::: ([\w.]+)", page.read_text(), re.M)
    assert identifiers
    for identifier in identifiers:
        assert not any(part.startswith("_") for part in identifier.split(".")), identifier
        parts = identifier.split(".")
        for i in range(len(parts), 0, -1):  # the longest importable module prefix, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ModuleNotFoundError:
                continue
            for attr in parts[i:]:
                obj = getattr(obj, attr)
            break
        else:
            pytest.fail(f"{identifier}: not importable")
