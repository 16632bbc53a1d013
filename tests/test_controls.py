"""Known input signals u(t) (controls): profiles, simulation against a closed form, samples, fit, predict, bands,
tables (issue 24, part 1)."""

import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.signals import Controls

DT = torch.float64


def test_profiles_match_a_hand_interpolation():
    knots = [torch.tensor([0.0, 1.0, 3.0], dtype=DT), torch.tensor([0.0, 2.0], dtype=DT)]
    values = [torch.tensor([1.0, 2.0, 4.0], dtype=DT), torch.tensor([5.0, 7.0], dtype=DT)]
    hold = Controls(knots, values)
    lin = Controls(knots, values, kind="linear")
    t = torch.tensor([[-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 9.0], [-1.0, 0.0, 1.0, 2.0, 2.5, 3.0, 9.0]], dtype=DT)
    want_hold = [[1, 1, 1, 2, 2, 4, 4], [5, 5, 5, 7, 7, 7, 7]]
    want_lin = [[1, 1, 1.5, 2, 3, 4, 4], [5, 5, 6, 7, 7, 7, 7]]
    assert hold.at(t)[..., 0].tolist() == want_hold
    assert lin.at(t)[..., 0].tolist() == want_lin
    assert hold.at(torch.tensor(1.5, dtype=DT))[:, 0].tolist() == [2.0, 5.0]  # a scalar time: every experiment
    assert hold.at(torch.tensor([0.5, 2.5], dtype=DT))[:, 0].tolist() == [1.0, 7.0]  # one time per experiment
    assert hold.jumps.tolist() == [1.0, 2.0, 3.0] and lin.jumps is None  # the first knot: nothing before it differs
    assert hold[[1]].at(t[1:])[0, :, 0].tolist() == want_hold[1]
    assert hold.repeat(2).num_experiments == 4
    with pytest.raises(tms.InputError, match=r"kind: expected one of \('previous', 'linear'\)"):
        Controls(knots, values, kind="cubic")
    with pytest.raises(tms.InputError, match=r"strictly increasing"):
        Controls([torch.tensor([0.0, 0.0])], [torch.tensor([1.0, 2.0])])
    with pytest.raises(tms.InputError, match=r"a control is known"):
        Controls(torch.tensor([0.0, 1.0]), torch.tensor([[[1.0], [math.nan]]]))


def tank(correction=None):
    """dy/dt = -a y + u (known), plus an optional missing term; not a shipped system."""
    a = 0.7

    def known(t, y, u):
        return -a * y + u

    return tms.MisspecifiedSystem(
        known,
        1,
        num_controls=1,
        correction=correction,
        correction_inputs=["level", "inflow"],
        state_names=["level"],
        control_names=["inflow"],
        name="tank",
    ), a


def test_simulation_matches_the_closed_form_under_a_piecewise_constant_input():
    system, a = tank()
    knots = torch.tensor([0.0, 1.3, 2.1], dtype=DT)
    levels = torch.tensor([[1.0, 0.2, 2.0], [0.0, 3.0, 0.5]], dtype=DT)
    controls = Controls(knots, levels.unsqueeze(-1))
    y0 = torch.tensor([[0.5], [2.0]], dtype=DT)
    times = torch.linspace(0, 4, 9, dtype=DT)
    sim = tms.simulate(system, y0, times, controls=controls)

    def exact(y, u, tau):  # one interval of a constant input
        return u / a + (y - u / a) * math.exp(-a * tau)

    for k in range(2):
        for j, t in enumerate(times.tolist()):
            y, start = float(y0[k, 0]), 0.0
            for i, s in enumerate(knots.tolist() + [math.inf]):
                if i == 0:
                    continue
                end = min(s, t)
                if end > start:
                    y = exact(y, float(levels[k, i - 1]), end - start)
                    start = end
            assert float(sim.states[k, j, 0]) == pytest.approx(y, rel=1e-8, abs=1e-10)
    assert torch.equal(sim.controls.values, controls.values)  # the result carries its profiles
    with pytest.raises(tms.InputError, match=r"has 1 control\(s\) \['inflow'\]; expected a torchmisspec"):
        tms.simulate(system, y0, times)


