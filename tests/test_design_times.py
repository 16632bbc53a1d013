"""Which times to measure (issue 24 part 4): ``design.sampling_times`` against brute force on tiny problems."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design

DT = torch.float64


def two_compartments(y):
    c, p = y[..., 0], y[..., 1]
    return torch.stack([-0.8 * c + 0.2 * p, 0.5 * c - 0.2 * p], dim=-1)


def pk() -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(two_compartments, 2, correction_inputs=[0], correction_outputs=[0], name="pk")


def rbf_gain(x: torch.Tensor, outputscale: float, lengthscale: float, noise: float) -> float:
    """(1/2) logdet(I + K / noise) by hand, for one output."""
    K = outputscale * torch.exp(-0.5 * torch.cdist(x, x).pow(2) / lengthscale**2)
    return 0.5 * float(torch.logdet(torch.eye(len(x), dtype=DT) + K / noise))


def test_the_times_chosen_are_at_least_half_the_best_and_respect_every_budget():
    """Brute force over every choice of 2 of 6 times in each of 2 experiments (225 sets): the greedy's gain is the
    criterion of its picks (recomputed by hand), at least 1/2 of the optimum (Fisher et al. 1978 for a partition
    matroid), and here equal to it."""
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    y0 = torch.tensor([[1.0, 0.0], [3.5, 0.0]], dtype=DT)
    t = torch.linspace(0, 8, 6, dtype=DT)
    result = design.sampling_times(y0, t, 2, system=pk(), gp=gp)
    assert [len(c) for c in result.times] == [2, 2]
    paths = tms.simulate(pk(), y0, t, known_only=True).states[..., :1]  # F's input: the central compartment
    for k in range(2):
        assert torch.equal(result.times[k], t[result.indices[k]])
        assert bool((result.indices[k][1:] > result.indices[k][:-1]).all())
    picked = torch.cat([paths[k, result.indices[k]] for k in range(2)])
    assert math.isclose(result.design.information_gain, rbf_gain(picked, 0.1, 0.5, 1e-3), rel_tol=1e-6)
    best = max(
        rbf_gain(torch.cat([paths[0, list(a)], paths[1, list(b)]]), 0.1, 0.5, 1e-3)
        for a in itertools.combinations(range(6), 2)
        for b in itertools.combinations(range(6), 2)
    )
    assert result.design.information_gain >= 0.5 * best
    assert math.isclose(result.design.information_gain, best, rel_tol=1e-9)


def test_a_known_start_is_never_a_sample_and_the_rest_is_the_brute_force_best():
    """``skip_first``: the initial state's time is not a candidate (a new subject's known start); the picks are the
    best of the other times by brute force, their indices and times in the whole grid's terms."""
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    y0 = torch.tensor([[0.2, 0.0]], dtype=DT)  # the start itself the most informative state: an unknown start picks it
    t = torch.linspace(0, 8, 6, dtype=DT)
    assert 0 in design.sampling_times(y0, t, 2, system=pk(), gp=gp).indices[0].tolist()
    result = design.sampling_times(y0, t, 2, system=pk(), gp=gp, skip_first=True)
    assert 0 not in result.indices[0].tolist() and torch.equal(result.times[0], t[result.indices[0]])
    paths = tms.simulate(pk(), y0, t, known_only=True).states[0, :, :1]
    best = max(rbf_gain(paths[list(a)], 0.1, 0.5, 1e-3) for a in itertools.combinations(range(1, 6), 2))
    assert math.isclose(result.design.information_gain, best, rel_tol=1e-9)
    with pytest.raises(tms.InputError, match="at most the 5 candidate times"):
        design.sampling_times(y0, t, 6, system=pk(), gp=gp, skip_first=True)
    with pytest.raises(tms.InputError, match=r"skip_first: expected True or False, got 'yes'"):
        design.sampling_times(y0, t, 2, system=pk(), gp=gp, skip_first="yes")  # no truthy string taken as a switch


