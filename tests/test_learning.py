"""fit_correction: the lengthscale by cross-validation on held-out trajectories, and single shooting (issue 9)."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.fit import LENGTHSCALE_GRID, cross_validate_lengthscale
from torchmisspec.systems import LinearField, MisspecifiedSystem

DT = torch.float64


def noisy(system, K: int, T: int, t_end: float, noise: float, seed: int) -> tms.Trajectories:
    g = torch.Generator().manual_seed(seed)
    y0 = torch.rand(K, system.state_dim, generator=g, dtype=DT) * 2 - 1
    clean = tms.simulate(system, y0, torch.linspace(0, t_end, T, dtype=DT))
    rms = clean.states.pow(2).mean(dim=(0, 1)).sqrt()
    return tms.Trajectories(
        clean.times, clean.states + noise * rms * torch.randn(clean.states.shape, generator=g, dtype=DT)
    )


@pytest.fixture(scope="module")
def linear_noisy():
    """paper 5.1 observed as states: K = 10, T = 11 on [0, 6], 1 % state noise; and a test set."""
    system = tms.systems.paper_linear()
    traj = noisy(system, 10, 11, 6.0, 1e-2, seed=100)
    y0 = torch.rand(25, 2, generator=torch.Generator().manual_seed(7), dtype=DT) * 2 - 1
    times = torch.linspace(0, 6, 61, dtype=DT)
    true = tms.simulate(system, y0, times).states
    base = tms.trajectory_rmse(tms.simulate(system, y0, times, known_only=True).states, true)
    return system, traj, (y0, times, true, float(base))


def ratio(system, gp, test) -> float:
    y0, times, true, base = test
    return float(tms.trajectory_rmse(tms.CorrectedODE(system, gp).predict(y0, times), true)) / base


def test_cross_validation_beats_the_marginal_likelihood_on_noisy_states(linear_noisy, one_thread):
    system, traj, test = linear_noisy
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)  # the estimator self-check warns at 1 % noise
        ml = tms.fit_correction(traj, system, gp=tms.CorrectionGP(), select="evidence")
        cv = tms.fit_correction(traj, system, gp=tms.CorrectionGP())  # the RBF kernel's lengthscale by CV
    assert ml.cross_validation_ is None and cv.cross_validation_ is not None
    # measured: marginal likelihood lengthscale 0.20, ratio 0.77; cross-validated 2.9, ratio 0.18
    assert float(cv.lengthscale) > 5 * float(ml.lengthscale)
    assert ratio(system, cv, test) < 0.3 < ratio(system, ml, test)
    result = cv.cross_validation_
    assert result.improves and result.best_lengthscale == pytest.approx(float(cv.lengthscale), rel=1e-12)
    assert result.best == f"rbf lengthscale={result.best_lengthscale:.4g}"
    assert len(result.scores) == len(result.lengthscales) == len(result.candidates) >= len(LENGTHSCALE_GRID)
    assert min(result.scores) == result.scores[result.index] < result.baseline
    assert list(result.lengthscales) == sorted(result.lengthscales) and result.folds == 5
    assert len(cv.samples_) == 110


def test_single_shooting_is_not_biased_by_noisy_start_states(linear_noisy, one_thread):
    system, traj, test = linear_noisy
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system, gp=tms.CorrectionGP())
    single = tms.fit_trajectories(gp, system, traj)  # the default
    multiple = tms.fit_trajectories(gp, system, traj, shooting="multiple")
    # measured: single 0.24, multiple 0.37 (errors in variables: noisy start states teach a spurious damping)
    assert ratio(system, single, test) < 0.8 * ratio(system, multiple, test)
    assert single.initial_states_.shape == (10, 2) and single.state_noise_.shape == (2,)
    # the estimated initial states move by about the noise level, no more (1 % of the RMS: ~5e-3)
    moved = (single.initial_states_ - traj.initial_conditions).abs().max()
    assert 0 < float(moved) < 5 * float(single.state_noise_.max().sqrt())


def test_no_correction_to_find_warns():
    """The known model is exact (F = 0) and the states are noisy: no correction predicts held-out experiments
    better than the known model, and fit_correction says so and returns the known model (issue 41, do no harm)."""
    A = torch.tensor([[-0.1, 1.0], [-1.0, -0.1]], dtype=DT)
    system = MisspecifiedSystem(LinearField(A), 2, known_matrix=A, name="exact")
    traj = noisy(system, 6, 21, 6.0, 2e-2, seed=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = tms.fit_correction(traj, system, derivative="central", order=4)
    messages = [str(w.message) for w in caught if issubclass(w.category, tms.TorchMisspecWarning)]
    assert any("better than the known model alone" in m and "returning the known model" in m for m in messages)
    assert not gp.cross_validation_.improves and gp.known_model_
    y = torch.randn(4, 2, dtype=DT)
    assert float(gp.predict_mean(y).abs().max()) < 1e-8  # F = 0


def test_fallbacks_and_bad_input(linear_noisy):
    system, traj, _ = linear_noisy
    one = traj[[0]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        # one experiment of 11 times: scored on its two pieces in time (issue 41), each held out in turn
        single = tms.fit_correction(one, system, refine=False)
        assert single.cross_validation_.folds == 2 and len(single.cross_validation_.gains) == 2
        # too short for two pieces of 5 times: nothing to hold out, chosen by evidence (kernel="auto")
        t, y = one.experiments()[0]
        short = tms.fit_correction(tms.Trajectories(t[:9], y[None, :9]), system, refine=False)
        assert short.cross_validation_ is None and short.auto and len(short.model_selection_) == 4
        poly = tms.fit_correction(traj, system, gp=tms.CorrectionGP(kernel="polynomial"))
        # a template without a lengthscale is still scored on held-out experiments (for the warning)
        assert poly.kernel == "polynomial" and poly.cross_validation_.candidates == ("polynomial degree=2",)
        fixed = tms.fit_correction(traj, system, gp=tms.CorrectionGP(lengthscale=2.0))  # scored, not searched
        assert fixed.lengthscale == pytest.approx(2.0) and fixed.cross_validation_.candidates == ("rbf lengthscale=2",)
        # select="evidence" among candidates: the highest evidence score wins, every candidate recorded
        pool = [tms.CorrectionGP(lengthscale=ell) for ell in (0.05, 1.0, 20.0)]
        best = tms.fit_correction(traj, system, candidates=pool, select="evidence", refine=False)
        scores = [r["score"] for r in best.model_selection_]
        assert best.cross_validation_ is None and best.evidence_score == pytest.approx(max(scores), rel=1e-12)
        assert [r["chosen"] for r in best.model_selection_] == [s == max(scores) for s in scores]
        assert not any(c.is_fitted for c in pool)  # the templates are not touched
        # an unfitted kernel="auto" template holds an RBF, yet it is scored as it is (its kernel chosen by
        # evidence), not turned into a grid of RBF lengthscales
        auto = tms.fit_correction(traj, system, gp=tms.CorrectionGP(kernel="auto"), refine=False)
        assert auto.auto and len(auto.model_selection_) == 4 and len(auto.cross_validation_.candidates) == 1
    for bad in ("ml", "foo", None, True, 2.0):
        with pytest.raises(tms.InputError, match=r"select: expected 'cv' \(held-out experiments\) or 'evidence'"):
            tms.fit_correction(traj, system, select=bad)
    with pytest.raises(tms.InputError, match=r"gp: expected a CorrectionGP template or None, got str"):
        tms.fit_correction(traj, system, gp="rbf")
    samples = tms.correction_samples(traj, system, derivative="central")
    with pytest.raises(
        tms.InputError, match=r"expected at least 2 experiments and 2 folds for cross-validation, got K=10, folds=1"
    ):
        cross_validate_lengthscale(system, traj, samples, folds=1)
    with pytest.raises(tms.InputError, match=r"expected the correction samples of these 2 experiments"):
        cross_validate_lengthscale(system, traj[[0, 1]], samples)
    with pytest.raises(tms.InputError, match=r"chooses the lengthscale of a shared RBF or Matern kernel"):
        cross_validate_lengthscale(system, traj, samples, gp=tms.CorrectionGP(lengthscale=1.0))
    with pytest.raises(tms.InputError, match=r"shared RBF or Matern kernel; got kernel 'auto'"):
        cross_validate_lengthscale(system, traj, samples, gp=tms.CorrectionGP(kernel="auto"))
    with pytest.raises(tms.InputError, match=r"lengthscales: expected positive numbers"):
        cross_validate_lengthscale(system, traj, samples, lengthscales=[1.0, -2.0])
    with pytest.raises(
        tms.InputError, match=r"candidates: expected either a gp template or a list of candidates, got both"
    ):
        tms.fit_correction(traj, system, gp=tms.CorrectionGP(), candidates=[tms.CorrectionGP()])
    with pytest.raises(tms.InputError, match=r"candidates: expected a non-empty list of CorrectionGP templates"):
        tms.cross_validate(system, traj, samples, [])
    with pytest.raises(tms.InputError, match=r"candidates: expected a non-empty list of CorrectionGP templates"):
        tms.cross_validate(system, traj, samples, ["rbf"])


def test_fit_trajectories_bad_shooting_and_state_noise(linear_noisy):
    system, traj, _ = linear_noisy
    gp = tms.CorrectionGP(lengthscale=1.0).fit(tms.correction_samples(traj, system, derivative="central"))
    with pytest.raises(tms.InputError, match=r"shooting: expected one of \['single', 'multiple'\], got 'double'"):
        tms.fit_trajectories(gp, system, traj, shooting="double")
    with pytest.raises(tms.InputError, match=r"state_noise: expected a positive number or 2 positive variances"):
        tms.fit_trajectories(gp, system, traj, state_noise=[1e-4, 1e-4, 1e-4])
    with pytest.raises(tms.InputError, match=r"state_noise: expected a positive number or 2 positive variances"):
        tms.fit_trajectories(gp, system, traj, state_noise=[1e-4, -1.0])
    refined = tms.fit_trajectories(gp, system, traj, state_noise=[1e-4, 2e-4], max_iter=2)
    assert refined.state_noise_.tolist() == pytest.approx([1e-4, 2e-4])


def test_student_t_quantiles_and_the_critical_value():
    from torchmisspec.learning.choice.cross_validation import CrossValidation, student_t_quantile

    # reference values of the 97.5 % quantile (standard tables)
    for df, value in ((1, 12.706), (2, 4.303), (3, 3.182), (4, 2.776), (9, 2.262), (29, 2.045), (1000, 1.962)):
        assert student_t_quantile(0.975, df) == pytest.approx(value, rel=2e-3)
    assert student_t_quantile(0.5, 7) == pytest.approx(0.0, abs=1e-12)
    gains = (0.0, -0.02, 2.1, 1.7, 1.48)  # mean 1.05, 2.37 standard errors: not enough with 5 experiments
    cv = CrossValidation(("a",), (None,), (1.0,), 2.0, "a", 5, gains, 0)
    assert cv.improves and cv.critical == pytest.approx(2.776, rel=1e-3) and not cv.significant
    assert CrossValidation(("a",), (None,), (1.0,), 2.0, "a", 5, gains * 4, 0).significant  # 20 experiments


def test_cross_validation_accepts_float32_trajectories_and_templates(one_thread):
    """The held-out field evaluated the GP's kernel on the trajectories' float32 states against its float64 training
    inputs and raised a bare dtype error; the field now follows the GP's dtype and returns the states'."""
    system = tms.systems.paper_linear()
    t = torch.linspace(0, 6, 11, dtype=DT)
    y0 = torch.tensor([[0.5, -0.3], [0.2, 0.4], [-0.5, 0.1], [0.3, 0.3]], dtype=DT)
    traj = tms.simulate(system, y0, t)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp64 = tms.fit_correction(traj.to(torch.float32), system, derivative="central", gp=tms.CorrectionGP())
        gp32 = tms.fit_correction(traj, system, derivative="central", gp=tms.CorrectionGP(dtype=torch.float32))
    assert gp64.dtype == DT and gp32.dtype == torch.float32
    assert gp64.cross_validation_ is not None and gp32.cross_validation_ is not None
    samples = tms.correction_samples(traj.to(torch.float32), system, derivative="central")
    result, _ = tms.cross_validate(system, traj.to(torch.float32), samples, [tms.CorrectionGP(lengthscale=1.0)])
    assert all(torch.isfinite(torch.tensor(result.scores)))


def test_a_known_model_that_diverges_does_not_break_the_defaults(one_thread):
    """G(y) = y^2 blows up from y0 > 1 before t = 1, while the truth G + F = -y is stable: the case a correction
    exists to fix. derivative='auto' (whose self-check integrates G alone) and the cross-validation baseline (G
    alone on each held-out experiment) raised IntegrationError; now the check uses the experiments G can be
    integrated over (with a warning) and the baseline scores the others as infinite error."""
    system = tms.MisspecifiedSystem(lambda y: y**2, 1, correction=lambda x: -(x**2) - x, name="blowup_known")
    t = torch.linspace(0, 1, 21, dtype=DT)
    y0 = torch.tensor([[2.0], [1.5], [0.8], [0.5], [-0.5], [-1.0]], dtype=DT)
    traj = tms.simulate(system, y0, t)
    with pytest.warns(tms.TorchMisspecWarning, match=r"experiments \[0, 1\].*the other 4"):
        samples = tms.correction_samples(traj, system)
    assert torch.isfinite(samples.targets).all()
    gp = tms.fit_correction(traj, system, derivative="central", gp=tms.CorrectionGP())
    cv = gp.cross_validation_
    assert cv.baseline == float("inf") and cv.significant
    assert sum(g == float("inf") for g in cv.gains) == 2
    pred = tms.CorrectedODE(system, gp).predict(y0, t)
    assert float((pred - traj.states).abs().max()) < 1e-2
    # G diverges from every experiment (the lynx data, issue 41): nothing ranks the estimators, so the first that
    # fits is used, with a warning (it raised IntegrationError: a crash of the default fit)
    with pytest.warns(tms.TorchMisspecWarning, match="diverges from all 2.*central \\{'order': 4\\}.*unchecked"):
        unranked = tms.correction_samples(traj[[0, 1]], system)
    assert unranked.derivative == "central order=4" and bool(torch.isfinite(unranked.targets).all())


def test_given_candidates_are_never_silently_replaced(one_thread, monkeypatch):
    """With one experiment the given candidates were ignored and a default RBF returned; when every candidate failed
    cross-validation, the same happened without a word about it."""
    system = tms.systems.paper_linear()
    t = torch.linspace(0, 6, 21, dtype=DT)
    one = tms.simulate(system, torch.tensor([[0.5, -0.3]], dtype=DT), t)
    poly = tms.CorrectionGP(kernel="polynomial", degree=2)
    gp = tms.fit_correction(one, system, candidates=[poly], derivative="oracle")
    # one experiment of 21 times: the candidates scored on its 3 pieces in time (issue 41)
    assert gp.kernel == "polynomial" and gp.cross_validation_.candidates == ("polynomial degree=2",)
    assert gp.cross_validation_.folds == 3
    # too short for two pieces, nothing to hold out: the candidates compete by evidence (every one recorded)
    short = tms.simulate(system, torch.tensor([[0.5, -0.3]], dtype=DT), t[:9])
    chosen = tms.fit_correction(short, system, candidates=[poly, tms.CorrectionGP()], derivative="oracle")
    assert chosen.cross_validation_ is None and [r["kernel"] for r in chosen.model_selection_] == ["polynomial", "rbf"]
    with pytest.raises(tms.InputError, match="non-empty list of CorrectionGP templates, got an empty list"):
        tms.fit_correction(one, system, candidates=[], derivative="oracle")
    many = tms.simulate(system, torch.tensor([[0.5, -0.3], [0.2, 0.4], [-0.5, 0.1]], dtype=DT), t)
    from torchmisspec.learning.choice import cross_validation

    monkeypatch.setattr(cross_validation, "_held_out_errors", _fail_held_out)
    with pytest.warns(tms.TorchMisspecWarning, match="every candidate failed cross-validation.*polynomial"):
        gp = tms.fit_correction(many, system, candidates=[poly], derivative="oracle")
    assert gp.kernel == "polynomial" and gp.cross_validation_.scores == (float("inf"),)


def _fail_held_out(system, trajectories, field=None, noise=None):
    if field is None:  # the known model's baseline
        return torch.ones(trajectories.num_experiments, dtype=DT)
    raise tms.IntegrationError("made to fail")


def test_fit_correction_shows_progress_by_default_and_is_silent_when_asked(capfd):
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(2)
    y0 = torch.rand(4, 2, generator=g, dtype=torch.float64) * 2 - 1
    trajs = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=torch.float64))
    tms.fit_correction(trajs, system, derivative="central", refine=False, progress=False)
    assert capfd.readouterr().err == ""
    tms.fit_correction(trajs, system, derivative="central", refine=False)
    assert "fit_correction: cross-validating candidate models" in capfd.readouterr().err


def test_thinned_keeps_each_experiments_ends_evenly_spaced():
    x = torch.arange(30, dtype=DT).unsqueeze(1)
    experiment = torch.tensor([0] * 20 + [1] * 8 + [2] * 2)
    samples = tms.CorrectionSamples(x, x.clone(), x.clone(), experiment)
    assert samples.thinned(30) is samples and samples.thinned(100) is samples
    kept = samples.thinned(15)
    rows = kept.inputs.squeeze(1).long().tolist()
    assert rows == [0, 2, 4, 6, 8, 11, 13, 15, 17, 19, 20, 22, 25, 27, 28, 29]  # 10 of 20, 4 of 8, both of 2
    assert kept.experiment.tolist() == [0] * 10 + [1] * 4 + [2] * 2
    for bad in (0, -3, 2.5, "10"):
        with pytest.raises(tms.InputError, match="at_most: expected an integer >= 1"):
            samples.thinned(bad)


def test_the_model_is_chosen_on_a_subsample_and_fitted_on_all(linear_noisy, one_thread, monkeypatch):
    """Above SELECTION_SAMPLES the candidates are scored on each experiment's samples thinned evenly; the chosen
    template is then fitted on every sample (its lengthscale the chosen one); at or below it nothing changes."""
    import torchmisspec.learning.fit as learning

    system, traj, test = linear_noisy
    monkeypatch.setattr(learning, "SELECTION_SAMPLES", 40)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system, gp=tms.CorrectionGP(), progress=False)
    cv = gp.cross_validation_
    assert cv.samples == 40 and gp.train_inputs_.shape[0] == len(gp.samples_) == 110
    assert float(gp.lengthscale) == pytest.approx(cv.best_lengthscale, rel=1e-12)
    assert ratio(system, gp, test) < 0.3  # still the right model (the full choice: 0.18, above)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        auto = tms.fit_correction(traj, system, select="evidence", progress=False)  # kernel="auto" on 40
    chosen = [r for r in auto.model_selection_ if r["chosen"]]
    assert auto.train_inputs_.shape[0] == 110 and len(chosen) == 1 and chosen[0]["kernel"] == auto.kernel
    monkeypatch.setattr(learning, "SELECTION_SAMPLES", 110)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        full = tms.fit_correction(traj, system, gp=tms.CorrectionGP(), progress=False)
    assert full.cross_validation_.samples == 110


def test_the_lengthscale_grid_is_the_median_distance_between_distinct_inputs():
    """The grid's scale counts each pair of distinct inputs once, no input with itself: torch.cdist's matrix-product
    form gave some self-distances of ~3e-8 instead of 0, how many depending on rounding, so the same samples in other
    units (a power of ten there and back) moved the grid by 7.5e-4 (tests/test_scale.py's RBF case)."""
    from torchmisspec.gp._exact import median_distance

    g = torch.Generator().manual_seed(0)
    X = torch.cat([torch.randn(89, 2, generator=g, dtype=DT) * torch.tensor([1.5, 0.2], dtype=DT), torch.zeros(1, 2)])
    X = torch.cat([X, X[:5]])  # repeated inputs: not distinct, left out
    i, j = torch.triu_indices(X.shape[0], X.shape[0], 1)
    pairs = (X[i] - X[j]).pow(2).sum(-1).sqrt()
    assert median_distance(X) == float(pairs[pairs > 0].median())
    S = torch.tensor([1e3, 1e-2], dtype=DT)
    assert median_distance(X * S / S) == pytest.approx(median_distance(X), rel=1e-14)
