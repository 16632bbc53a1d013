"""The paper's studies (Figs 5 and 8): the claims they support, on reduced set-ups, and the StudyResult bookkeeping.

Every claim is asserted as a paired difference larger than twice its own standard error over the run's
realizations, not against a typed-in number. The reduced set-ups were chosen from measurements (docs in each test).
"""

import json
import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.paper.studies import StudyResult, gravity_study, linear_study


def paired(study: StudyResult, better: str, worse: str, ks) -> tuple[float, float]:
    """Mean over realizations of (worse - better) averaged over ``ks``, and its standard error."""
    cols = [study.ks.index(k) for k in ks]
    diff = (study.errors[worse] - study.errors[better])[:, cols].mean(1)
    return float(diff.mean()), float(diff.std() / math.sqrt(diff.numel()))


# ------------------------------------------------------------------------------------------------------ Fig 5
@pytest.fixture(scope="module")
def linear_reduced():
    """Fig 5 reduced: 30 realizations, K up to 10, 21 x 21 quadrature (about 1-2 s).

    Measured with seed 0: data-driven / design from 14.3 (K=1) to 2.0 (K=8), each > 10 standard errors; over
    K = 5-10 design / random = 0.80 (difference 5.6 standard errors; seeds 0-9 give 2.6-6.0); over K = 2-4
    design / random = 1.51 (11 standard errors).
    """
    return linear_study((1, 2, 3, 4, 5, 6, 8, 10), realizations=30, seed=0, resolution=21)


def test_fig5_data_driven_estimator_is_worst_at_every_k(linear_reduced):
    """Paper §5.2: the fully data-driven GP (no known G) estimates F worse than design + misspecified model."""
    for k in linear_reduced.ks:
        mean, se = paired(linear_reduced, "design", "data-driven", [k])
        assert mean > 2 * se > 0, f"K={k}: data-driven - design = {mean:.3g} +- {se:.2g}"


def test_fig5_design_beats_random_sets_over_the_mid_range(linear_reduced):
    """Paper §5.2: designed sets beat random sets; measured to hold on average over K = 5-10."""
    mean, se = paired(linear_reduced, "design", "random", (5, 6, 8, 10))
    assert mean > 2 * se > 0, f"random - design over K = 5-10: {mean:.3g} +- {se:.2g}"


def test_fig5_design_loses_to_random_sets_at_k_2_to_4(linear_reduced):
    """Where the reproduction differs from the paper (docs/reproduction.md, Fig 5): with K <= 4 the design is the
    grid's corners and centre-less, and random sets do better. Kept as a test so the documented verdict stays true."""
    mean, se = paired(linear_reduced, "random", "design", (2, 3, 4))
    assert mean > 2 * se > 0, f"design - random over K = 2-4: {mean:.3g} +- {se:.2g}"


@pytest.mark.slow
def test_fig5_claims_over_the_papers_k_range():
    """The same claims over the paper's K = 1-20, with 60 realizations and 51 x 51 quadrature (about 7 s).

    Measured with seed 1: data-driven - design > 14 standard errors at every K; over K = 5-10 design / random =
    0.85 (5.3 standard errors; seed 2: 5.6). Over K = 5-20 the margin is smaller (2.5-3.6 standard errors with 30
    realizations and seeds 1-3), so the test keeps to K = 5-10.
    """
    study = linear_study(realizations=60, seed=1, resolution=51)
    for k in study.ks:
        mean, se = paired(study, "design", "data-driven", [k])
        assert mean > 2 * se > 0, f"K={k}: data-driven - design = {mean:.3g} +- {se:.2g}"
    mean, se = paired(study, "design", "random", (5, 6, 8, 10))
    assert mean > 2 * se > 0, f"random - design over K = 5-10: {mean:.3g} +- {se:.2g}"


# ------------------------------------------------------------------------------------------------------ Fig 8
def test_fig8_aided_design_beats_agnostic_design_at_small_k():
    """Paper §5.3 / Fig 8: the misspecified-aided design has a lower mean squared error of F_hat over D than the
    agnostic design at small K.

    With one candidate set the designs are fixed and the noise standard errors are tiny, so the ordering depends on
    the set (docs/reproduction.md: with seed 0 the aided design is worse at K = 1-3). The claim is therefore tested
    over candidate sets: 200 realizations, each with its own 30 candidates and designs, K = 1 and 2, 21 x 21
    quadrature (a few seconds). Measured: aided / agnostic 0.84, the paired difference 6.1 standard errors; over
    16 other blocks of 100-200 candidate sets it stays above 2.5 standard errors.
    """
    study = gravity_study(
        (1, 2), realizations=200, seed=0, n_candidates=30, resolution=21, include_random=False, redraw_candidates=True
    )
    mean, se = paired(study, "misspecified-aided", "agnostic", (1, 2))
    assert mean > 2 * se > 0, f"agnostic - aided over K = 1, 2: {mean:.3g} +- {se:.2g}"