def lab(seed: int, K: int = 8, T: int = 25, noise: float = 0.0):
    """Experiments of the tank with a missing outflow that grows with the inflow: F(y, u) = -0.4 u y."""

    def missing(x):
        return -0.4 * x[..., :1] * x[..., 1:]

    system, _ = tank(missing)
    gen = torch.Generator().manual_seed(seed)
    y0 = 0.5 + 1.5 * torch.rand(K, 1, generator=gen, dtype=DT)
    knots = torch.tensor([0.0, 2.0, 4.0, 6.0], dtype=DT)
    levels = 2.0 * torch.rand(K, 4, 1, generator=gen, dtype=DT)
    controls = Controls(knots, levels, names=["inflow"])
    times = torch.linspace(0, 8, T, dtype=DT)
    sim = tms.simulate(system, y0, times, controls=controls)
    states = sim.states + noise * torch.randn(sim.states.shape, generator=gen, dtype=DT)
    return system, tms.Trajectories(times, states, state_names=["level"], controls=controls)


def test_samples_carry_the_controls_and_the_targets_are_exact_with_oracle_derivatives():
    system, traj = lab(0, K=3, T=9)
    samples = tms.correction_samples(traj, system, derivative="oracle")
    assert samples.inputs.shape == (27, 2)
    u = traj.control_values().reshape(-1, 1)
    torch.testing.assert_close(samples.inputs[:, 1:], u)
    torch.testing.assert_close(samples.targets, -0.4 * samples.inputs[:, :1] * samples.inputs[:, 1:])


def test_fit_and_predict_new_initial_states_and_new_input_profiles():
    system, traj = lab(1, noise=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system, progress=False)
    assert gp.input_names_ == ("level", "inflow")
    _, test = lab(2, K=6)  # new initial states and new profiles
    model = tms.CorrectedODE(system, gp)
    y0 = test.states[:, 0]
    pred = model.predict(y0, test.times, controls=test.controls)
    known = tms.simulate(system, y0, test.times, controls=test.controls, known_only=True).states
    ratio = float(tms.trajectory_rmse(pred, test.states) / tms.trajectory_rmse(known, test.states))
    assert ratio < 0.1, ratio  # measured 0.040 (stencils cut at the jumps; 8.4 before they were)
    post = model.posterior(y0, test.times, controls=test.controls, num_samples=8, scale=1.0)
    assert post.samples.shape == (8, 6, 25, 1) and bool(torch.isfinite(post.samples).all())
    with pytest.raises(tms.InputError, match=r"expected a torchmisspec.signals.Controls"):
        model.predict(y0, test.times)