def test_times_are_spread_where_the_path_moves_and_conditioned_on_data():
    """A decaying dose: most of the picks fall early, where the central concentration changes; once data cover
    the early states (a fitted GP), the design moves to where they do not."""
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    y0 = torch.tensor([[3.5, 0.0]], dtype=DT)
    t = torch.linspace(0, 8, 33, dtype=DT)
    prior = design.sampling_times(y0, t, 4, system=pk(), gp=gp)
    assert float(prior.times[0].median()) < 2.0  # the path moves fastest at the start
    x = torch.linspace(1.5, 3.5, 20, dtype=DT).unsqueeze(-1)  # data already cover concentrations 1.5-3.5
    fitted = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3).fit(x, torch.zeros_like(x))
    after = design.sampling_times(
        y0,
        t,
        4,
        system=pk(),
        gp=fitted,
        proxy=design.Proxy("known"),
    )
    paths = tms.simulate(pk(), y0, t, known_only=True).states[0, :, 0]
    assert float(paths[after.indices[0]].max()) < 1.5  # none where the data already are


def test_a_system_with_inputs_runs_its_proxies_under_each_profile():
    def tank(t, y, u):
        return -0.7 * y + u

    system = tms.MisspecifiedSystem(tank, 1, num_controls=1, correction_inputs=[0], name="tank")
    profiles = tms.Controls(torch.tensor([0.0, 2.0], dtype=DT), torch.tensor([[[0.0], [2.0]], [[1.0], [0.0]]]))
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    t = torch.linspace(0, 4, 9, dtype=DT)
    result = design.sampling_times(
        torch.tensor([[0.5], [0.5]], dtype=DT), t, 3, system=system, gp=gp, controls=profiles
    )
    assert [len(c) for c in result.times] == [3, 3]
    # F depending on the input: the samples' inputs are (level, inflow at the sample's time); an inflow that jumps
    # makes the states after the jump new information even where the level barely moves
    uses_u = tms.MisspecifiedSystem(tank, 1, num_controls=1, correction_inputs=[0, 1], name="tank")
    both = design.sampling_times(torch.tensor([[0.5]], dtype=DT), t, 2, system=uses_u, gp=gp, controls=profiles[[0]])
    inflow = profiles[[0]].at(both.times[0].unsqueeze(0))[0, :, 0]
    assert set(inflow.tolist()) == {0.0, 2.0}  # one sample under each inflow level


def test_bad_budgets_and_times_are_refused_with_the_fix():
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    y0 = torch.tensor([[1.0, 0.0]], dtype=DT)
    t = torch.linspace(0, 8, 5, dtype=DT)
    with pytest.raises(tms.InputError, match=r"per_experiment: expected at most the 5 candidate times, got 6"):
        design.sampling_times(y0, t, 6, system=pk(), gp=gp)
    with pytest.raises(tms.InputError, match=r"times: expected strictly increasing values, got 8.0 followed by 6.0"):
        design.sampling_times(y0, t.flip(0), 2, system=pk(), gp=gp)
    with pytest.raises(tms.ShapeError, match=r"initial_states: expected shape \(N, 2\), got \(3,\)"):
        design.sampling_times(torch.ones(3, dtype=DT), t, 2, system=pk(), gp=gp)
    with pytest.raises(tms.InputError, match=r"partition: expected none .sampling_times sets it"):
        design.sampling_times(y0, t, 2, system=pk(), gp=gp, partition=[0] * 5)


