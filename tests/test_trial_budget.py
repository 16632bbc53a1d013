"""Fits through the ODE do not pay for trial steps they reject: a trial step's solve has a step budget of a few
times the current point's (issue 41: on the lynx data four trial steps of the known model's fit were integrated to
the step limit, 19 of the fit's 48 s); the Jacobian of the joint fit is one batched solve; copies of G that share
their parameters share a call of G; a held-out prediction that leaves the data's box is stopped there."""

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec import _ode
from torchmisspec.gp._features import FeatureKernel
from torchmisspec.learning.choice.cross_validation import HELD_OUT_WIDTHS, predicted_residuals
from torchmisspec.learning.refinement import _jacobian as tm
from torchmisspec.learning.refinement import _known_fit
from torchmisspec.learning.refinement import trajectory_fit as tf
from torchmisspec.noise import Additive

DT = torch.float64


def test_the_trial_budget_is_a_multiple_of_the_current_solve_within_bounds():
    assert _ode.trial_budget(10) == _ode.TRIAL_MIN_STEPS
    assert _ode.trial_budget(100) == _ode.TRIAL_STEPS_FACTOR * 100
    assert _ode.trial_budget(10**6, 4000) == 4000
    assert _ode.trial_budget(10**9) == _ode.DEFAULT_MAX_STEPS


def _chain(y, theta):
    a, b = theta[0], theta[1]
    return torch.stack([-a * y[..., 0], a * y[..., 0] - b * y[..., 1]], dim=-1)


def _chain_data():
    truth = tms.MisspecifiedSystem(lambda y: _chain(y, torch.tensor([0.8, 0.3], dtype=y.dtype)), 2)
    times = torch.linspace(0.0, 8.0, 16, dtype=DT)
    y = tms.simulate(truth, torch.tensor([[4.0, 0.1]], dtype=DT), times).states
    y = y + 0.05 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    y[:, :, 0] = math.nan
    return tms.Trajectories(times, y)


def test_the_known_models_trial_steps_are_solved_within_their_budget(monkeypatch):
    """Every solve of the known model's fit either is a Jacobian's or the current point's (the step limit), or a
    trial step's, whose limit is the budget of the solve before it (the current point's or a Jacobian's)."""
    calls = []
    solve = _known_fit._solve_rhs

    def recorded(*args, **kwargs):
        out = solve(*args, **kwargs)
        calls.append((kwargs["max_steps"], out[1] / _ode.EVALS_PER_STEP))
        return out

    monkeypatch.setattr(_known_fit, "_solve_rhs", recorded)
    system = tms.MisspecifiedSystem(_chain, 2, parameters={"a": (0.5, 50.0), "b": (0.5, 50.0)})
    data = _chain_data()
    start = data.initial_conditions.clone()
    start[:, 0] = 2.0
    fit = _known_fit.fit_known_model(system, data.with_initial_states(start), torch.tensor([[True, False]]), Additive())
    assert fit.theta.tolist() == pytest.approx([0.8, 0.3], rel=0.1)
    trials = [(i, limit) for i, (limit, _) in enumerate(calls) if limit != _known_fit.MAX_STEPS]
    assert trials, "no trial step was budgeted"
    steps_seen = [steps for _, steps in calls]
    for i, limit in trials:
        assert any(limit == _ode.trial_budget(s, _known_fit.MAX_STEPS) for s in steps_seen[:i])
        assert calls[i][1] <= limit


@pytest.mark.parametrize("branching", [False, True])
def test_copies_of_g_take_one_call_for_every_row(branching):
    """A G that broadcasts its parameters over the rows is called once for all copies; one with Python control flow
    on a parameter's value, once per distinct theta; both give each copy's own G."""
    calls = []

    def g(y, theta):
        calls.append(theta.clone())
        if branching and float(theta[0]) < 0:  # control flow on a value: neither broadcast nor vmap
            theta = -theta
        return _chain(y, theta)

    system = tms.MisspecifiedSystem(g, 2, parameters={"a": (0.5, 0.1), "b": (0.5, 0.1)})
    thetas = torch.tensor([[0.8, 0.3], [0.9, 0.3], [0.8, 0.3], [0.8, 0.4]], dtype=DT)
    y = torch.rand(4 * 3, 2, generator=torch.Generator().manual_seed(1), dtype=DT)  # 3 rows per copy
    rhs = system.copies_rhs(thetas)
    rhs(y)  # the first call whose rows differ also finds how G takes each row's theta
    calls.clear()
    out = rhs(y)
    assert len(calls) == (3 if branching else 1)  # three distinct thetas, or one call for all
    expected = torch.cat([_chain(y[3 * c : 3 * c + 3], thetas[c]) for c in range(4)])
    torch.testing.assert_close(out, expected)