def test_calibration_holds_out_each_experiment_with_its_own_profile():
    system, traj = lab(3, noise=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(traj, system, progress=False)
        result = tms.CorrectedODE(system, gp).calibrate(traj, num_samples=16, folds=4, progress=False)
    assert result.scale > 0 and math.isfinite(result.scale)


def test_tables_round_trip_the_controls_and_keep_knots_between_measurements(tmp_path):
    system, traj = lab(4, K=2, T=4)
    path = traj.save(tmp_path / "lab.csv")
    text = path.read_text().splitlines()
    assert text[0] == "experiment,time,level,inflow"
    back = tms.Trajectories.load(path, control_columns=["inflow"])
    torch.testing.assert_close(back.states, traj.states)
    t = torch.linspace(0, 8, 41, dtype=DT).expand(2, -1)
    torch.testing.assert_close(back.controls.at(t), traj.controls.at(t))  # the same profile, jumps included
    assert any(row.split(",")[2] == "" for row in text[1:])  # knots 2, 4, 6 between the measurements
    bad = tmp_path / "bad.csv"
    bad.write_text("experiment,time,level,inflow\n0,0,1.0,\n0,1,1.1,0.5\n")
    with pytest.raises(tms.InputError, match=r"expected a value of the control 'inflow' on line 2"):
        tms.Trajectories.load(bad, control_columns=["inflow"])


def test_systems_without_controls_refuse_them_and_the_design_says_what_is_not_built():
    system, traj = lab(5, K=2, T=5)
    plain = tms.systems.paper_linear()
    with pytest.raises(tms.InputError, match=r"has no controls \(num_controls=0\)"):
        tms.simulate(plain, torch.ones(2, 2, dtype=DT), torch.linspace(0, 1, 3, dtype=DT), controls=traj.controls)
    with pytest.raises(tms.InputError, match=r"pass controls=\.\.\. \(one input profile per candidate\)"):
        tms.design.greedy(torch.ones(3, 1, dtype=DT), 1, system=system, times=torch.linspace(0, 1, 3), gp=None)
    with pytest.raises(tms.InputError, match=r"pass controls=\.\.\. \(one input profile per candidate\)"):
        tms.design.random(torch.ones(3, 1, dtype=DT), 1, system=system, times=torch.linspace(0, 1, 3), gp=None)
    with pytest.raises(tms.InputError, match=r"pass controls=\.\.\. \(one input profile per candidate\)"):
        tms.design.Campaign(system, torch.ones(3, 1, dtype=DT), torch.linspace(0, 1, 3, dtype=DT), None)
    others = r"use design.greedy, random, agnostic, sampling_times, refine or Campaign"
    with pytest.raises(tms.InputError, match=others):
        tms.design.proxy_check([0], torch.ones(3, 1, dtype=DT), system=system, times=torch.linspace(0, 1, 3), gp=None)
    with pytest.raises(tms.InputError, match=r"correction_inputs: expected state or control names"):
        tms.MisspecifiedSystem(lambda t, y, u: y, 1, num_controls=1, correction_inputs=["flow"])


def test_no_derivative_stencil_straddles_a_jump_of_the_input():
    """Where a piecewise-constant input jumps, dy/dt jumps: a stencil across it averages the two sides. The
    estimators run on the pieces between jumps (a sample at a jump takes the right derivative)."""
    system, traj = lab(6, K=4, T=33)  # samples at the jumps t = 2, 4, 6
    exact = tms.correction_samples(traj, system, derivative="oracle").targets
    # measured largest errors (|F| up to 1.36): central 0.027, smooth 0.163 (its one-sided fit at a piece's end),
    # gp 0.0016; with stencils across the jumps: central 0.63, smooth 0.73
    for derivative, bound in (("central", 0.05), ("smooth", 0.25), ("gp", 0.01)):
        samples = tms.correction_samples(traj, system, derivative=derivative)
        error = float((samples.targets - exact).abs().max())
        assert error < bound, (derivative, error)


SYSTEM_FILE = """
import torch
from torchmisspec import MisspecifiedSystem

def feed_tank():
    # a tank fed at a rate the lab sets (column "feed"); the outflow's dependence on the feed is what is missing
    return MisspecifiedSystem(
        lambda t, y, u: -0.7 * y + u, 1, num_controls=1, control_names=["feed"], state_names=["level"],
        correction_inputs=["level", "feed"], name="feed tank",
    )
"""


def feed_tank():
    namespace: dict = {}
    exec(SYSTEM_FILE, namespace)
    return namespace["feed_tank"]()


def _lab_csv(tmp_path, K: int):
    """A lab's table as it comes (``K`` flasks): named columns, ragged irregular times, noise, the input set between
    measurements; with the system file beside it. Returns the command line's common options."""
    _, traj = lab(7, K=K, T=30, noise=2e-3)
    gen = torch.Generator().manual_seed(8)
    rows = ["flask,day,level,feed"]
    for k, ((t, y), (knots, _)) in enumerate(zip(traj.experiments(), traj.controls.profiles(), strict=True)):
        keep = torch.rand(len(t), generator=gen) > 0.25  # irregular, ragged: a quarter of the samples lost
        keep[0] = True
        times = torch.cat([t[keep], knots])
        order = torch.argsort(times)
        level = torch.cat([y[keep, 0], torch.full((len(knots),), math.nan, dtype=DT)])
        u = traj.controls[[k]].at(times.unsqueeze(0))[0, :, 0]
        seen = set()
        for i in order.tolist():
            if float(times[i]) in seen:
                continue
            seen.add(float(times[i]))
            cell = "" if math.isnan(float(level[i])) else f"{float(level[i]):.6g}"
            rows.append(f"F{k},{float(times[i]):.6g},{cell},{float(u[i]):.6g}")
    data = tmp_path / "lab.csv"
    data.write_text("\n".join(rows) + "\n")
    (tmp_path / "tank.py").write_text(SYSTEM_FILE)
    system = f"{tmp_path / 'tank.py'}:feed_tank"
    return ["--data", str(data), "--system", system, "--experiment-column", "flask", "--time-column", "day"], system


def test_a_lab_csv_with_an_input_column_through_the_cli(tmp_path, capsys):
    """A lab's table as it comes, fitted and calibrated on the command line with the defaults, the input named by
    --input-columns."""
    from torchmisspec.cli import main

    common, system = _lab_csv(tmp_path, K=8)
    model = tmp_path / "model.pt"
    assert main(["fit", *common, "--input-columns", "feed", "--out", str(model), "--quiet"]) == 0
    assert model.is_file()
    assert main(["calibrate", "--model", str(model), *common, "--input-columns", "feed", "--quiet"]) == 0
    # predict new flasks under new feed profiles, given as a table of each flask's profile
    (tmp_path / "initial.csv").write_text("flask,level\nN1,0.5\nN2,1.5\n")
    (tmp_path / "feeds.csv").write_text("flask,day,feed\nN1,0,0.2\nN1,2,1.0\nN2,0,0.8\n")
    pred = tmp_path / "pred.csv"
    args = ["predict", "--model", str(model), "--system", system, "--initial", str(tmp_path / "initial.csv")]
    args += ["--experiment-column", "flask", "--time-column", "day", "--times", "0:4:9", "--out", str(pred)]
    assert main([*args, "--controls", str(tmp_path / "feeds.csv"), "--quiet"]) == 0
    table = [line.split(",") for line in pred.read_text().splitlines()]
    assert table[0][:3] == ["flask", "day", "level_mean"] and len(table) == 1 + 2 * 9
    gp = tms.CorrectionGP.load(model)
    feeds = Controls(
        [torch.tensor([0.0, 2.0], dtype=DT), torch.tensor([0.0], dtype=DT)],
        [torch.tensor([[0.2], [1.0]], dtype=DT), torch.tensor([[0.8]], dtype=DT)],
    )
    y0 = torch.tensor([[0.5], [1.5]], dtype=DT)
    mean = tms.CorrectedODE(feed_tank(), gp).predict(y0, torch.linspace(0, 4, 9, dtype=DT), controls=feeds)
    got = torch.tensor([float(row[2]) for row in table[1:]], dtype=DT).reshape(2, 9)
    torch.testing.assert_close(got, mean[..., 0], rtol=1e-9, atol=1e-12)  # the mean path the Python API predicts
    capsys.readouterr()
    assert main([*args, "--quiet"]) == 2  # the inputs' profiles are needed: one line saying how to give them
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--controls profiles.csv" in err[0]
    # without the input column: one line naming what the system needs, exit 2
    capsys.readouterr()
    assert main(["fit", *common, "--out", str(tmp_path / "m2.pt"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the system also takes 1 input(s) ['feed']: name their columns" in err[0]
    assert "--input-columns" in err[0]


def test_the_command_line_prints_the_terms_of_a_correction_on_an_input(tmp_path, capsys):
    """Five flasks: a feature kernel's terms are printed in the data's names, the input's included (it raised
    IndexError, "internal error", looking the input up among the states). Since a repeated input value is no jump
    (``test_a_repeated_value_is_no_jump``) the cross-validation keeps an RBF kernel on these flasks (held-out error
    0.0062 against the feature kernel's 0.27, which it kept before), so the terms are those of a feature kernel fitted
    to the table the command line reads, printed as it prints them."""
    import importlib.util

    from torchmisspec.cli import main
    from torchmisspec.cli._fit import _print_terms

    common, _ = _lab_csv(tmp_path, K=5)
    assert main(["fit", *common, "--input-columns", "feed", "--no-calibrate", "--out", str(tmp_path / "m.pt")]) == 0
    out = capsys.readouterr().out
    assert "internal error" not in out and "cross-validation (5 folds): chose " in out
    spec = importlib.util.spec_from_file_location("tank", tmp_path / "tank.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    system = module.feed_tank()
    observed = tms.Trajectories.load(
        tmp_path / "lab.csv", experiment_column="flask", time_column="day", state_columns=["level"],
        control_columns=["feed"],
    )  # fmt: skip
    gp = tms.fit_correction(observed, system, candidates=[tms.CorrectionGP(kernel="features")], progress=False)
    _print_terms(gp, system, observed)
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("correction of dlevel/dt:"))
    assert "feed" in line or "level" in line or "no term kept" in line, line


@pytest.mark.parametrize("shooting", ["single", "multiple"])
def test_the_fit_through_the_ode_runs_each_experiment_under_its_own_inputs(shooting):
    """fit_trajectories on a system with inputs: sparse samples (a biased derivative fit), refined on the observed
    states; its one-interval misfit falls, and the solve saw the inputs (the same fit without them is refused)."""
    system, traj = lab(11, K=6, T=9, noise=1e-3)
    known = tms.MisspecifiedSystem(system.known, 1, num_controls=1, correction_inputs=[0, 1], time_dependent=False)
    gp = tms.fit_correction(traj, known, select="evidence", derivative="central", progress=False)
    refined = tms.fit_trajectories(gp, known, traj, shooting=shooting, max_iter=15)
    before = tms.learning.refinement.trajectory_fit.shooting_misfit(gp, known, traj)
    after = tms.learning.refinement.trajectory_fit.shooting_misfit(refined, known, traj)
    assert after < 0.25 * before, (before, after)  # measured: 0.060 -> 0.0025 (single), 0.0023 (multiple)
    stripped = tms.Trajectories(traj.time_grid, traj.states)
    with pytest.raises(tms.InputError):
        tms.fit_trajectories(gp, known, stripped)


def test_greedy_chooses_among_input_profiles_where_the_data_leave_f_unknown():
    """A candidate experiment is an initial state and an input profile. F depends on the inflow; the data saw inflows
    below 1 only, so the design given the data must pick profiles that reach high inflows first (it cannot if it
    ignores the profiles: every candidate has the same initial state, and they would all tie)."""
    system, traj = lab(12, K=6, T=17)
    low = Controls(traj.controls.knots, 0.5 * traj.controls.values)  # inflows in [0, 1)
    data = tms.simulate(system, traj.states[:, 0], traj.time_grid, controls=low)
    gp = tms.fit_correction(data, system, select="evidence", derivative="central", progress=False)
    levels = torch.tensor([[0.2], [0.5], [0.8], [1.5], [1.8], [0.3]], dtype=DT)  # constant profiles
    profiles = Controls(torch.tensor([0.0], dtype=DT), levels.unsqueeze(1))
    y0 = torch.full((6, 1), 1.0, dtype=DT)
    times = torch.linspace(0, 4, 9, dtype=DT)
    plan = tms.design.greedy(y0, 2, system=system, times=times, gp=gp, controls=profiles)
    assert set(plan.indices.tolist()) == {3, 4}, plan.indices  # the two high inflows, where F is unknown
    assert plan.diagnostics["conditioned"] == gp.train_inputs_.shape[0]
    # the proxies ran under each pick's profile: the corrected model's paths (a fitted GP's default proxy) ...
    picks = plan.indices.tolist()
    corrected = tms.CorrectedODE(system, gp).predict(y0[picks], times, controls=profiles[picks])
    torch.testing.assert_close(plan.proxies, corrected, rtol=1e-4, atol=1e-5)
    # ... and G's alone: u/a + (1 - u/a) exp(-a t) from 1.0 under a constant inflow u
    known = tms.design.proxy_trajectories(system, y0, times, controls=profiles)
    a = 0.7
    expected = levels / a + (1 - levels / a) * torch.exp(-a * times)
    torch.testing.assert_close(known[..., 0], expected, rtol=1e-5, atol=1e-6)


def test_a_repeated_value_is_no_jump():
    """A lab's table repeats the input on every row (nlme's Remifentanil: the infusion rate on each of ~50 sample
    rows, changing once): only a changed value is a jump, for the solver's restarts and the derivative estimator's
    cuts. Before, every knot was one: the population fit's solves restarted at ~400 of them on 8 subjects."""
    from torchmisspec.learning.samples._estimators import _cut_at_jumps

    knots = torch.arange(12, dtype=DT)
    rate = torch.where(knots < 5.5, 3.0, 0.0)
    values = torch.stack([rate, torch.full_like(rate, 2.0)])[..., None]  # (2, 12, 1): the second never changes
    hold = Controls(knots, values)
    assert hold.jumps.tolist() == [6.0]
    assert hold.changes().sum().item() == 1
    assert Controls(knots, values[1:]).jumps.numel() == 0
    states = torch.linspace(0.0, 1.0, 12, dtype=DT).expand(2, -1)[..., None].clone()
    segments, rows = _cut_at_jumps(tms.Trajectories(knots, states, controls=hold))
    assert segments.num_experiments == 3  # the first experiment cut once, at 6; the second whole
    assert [int(n) for n in segments.lengths] == [7, 6, 12] and rows.numel() == 24


def test_a_dose_row_that_measures_nothing_is_named_when_it_is_dropped(tmp_path):
    """A lab writes the dose row with an empty concentration (nlme's Remifentanil): the experiment starts at its first
    measured row, and the loader says so and how to keep the start (0 before a dose, written in the cell)."""
    path = tmp_path / "dose.csv"
    path.write_text("subject,time,conc,rate\nA,0,,5\nA,1.5,9.5,5\nA,3,12,0\nB,0,0,4\nB,2,7,4\nB,4,6,0\n")
    with pytest.warns(tms.TorchMisspecWarning, match=r"1 experiment\(s\) measure nothing.*'A': 0 -> 1.5.*0 before"):
        data = tms.Trajectories.load(
            path, experiment_column="subject", time_column="time", state_columns=["conc"], control_columns=["rate"]
        )
    assert [float(t[0]) for t, _ in data.experiments()] == [1.5, 0.0]
    assert float(data.controls.knots[0, 0]) == 0.0  # the input is still known from the dose on
    path.write_text("subject,time,conc,rate\nA,0,0,5\nA,1.5,9.5,5\nA,3,12,0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tms.Trajectories.load(path, experiment_column="subject", time_column="time", control_columns=["rate"])