def test_the_command_line_writes_the_times_to_measure(tmp_path, capsys):
    from torchmisspec.cli import main

    (tmp_path / "pk.py").write_text(
        "import torch\nimport torchmisspec as tms\n\n\ndef pk():\n    return tms.MisspecifiedSystem(\n"
        "        lambda y: torch.stack([-0.8 * y[..., 0] + 0.2 * y[..., 1], 0.5 * y[..., 0] - 0.2 * y[..., 1]], -1),\n"
        "        2, state_names=['central', 'peripheral'], correction_inputs=[0], correction_outputs=[0], name='pk')\n"
    )
    (tmp_path / "doses.csv").write_text("central,peripheral\n" + "".join(f"{0.5 + 0.5 * i},0\n" for i in range(8)))
    prior = ["--lengthscale", "0.5", "--outputscale", "0.1", "--noise-variance", "1e-3"]
    common = ["design", "--system", f"{tmp_path / 'pk.py'}:pk", "--candidates", str(tmp_path / "doses.csv")]
    out = tmp_path / "plan.csv"
    args = [*common, "--budget", "2", "--times", "0:8:17", *prior, "--out", str(out), "--quiet"]
    assert main([*args, "--samples-per-experiment", "4"]) == 0
    header, *rows = out.read_text().splitlines()
    assert header.endswith(",measure_at") and len(rows) == 2
    for row in rows:
        times = [float(v) for v in row.rsplit(",", 1)[1].split()]
        assert len(times) == 4 and times == sorted(times) and all(0 <= v <= 8 for v in times)
    assert "4 of the 17 times chosen in each" in capsys.readouterr().out
    assert main([*args, "--samples-per-experiment", "18"]) == 2
    assert "--samples-per-experiment: expected 1 to 17 (the number of --times), got 18" in capsys.readouterr().err


