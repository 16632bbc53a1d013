"""design.Campaign: the sequential ask / tell loop (issue 11, point 5)."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.design.candidates import grid
from torchmisspec.paper._setup import LINEAR_PRIOR, NOISE_STD

DT = torch.float64
TIMES = torch.linspace(0, 6, 11, dtype=DT)


def _campaign(**kw):
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 7)
    options = dict(derivative="oracle", noise_std=NOISE_STD, refit_after=30, seed=3)
    options.update(kw)
    return system, design.Campaign(system, cand, TIMES, tms.CorrectionGP(**LINEAR_PRIOR), **options)


def _run(system, camp, rounds, k=2):
    for _ in range(rounds):
        camp.tell(tms.simulate(system, camp.ask(k), TIMES))


def test_first_ask_is_the_prior_design_and_later_asks_condition_on_the_data():
    system, camp = _campaign()
    first = camp.ask(3)
    plan = design.greedy(camp.candidates, 3, system=system, times=TIMES, gp=camp.prior)
    torch.testing.assert_close(first, camp.candidates[plan.indices])
    camp.tell(tms.simulate(system, first, TIMES))
    assert camp.gp.is_fitted and camp.num_samples == 33 and camp.pending == []
    second = camp.ask(2)
    assert camp.history[-1]["design"]["conditioned"] == 33
    assert camp.history[-1]["design"]["proxy"] == "corrected"
    pool = sorted(camp.remaining.tolist() + camp.history[-1]["indices"])
    expected = design.greedy(camp.candidates[pool], 2, system=system, times=TIMES, gp=camp.gp)
    assert [pool[i] for i in expected.indices.tolist()] == camp.history[-1]["indices"]
    torch.testing.assert_close(second, expected.points)
    assert not set(camp.history[-1]["indices"]) & set(camp.history[0]["indices"])


def test_tell_refits_once_there_are_enough_samples_and_records_errors():
    system, camp = _campaign(refit_after=30)
    camp.tell(tms.simulate(system, camp.ask(2), TIMES))  # 22 samples: prior hyperparameters
    assert camp.history[-1]["learned"] is False
    assert camp.history[-1]["hyperparameters"]["lengthscale"] == pytest.approx(LINEAR_PRIOR["lengthscale"])
    camp.tell(tms.simulate(system, camp.ask(1), TIMES))  # 33 samples: learned
    assert camp.history[-1]["learned"] is True
    assert camp.gp.fixed.get("lengthscale") is None
    errors = [h["error"] for h in camp.history if h["event"] == "tell"]
    assert len(errors) == 2 and all(e > 0 for e in errors)
    assert errors[-1] == pytest.approx(tms.correction_error(camp.gp, system, resolution=51))


def test_pilot_batch_is_random_and_seeded():
    system, a = _campaign(pilot=3, seed=11)
    _, b = _campaign(pilot=3, seed=11)
    _, c = _campaign(pilot=3, seed=12)
    pa, pb, pc = a.ask(4), b.ask(4), c.ask(4)
    torch.testing.assert_close(pa, pb)
    assert a.history[-1]["pilot"] == 3 and a.history[-1]["gains"][:3] == [None] * 3  # drawn, not designed
    assert not torch.equal(pa[:3], pc[:3])


def test_unrequested_experiments_are_accepted_and_noted():
    system, camp = _campaign()
    asked = camp.ask(1)
    extra = torch.tensor([[0.3, -0.2]], dtype=DT)
    camp.tell(tms.simulate(system, torch.cat([asked, extra]), TIMES))
    entry = camp.history[-1]
    assert entry["unrequested"] == 1 and "not asked for" in entry["note"]
    assert camp.measured[-1] == -1 and camp.pending == []


def test_save_load_round_trip_and_resumed_campaign_picks_the_same(tmp_path):
    system, camp = _campaign(pilot=1)
    _run(system, camp, 3)
    pending = camp.ask(2)  # saved with a pending ask
    path = camp.save(tmp_path / "campaign.pt")
    resumed = design.Campaign.load(path, system)
    assert resumed.history == camp.history
    assert resumed.pending == camp.pending and resumed.asked == camp.asked
    assert resumed.num_samples == camp.num_samples
    x = torch.rand(5, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(resumed.gp.predict_mean(x), camp.gp.predict_mean(x))
    for c in (camp, resumed):
        c.tell(tms.simulate(system, pending, TIMES))
    _run(system, camp, 2)
    _run(system, resumed, 2)
    assert resumed.asked == camp.asked
    assert resumed.history[-1]["error"] == pytest.approx(camp.history[-1]["error"], rel=1e-9)


def test_bad_input_loses_nothing(tmp_path):
    system, camp = _campaign()
    _run(system, camp, 1)
    before = (list(camp.history), camp.num_samples, list(camp.pending))
    with pytest.raises(tms.InputError, match="k: expected a positive integer"):
        camp.ask(0)
    with pytest.raises(tms.InputError, match="at most the 47 candidates"):
        camp.ask(48)
    with pytest.raises(tms.ShapeError, match="dimension 2"):
        camp.tell(tms.Trajectories(TIMES, torch.zeros(1, 11, 3, dtype=DT)))
    with pytest.raises(tms.InputError, match="Trajectories"):
        camp.tell(torch.zeros(1, 11, 2))
    assert (camp.history, camp.num_samples, camp.pending) == before
    with pytest.raises(tms.InputError, match="criterion"):
        _campaign(criterion="entropy")
    with pytest.raises(tms.InputError, match="domain"):
        _campaign(criterion="domain", domain=((-1, 1),))
    # damaged files
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a campaign")
    with pytest.raises(tms.InputError, match="could not be read safely"):
        design.Campaign.load(bad, system)
    torch.save({"format": "something else"}, bad)
    with pytest.raises(tms.InputError, match="Campaign file .* got format .something else."):
        design.Campaign.load(bad, system)
    good = camp.save(tmp_path / "good.pt")
    blob = torch.load(good, weights_only=True)
    blob["asked"] = [10_000]
    torch.save(blob, bad)
    with pytest.raises(tms.InputError, match="'asked'.*damaged"):
        design.Campaign.load(bad, system)
    other = tms.systems.paper_gravity()
    with pytest.raises(tms.InputError, match="expected the system the campaign was run with, 'paper_linear'"):
        design.Campaign.load(good, other)


def test_information_campaign_with_a_domain_scores_errors_there():
    """A domain with the information criterion is only where the error is scored; asks still work."""
    system, camp = _campaign(domain=((-0.5, 0.5), (-0.5, 0.5)))
    _run(system, camp, 1)
    assert camp.history[-1]["error"] == pytest.approx(
        tms.correction_error(camp.gp, system, domain=((-0.5, 0.5), (-0.5, 0.5)), resolution=51)
    )


def test_duplicate_candidates_match_one_ask_each():
    system = tms.systems.paper_linear()
    cand = torch.tensor([[0.5, 0.5], [0.1, -0.2], [0.5, 0.5]], dtype=DT)
    camp = design.Campaign(system, cand, TIMES, tms.CorrectionGP(**LINEAR_PRIOR), derivative="oracle", pilot=3)
    asked = camp.ask(3)
    camp.tell(tms.simulate(system, asked, TIMES))
    assert camp.pending == [] and sorted(camp.measured) == [0, 1, 2]
    assert camp.history[-1]["unrequested"] == 0


def test_a_failed_tell_leaves_the_random_state_as_it_was(monkeypatch):
    system, camp = _campaign(pilot=2)
    _, twin = _campaign(pilot=2)
    for c in (camp, twin):
        c.tell(tms.simulate(system, c.ask(2), TIMES))
    y0 = camp.ask(1)
    twin.ask(1)
    traj = tms.simulate(system, y0, TIMES)
    original = design.Campaign._fit

    def broken(self, *args):
        raise tms.FittingError("made to fail")

    monkeypatch.setattr(design.Campaign, "_fit", broken)
    with pytest.raises(tms.FittingError):
        camp.tell(traj)
    monkeypatch.setattr(design.Campaign, "_fit", original)
    camp.tell(traj)  # the retry draws the noise an uninterrupted campaign draws
    twin.tell(traj)
    torch.testing.assert_close(torch.cat(camp._targets), torch.cat(twin._targets))


def test_a_feature_prior_keeps_its_price_and_library_when_the_campaign_learns():
    """The campaign's learner is built from the prior's settings: a feature kernel's price per term and its
    library survive (they were dropped, so a refit used the default price and the monomials)."""
    system = tms.systems.paper_linear()
    library = [lambda x: x[..., 0] ** 2, lambda x: x[..., 1] ** 2]
    prior = tms.CorrectionGP(kernel="features", min_gain=1.7, library=library, library_names=["a", "b"])
    camp = design.Campaign(system, grid(system.domain, 5), TIMES, prior, refit_after=1, derivative="oracle")
    X = torch.rand(30, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    gp, note = camp._fit([X], [0.01 * X**2], [None])
    assert note == "learned"
    assert gp.min_gain == 1.7 and gp.feature_names() == ["a", "b"]


def test_a_fitted_gp_starts_the_campaign_from_its_data_and_noisy_first_states_match_their_asks(tmp_path):
    """A campaign started from a fitted GP (the loop fit_correction -> Campaign) conditions its first design on the
    samples that GP was fitted on, and a told experiment whose first state was measured with noise is matched to
    the ask it answers (it was counted as 'not asked for')."""
    system = tms.systems.paper_linear()
    cand = grid(system.domain, 7)
    g = torch.Generator().manual_seed(0)
    traj = tms.simulate(system, cand[[0, 6, 42]], TIMES)
    samples = tms.correction_samples(traj, system, derivative="oracle", noise_std=NOISE_STD, generator=g)
    fitted = tms.CorrectionGP(per_output=True).fit(samples)
    camp = design.Campaign(system, cand, TIMES, fitted, derivative="oracle", noise_std=NOISE_STD)
    assert camp.num_samples == 33 and camp.gp is fitted
    picks = camp.ask(2)
    assert camp.history[-1]["design"]["conditioned"] == 33
    expected = design.greedy(cand, 2, system=system, times=TIMES, gp=fitted)
    assert camp.history[-1]["indices"] == expected.indices.tolist()
    noisy = picks + 1e-3 * torch.randn(picks.shape, generator=g, dtype=DT)  # a measured first state
    told = tms.simulate(system, noisy, TIMES)
    camp.tell(told)
    assert camp.history[-1]["unrequested"] == 0 and camp.pending == [] and camp.num_samples == 55
    path = camp.save(tmp_path / "camp.pt")
    again = design.Campaign.load(path, system)
    torch.testing.assert_close(again.ask(1), camp.ask(1))


def test_tell_can_be_told_which_asks_the_experiments_answer():
    system, camp = _campaign(refit_after=0)
    asked = camp.ask(3)
    far = asked + 0.5  # first states nowhere near the asks: matched by position when told so
    camp.tell(tms.simulate(system, far[:2], TIMES), asked="pending")
    assert camp.history[-1]["unrequested"] == 0 and camp.pending == camp.history[0]["indices"][2:]
    with pytest.raises(tms.InputError, match=r"asked: expected pending asks \(each once\) or -1"):
        camp.tell(tms.simulate(system, far[2:], TIMES), asked=[camp.history[0]["indices"][0]])
    with pytest.raises(tms.InputError, match="asked: expected 'pending' or a list of 1"):
        camp.tell(tms.simulate(system, far[2:], TIMES), asked=[0, 1])
    camp.tell(tms.simulate(system, far[2:], TIMES), asked=[-1])
    assert camp.history[-1]["unrequested"] == 1 and len(camp.pending) == 1