def test_the_joint_jacobian_equals_its_three_parts():
    """Coefficients', G's parameters' and the initial-state offsets' columns in one batched solve equal the columns of
    their own solves, ragged experiments included."""

    def g(y, theta):
        return torch.stack([-theta[0] * y[..., 0] + y[..., 1], -theta[1] * y[..., 1]], dim=-1)

    system = tms.MisspecifiedSystem(g, 2, parameters={"a": (0.5, 0.2), "b": (0.3, 0.1)})
    gen = torch.Generator().manual_seed(0)
    y0 = torch.rand(3, 2, generator=gen, dtype=DT) * 2 - 1
    full = tms.simulate(system.at(torch.tensor([0.5, 0.3], dtype=DT)), y0, torch.linspace(0, 4, 9, dtype=DT))
    ragged = tms.Trajectories(
        [full.times[: 9 - 2 * k] for k in range(3)], [full.states[k, : 9 - 2 * k] for k in range(3)]
    )
    residuals, _, offsets = tf._shooting(ragged, "single", dict(rtol=1e-10, atol=1e-12, what="test"), system)
    features = FeatureKernel(2, 2).to(DT).features
    p = features(y0).shape[1]
    beta = 0.01 * torch.randn(p, 2, generator=gen, dtype=DT)
    active = torch.rand(p, 2, generator=gen) > 0.3
    v = torch.tensor([0.1, -0.2], dtype=DT)
    m, s = system.parameters.mean.to(DT), system.parameters.scale.to(DT)

    def make_fields(bs, vs=None):
        vs = v if vs is None else vs
        known = system.at(m + s * vs).known_rhs if vs.dim() == 1 else system.copies_rhs(m + s * vs)

        def field(y, t=None, u=None):
            f = features(y).reshape(bs.shape[0], -1, p)
            return known(y, t, u) + torch.einsum("mkp,mpo->mko", f, bs).reshape(y.shape[0], -1)

        return field

    def make_field(b):
        return make_fields(b.unsqueeze(0))

    sd = torch.full((2,), 1e-2, dtype=DT)
    off = 0.1 * torch.randn(offsets.shape, generator=gen, dtype=DT)
    joint = tm._joint_columns(residuals, make_fields, beta, active, v, off, sd)
    # the reference: one solve per perturbation, plain central differences
    cols, h = [], 1e-5
    typical = float(beta.abs().max()) * 1e-3
    for i, o in active.nonzero().tolist():
        step = tm._step(float(beta[i, o]), typical)
        plus, minus = beta.clone(), beta.clone()
        plus[i, o] += step
        minus[i, o] -= step
        diff = residuals(make_field(plus), off, sd) - residuals(make_field(minus), off, sd)
        cols.append(diff / (2 * step) / sd)
    for j in range(2):
        dv = torch.zeros(2, dtype=DT)
        dv[j] = h
        up = residuals(make_fields(beta.unsqueeze(0), v + dv), off, sd)
        down = residuals(make_fields(beta.unsqueeze(0), v - dv), off, sd)
        cols.append((up - down) / (2 * h) / sd)
    rows = residuals.experiment
    offset_cols = {}
    for j in range(2):  # offset (experiment e, component j) moves only experiment e's rows
        up, down = off.clone(), off.clone()
        up[:, j] += h
        down[:, j] -= h
        delta = (residuals(make_field(beta), up, sd) - residuals(make_field(beta), down, sd)) / (2 * h) / sd
        for e in range(3):
            offset_cols[e, j] = torch.where((rows == e).unsqueeze(-1), delta, torch.zeros_like(delta))
    cols += [offset_cols[e, j] for e in range(3) for j in range(2)]  # the columns' order: experiment, component
    reference = torch.stack([c.reshape(-1) for c in cols], dim=1)
    assert joint.shape == reference.shape == (ragged.num_samples * 2, int(active.sum()) + 2 + 3 * 2)
    torch.testing.assert_close(joint, reference, rtol=1e-5, atol=1e-6 * float(reference.abs().max()))


def test_the_widened_box_ignores_nan_and_leaves_an_unseen_component_unbounded():
    points = torch.tensor([[0.0, math.nan], [1.0, math.nan], [math.nan, math.nan]], dtype=DT)
    lo, hi = _ode.widened_box(points, 10.0)
    assert lo.tolist() == [-10.0, -math.inf] and hi.tolist() == [11.0, math.inf]


def test_a_held_out_prediction_that_blows_up_is_stopped_at_the_box_and_scores_infinity():
    """Experiment 1's model blows up in finite time (dy/dt = y^2 from 1 reaches infinity at t = 1); it is stopped
    where it leaves the box of the data widened HELD_OUT_WIDTHS times, its residuals infinite from there, while
    experiment 0's stay finite, in one solve that does not run to its step limit."""
    times = torch.linspace(0.0, 2.0, 9, dtype=DT)
    states = torch.stack([torch.exp(-times), torch.exp(-times)]).unsqueeze(-1)  # (2, 9, 1)
    data = tms.Trajectories(times, states)
    system = tms.MisspecifiedSystem(lambda y: -y, 1)

    def field(y, rows, t=None, u=None):
        return torch.where((rows == 1).unsqueeze(-1), y.pow(2), -y)

    r = predicted_residuals(system, data, field)
    assert bool(torch.isfinite(r[0]).all()) and float(r[0].abs().max()) < 1e-5
    assert math.isinf(float(r[1, -1, 0]))
    left = int(torch.isinf(r[1, :, 0]).nonzero()[0])
    assert 1 <= left <= 4  # beyond the box (hi = 1 + 10 widths) before t = 1, where the true path blows up
    assert HELD_OUT_WIDTHS == 10.0


def test_a_component_given_only_at_the_start_does_not_bound_the_prediction():
    """R of an SIR-like chain is 0 at the start and never measured after: its growth is not a blow-up (the box of
    a component measured only in the first row is unbounded), and the measured component's residuals stay 0."""
    times = torch.linspace(0.0, 3.0, 7, dtype=DT)
    system = tms.MisspecifiedSystem(lambda y: torch.stack([-y[..., 0], y[..., 0]], dim=-1), 2)
    truth = tms.simulate(system, torch.tensor([[100.0, 0.0]], dtype=DT), times).states
    states = truth.clone()
    states[:, 1:, 1] = math.nan
    r = predicted_residuals(
        system, tms.Trajectories(times, states), lambda y, rows, t=None, u=None: system.known_rhs(y)
    )
    assert float(r[0, :, 0].abs().max()) < 1e-2  # the solver tolerance on values of 100