def test_gravity_study_fixed_candidates_reuse_one_set_and_its_designs():
    result = gravity_study(ks=(1, 3), realizations=2, n_candidates=40, resolution=21)
    assert set(result.errors) == {"misspecified-aided", "agnostic", "random"}
    for err in result.errors.values():
        assert err.shape == (2, 2) and torch.isfinite(err).all() and (err > 0).all()
    # the designs are fixed, so with fixed candidates only the noise differs between realizations
    assert len(result.meta["designs"]["agnostic"]) == 3
    assert result.references["mean energy of F"] > 0
    candidates = tms.design.candidates.orbits(40, generator=torch.Generator().manual_seed(0))
    plan = tms.design.agnostic(
        candidates,
        3,
        system=tms.systems.paper_gravity(),
        times=torch.linspace(0, 3, 20, dtype=torch.float64),
        gp=tms.CorrectionGP(lengthscale=1.0, outputscale=1e-3, noise_variance=1e-4),
    )
    assert result.meta["designs"]["agnostic"] == plan.indices.tolist()


def test_gravity_study_redraws_candidate_sets_per_realization():
    result = gravity_study(ks=(1, 2), realizations=3, n_candidates=20, resolution=11, redraw_candidates=True)
    designs = result.meta["designs"]
    assert [len(d) for d in designs["misspecified-aided"]] == [2, 2, 2]
    # realization r uses the candidates of seed + r: its designs are those of the fixed-candidate study of that seed
    alone = gravity_study(ks=(1, 2), realizations=1, seed=2, n_candidates=20, resolution=11)
    for name in ("misspecified-aided", "agnostic"):
        assert designs[name][2] == alone.meta["designs"][name]
    assert designs["agnostic"][0] != designs["agnostic"][1] or designs["agnostic"][1] != designs["agnostic"][2]


# ------------------------------------------------------------------------------------------- StudyResult
def test_study_result_summary_ratio_difference_table_and_files(tmp_path):
    errors = {
        "a": torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=torch.float64),
        "b": torch.tensor([[2.0, 2.0], [2.0, 8.0]], dtype=torch.float64),
    }
    result = StudyResult("toy", [1, 2], errors, {"ref": 5.0}, "error")
    mean, stderr = result.summary()["a"]
    assert mean == [2.0, 3.0] and stderr == pytest.approx([1.0, 1.0])
    ratio, ratio_se = result.ratio("a", "b")
    assert ratio == pytest.approx([(0.5 + 1.5) / 2, (1.0 + 0.5) / 2])
    assert ratio_se == pytest.approx([0.5, 0.25])  # std of (0.5, 1.5) / sqrt(2); of (1.0, 0.5) / sqrt(2)
    diff, diff_se = result.difference("b", "a")
    assert diff == pytest.approx([0.0, 2.0]) and diff_se == pytest.approx([1.0, 2.0])
    assert "| 1 | 2 ± 1 |" in result.table([("a", "b")])
    paths = result.save(tmp_path, ratios=[("a", "b")])
    assert json.loads(paths["json"].read_text())["ratios"]["a/b"][0] == pytest.approx(ratio)
    assert paths["figure"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(tms.InputError, match=r"strategy: expected one of \['a', 'b'\], got 'c'"):
        result.ratio("a", "c")


def test_study_bad_input():
    with pytest.raises(tms.InputError, match=r"ks: expected numbers of experiments in \[1, 169\], got \[0, 2\]"):
        linear_study(ks=(0, 2), realizations=1)
    with pytest.raises(tms.InputError, match="realizations: expected an integer >= 1, got 0"):
        linear_study(ks=(2,), realizations=0)
    with pytest.raises(tms.InputError, match=r"ks: expected numbers of experiments in \[1, 10\], got \[1, 11\]"):
        gravity_study(ks=(1, 11), realizations=1, n_candidates=10)
    with pytest.raises(tms.InputError, match="n_candidates: expected an integer >= 1, got 2.5"):
        gravity_study(realizations=1, n_candidates=2.5)


def test_data_driven_view_learns_the_whole_field(linear_system):
    """The data-driven estimator of Fig 5 is a GP of G + F: the view of the system it learns."""
    view = tms.systems.data_driven(linear_system)
    y = torch.rand(7, 2, dtype=torch.float64)
    torch.testing.assert_close(view.known(y), torch.zeros_like(y))
    torch.testing.assert_close(view.true_correction(y), linear_system.true_rhs(y))
    with pytest.raises(tms.InputError, match="the data-driven view needs a correction on all components"):
        tms.systems.data_driven(tms.systems.paper_gravity())