def test_the_command_line_designs_initial_states_with_input_profiles(tmp_path, capsys):
    from torchmisspec.cli import main

    (tmp_path / "tank.py").write_text(
        "import torchmisspec as tms\n\n\ndef tank():\n    return tms.MisspecifiedSystem(\n"
        "        lambda t, y, u: -0.7 * y + u, 1, num_controls=1, control_names=['inflow'], state_names=['level'],\n"
        "        correction_inputs=['level', 'inflow'], name='tank')\n"
    )
    g = torch.Generator().manual_seed(0)
    rows, profiles = ["run,level"], ["run,time,inflow"]
    for i in range(6):
        rows.append(f"c{i},{0.2 + 0.3 * (i % 3):.2f}")
        profiles += [f"c{i},{t},{float(2 * torch.rand(1, generator=g)):.3f}" for t in (0, 2, 4)]
    (tmp_path / "cands.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "profiles.csv").write_text("\n".join(profiles) + "\n")
    prior = ["--lengthscale", "0.7", "--outputscale", "0.1", "--noise-variance", "1e-4"]
    common = ["design", "--system", f"{tmp_path / 'tank.py'}:tank", "--candidates", str(tmp_path / "cands.csv")]
    common += ["--experiment-column", "run", "--budget", "2", "--times", "0:6:13", *prior, "--quiet"]
    out = tmp_path / "plan.csv"
    assert main([*common, "--controls", str(tmp_path / "profiles.csv"), "--out", str(out)]) == 0
    header, *picked = out.read_text().splitlines()
    assert header == "order,index,run,gain,level" and len(picked) == 2
    # the same choice as design.greedy with the profiles read back
    system = tms.MisspecifiedSystem(
        lambda t, y, u: -0.7 * y + u, 1, num_controls=1, correction_inputs=[0, 1], name="tank"
    )
    knots = torch.tensor([0.0, 2.0, 4.0], dtype=DT)
    levels = torch.tensor([[float(p.split(",")[2])] for p in profiles[1:]], dtype=DT).reshape(6, 3, 1)
    states = torch.tensor([[float(r.split(",")[1])] for r in rows[1:]], dtype=DT)
    gp = tms.CorrectionGP(lengthscale=0.7, outputscale=0.1, noise_variance=1e-4)
    plan = design.greedy(
        states, 2, system=system, times=torch.linspace(0, 6, 13, dtype=DT), gp=gp, controls=tms.Controls(knots, levels)
    )
    assert [int(r.split(",")[1]) for r in picked] == plan.indices.tolist()
    capsys.readouterr()
    assert main([*common, "--out", str(out)]) == 2
    assert "pass --controls profiles.csv" in capsys.readouterr().err


def test_refine_climbs_the_criterion_inside_the_box():
    """One experiment of a decay y' = -y with F(y): the trajectory from the largest y0 sweeps every smaller state,
    so the criterion is largest at the top of the box, where refine must go from the middle; the criterion it reports
    is the one information_gain computes on the proxies of its points."""
    system = tms.MisspecifiedSystem(lambda y: -y, 1, name="decay")
    gp = tms.CorrectionGP(lengthscale=0.3, outputscale=0.1, noise_variance=1e-3)
    t = torch.linspace(0, 3, 16, dtype=DT)
    result = design.refine(torch.tensor([[1.0]], dtype=DT), system=system, times=t, gp=gp, box=[(0.1, 3.0)], steps=80)
    assert float(result.points[0, 0]) > 2.9 and result.information_gain > result.start_gain
    paths = design.proxy_trajectories(system, result.points, t)
    again = design.information_gain(paths.reshape(-1, 1), gp, d_out=1)
    assert math.isclose(result.information_gain, again, rel_tol=1e-5)
    with pytest.raises(tms.InputError, match=r"initial_states: expected every state inside box"):
        design.refine(torch.tensor([[5.0]], dtype=DT), system=system, times=t, gp=gp, box=[(0.1, 3.0)])


def test_refine_never_returns_worse_than_the_greedy_picks():
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    g = torch.Generator().manual_seed(0)
    candidates = torch.stack(
        [0.5 + 3.5 * torch.rand(12, generator=g, dtype=DT), 2 * torch.rand(12, generator=g, dtype=DT)], -1
    )
    t = torch.linspace(0, 8, 20, dtype=DT)
    plan = design.greedy(candidates, 3, system=pk(), times=t, gp=gp)
    result = design.refine(plan.points, system=pk(), times=t, gp=gp, box=[(0.5, 4.0), (0.0, 2.0)], steps=20)
    assert math.isclose(result.start_gain, plan.information_gain, rel_tol=1e-5)
    assert result.information_gain >= result.start_gain and len(result.history) == 21
    assert bool(
        (
            (result.points >= torch.tensor([0.5, 0.0], dtype=DT))
            & (result.points <= torch.tensor([4.0, 2.0], dtype=DT))
        ).all()
    )


def test_random_and_agnostic_designs_take_input_profiles():
    def tank(t, y, u):
        return -0.7 * y + u

    system = tms.MisspecifiedSystem(tank, 1, num_controls=1, correction_inputs=[0, 1], name="tank")
    profiles = tms.Controls(
        torch.tensor([0.0, 2.0], dtype=DT), torch.rand(5, 2, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    )
    states = torch.linspace(0.2, 1.0, 5, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    t = torch.linspace(0, 4, 9, dtype=DT)
    chance = design.random(
        states, 2, system=system, times=t, gp=gp, controls=profiles, generator=torch.Generator().manual_seed(1)
    )
    # its gains are the greedy's criterion of the same picks (the profiles' inputs included)
    same = design.marginal_gains(chance.indices, states, system=system, times=t, gp=gp, controls=profiles)
    assert torch.allclose(chance.gains, same) and math.isfinite(chance.information_gain)
    paths = design.proxy_trajectories(system, states[chance.indices], t, controls=profiles[chance.indices.tolist()])
    u = profiles[chance.indices.tolist()].at(t.expand(2, -1))
    points = torch.cat([paths, u], dim=-1).reshape(-1, 2)
    assert math.isclose(chance.information_gain, design.information_gain(points, gp, d_out=1), rel_tol=1e-9)
    blind = design.agnostic(states, 2, system=system, times=t, gp=gp, controls=profiles)
    assert blind.method == "agnostic-lazy" and len(blind) == 2


def test_refine_moves_input_levels_within_their_box_too():
    """A tank whose correction depends on the inflow: the profiles' levels are refined with the initial levels,
    inside the control box, and the criterion reported is the greedy's criterion of the refined experiments."""

    def tank(t, y, u):
        return -0.7 * y + u

    system = tms.MisspecifiedSystem(tank, 1, num_controls=1, correction_inputs=[0, 1], name="tank")
    profiles = tms.Controls(torch.tensor([0.0, 2.0], dtype=DT), torch.full((2, 2, 1), 0.5, dtype=DT))
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=0.1, noise_variance=1e-3)
    t = torch.linspace(0, 4, 9, dtype=DT)
    y0 = torch.tensor([[0.5], [0.6]], dtype=DT)
    kept = design.refine(y0, system=system, times=t, gp=gp, box=[(0.0, 2.0)], controls=profiles, steps=15)
    moved = design.refine(
        y0, system=system, times=t, gp=gp, box=[(0.0, 2.0)], controls=profiles, control_box=[(0.0, 2.0)], steps=15
    )
    assert torch.equal(kept.controls.values, profiles.values)
    assert moved.information_gain > kept.information_gain  # the levels were all 0.5: spreading them informs F(y, u)
    levels = moved.controls.values
    assert bool(((levels >= 0) & (levels <= 2)).all()) and float((levels - 0.5).abs().max()) > 0.1
    again = design.marginal_gains([0, 1], moved.points, system=system, times=t, gp=gp, controls=moved.controls)
    assert math.isclose(float(again.sum()), moved.information_gain, rel_tol=1e-4)
    with pytest.raises(tms.InputError, match=r"expected every level inside control_box"):
        design.refine(y0, system=system, times=t, gp=gp, box=[(0.0, 2.0)], controls=profiles, control_box=[(1.0, 2.0)])


def test_a_campaign_asks_for_states_with_profiles_and_resumes(tmp_path):
    """The sequential loop on a tank with an inflow: ask returns states and profiles, tell matches each told
    experiment by its first state and its profile (every candidate starts at the same level), save/load keeps the
    profiles."""

    def tank(t, y, u):
        return -0.7 * y + u

    truth = tms.MisspecifiedSystem(
        tank,
        1,
        num_controls=1,
        correction=lambda x: -0.5 * x[..., 1:] * x[..., :1] / (1 + x[..., :1]),
        correction_inputs=[0, 1],
        name="tank",
    )
    system = tms.MisspecifiedSystem(tank, 1, num_controls=1, correction_inputs=[0, 1], name="tank")
    g = torch.Generator().manual_seed(0)
    states = torch.full((6, 1), 0.5, dtype=DT)  # one initial level: the candidates differ by their profiles only
    profiles = tms.Controls(torch.tensor([0.0, 2.0], dtype=DT), 2 * torch.rand(6, 2, 1, generator=g, dtype=DT))
    prior = tms.CorrectionGP(lengthscale=0.7, outputscale=0.1, noise_variance=1e-4)
    t = torch.linspace(0, 4, 21, dtype=DT)
    campaign = design.Campaign(system, states, t, prior, controls=profiles)
    y0, u = campaign.ask(2)
    assert y0.shape == (2, 1) and u.num_experiments == 2
    picks = campaign.pending
    told = tms.simulate(truth, y0.flip(0), t, controls=u[[1, 0]])  # told in the other order
    campaign.tell(told)
    assert campaign.measured == picks[::-1] and campaign.pending == []
    path = campaign.save(tmp_path / "c.pt")
    again = design.Campaign.load(path, system)
    assert torch.equal(again.controls.values, campaign.controls.values)
    assert torch.equal(again.ask(1)[0], campaign.ask(1)[0])  # the same next design after a resume
    with pytest.raises(tms.InputError, match=r"tell the measured trajectories with the profiles"):
        again.tell(tms.Trajectories(t, told.states))
