"""The one batched solve: step limits, and clear errors for models and inputs a solver cannot handle."""

import pytest
import torch

import torchmisspec as tms
from torchmisspec.systems import MisspecifiedSystem

DT = torch.float64
Y0 = torch.tensor([[0.5, 0.5], [0.1, -0.2]], dtype=DT)
T01 = torch.tensor([0.0, 1.0], dtype=DT)


def test_step_limit_stops_a_stiff_solve_and_names_the_place():
    stiff = MisspecifiedSystem(lambda y: -1e4 * y, 1, name="stiff")
    with pytest.raises(
        tms.IntegrationError,
        match=r"simulate\(stiff\): the solver took more than 50 steps .* "
        r"stopped at t = .* of \[0, 10\].*raise max_steps",
    ):
        tms.simulate(stiff, torch.ones(1, 1, dtype=DT), torch.tensor([0.0, 10.0], dtype=DT), max_steps=50)


def test_step_limit_holds_for_absurd_time_spans():
    with pytest.raises(tms.IntegrationError, match="more than 30 steps"):
        tms.simulate(tms.systems.paper_linear(), Y0, torch.tensor([0.0, 1e300], dtype=DT), max_steps=30)


def test_step_limit_in_predict_and_proxies():
    system = tms.systems.paper_linear()
    times = torch.linspace(0, 6, 11, dtype=DT)
    s = tms.correction_samples(tms.simulate(system, Y0, times), system, derivative="oracle")
    ode = tms.CorrectedODE(
        system, tms.CorrectionGP(lengthscale=1.0, outputscale=1e-4, noise_variance=1e-4).fit(s.inputs, s.targets)
    )
    with pytest.raises(tms.IntegrationError, match=r"CorrectedODE.predict: the solver took more than 2 steps"):
        ode.predict(Y0, times, solver=tms.Solver(max_steps=2))
    gravity = tms.systems.paper_gravity()
    cand = torch.tensor([[1.0, 0.0, 0.0, 0.45]], dtype=DT)
    with pytest.raises(tms.IntegrationError, match="more than 3 steps"):
        tms.design.proxy_trajectories(gravity, cand, torch.linspace(0, 3, 5, dtype=DT), max_steps=3)


def test_singularity_reached_during_the_solve():
    pole = MisspecifiedSystem(lambda y: -1 / (1 + 3 * y), 1, correction=lambda y: -torch.ones_like(y), name="pole")
    with pytest.raises(tms.IntegrationError, match=r"simulate\(pole\): the solver gave up at t = 0\.1"):
        tms.simulate(pole, torch.zeros(2, 1, dtype=DT), T01)


def test_callbacks_with_the_wrong_output_shape_or_nan():
    narrow = MisspecifiedSystem(lambda y: y[..., :1], 2, name="narrow")
    with pytest.raises(
        tms.ShapeError, match=r"system .narrow.: G returned shape \(2, 1\) for inputs of shape \(2, 2\)"
    ):
        tms.simulate(narrow, Y0, T01)
    nan = MisspecifiedSystem(lambda y: y * float("nan"), 2, name="nan")
    with pytest.raises(tms.IntegrationError, match=r"not finite at 2 initial condition\(s\) \(indices \[0, 1\]\)"):
        tms.simulate(nan, Y0, T01)


def test_bad_states_times_and_options():
    system = tms.systems.paper_linear()
    with pytest.raises(tms.InputError, match="expected float32 or float64 states, got torch.bfloat16"):
        tms.simulate(system, Y0.bfloat16(), T01)
    with pytest.raises(tms.ShapeError, match=r"y0: expected at least one initial condition, got shape \(0, 2\)"):
        tms.simulate(system, torch.zeros(0, 2, dtype=DT), T01)
    with pytest.raises(tms.ShapeError, match=r"times: expected at least one time, got shape \(0,\)"):
        tms.simulate(system, Y0, torch.zeros(0, dtype=DT))
    with pytest.raises(
        tms.InputError, match='expected solver settings torchdiffeq accepts, got a refusal: Invalid method "bogus"'
    ):
        tms.simulate(system, Y0, T01, method="bogus")
    with pytest.raises(tms.InputError, match="max_steps: expected an integer >= 1, got 0"):
        tms.simulate(system, Y0, T01, max_steps=0)


def test_float32_solves_stay_float32_and_agree():
    system = tms.systems.paper_linear()
    times = torch.linspace(0, 6, 7, dtype=DT)
    ref = tms.simulate(system, Y0, times).states
    got = tms.simulate(system, Y0.float(), times.float(), rtol=1e-6, atol=1e-7).states
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), ref, rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    ("method", "options"),
    [("dopri5", None), ("dopri5", {"jump_t": torch.tensor([2.5, 7.0], dtype=torch.float64)}), ("bosh3", None),
     ("rk4", {"step_size": 0.05})],
)  # fmt: skip
@pytest.mark.parametrize("ragged", [False, True], ids=["shared", "per-row"])
def test_long_grids_interpolate_each_step_at_once_with_torchdiffeqs_numbers(method, options, ragged):
    """_integrate evaluates the outputs inside a step together, and on per-row grids only each row's own: the same
    steps and numbers as torchdiffeq's odeint on the union of the grids (which evaluates every output time one by
    one, for every row), values to the bit and gradients to rounding, on grids long enough to take that path."""
    from torchdiffeq import odeint

    from torchmisspec._ode import _VECTOR_OUTPUTS, _integrate

    g = torch.Generator().manual_seed(0)
    rows = 7
    shape = (rows, 2 * _VECTOR_OUTPUTS) if ragged else (5 * _VECTOR_OUTPUTS,)
    grid = torch.sort(torch.rand(shape, generator=g, dtype=torch.float64) * 10, dim=-1).values
    grid[..., 0] = 0.0
    y0 = torch.rand(rows, 2, generator=g, dtype=torch.float64).requires_grad_(True)

    def field(t, y):
        step = 1.0 + (t > 2.5).to(y) - 0.5 * (t > 7.0).to(y)  # a field that jumps where jump_t says
        return torch.stack([y[..., 1], -step * torch.sin(y[..., 0])], -1)

    ours = _integrate(field, y0, grid, method, 1e-7, 1e-9, options)
    union, inverse = torch.unique(grid.reshape(-1), sorted=True, return_inverse=True)
    theirs = odeint(field, y0, union, method=method, rtol=1e-7, atol=1e-9, options=options).transpose(0, 1)
    if ragged:
        theirs = torch.gather(theirs, 1, inverse.reshape(grid.shape).unsqueeze(-1).expand(-1, -1, 2))
    assert ours.shape == theirs.shape and torch.equal(ours, theirs)
    (g_ours,) = torch.autograd.grad(ours.square().sum(), y0)
    (g_theirs,) = torch.autograd.grad(theirs.square().sum(), y0)
    torch.testing.assert_close(g_ours, g_theirs, rtol=1e-10, atol=0.0)  # sums of the same terms, in another order


def test_a_row_that_leaves_the_box_stops_there_and_the_others_are_solved_as_alone():
    """solve(box=...): a row whose state leaves the box stops just outside it (its derivative is 0 from then on),
    so it does not hold back the batch; the other rows get what they get solved without it."""
    from torchmisspec._ode import solve

    growth = torch.tensor([[3.0], [-0.5], [0.2]], dtype=DT)  # y' = a y: the first leaves [-2, 2] near t = 0.23

    def field(y):
        return growth.to(y) * y

    y0 = torch.ones(3, 1, dtype=DT)
    times = torch.linspace(0, 2, 9, dtype=DT)
    box = (torch.tensor([-2.0], dtype=DT), torch.tensor([2.0], dtype=DT))
    states, _ = solve(field, y0, times, box=box)
    assert bool((states[0, 1:] > 2).all()) and float(states[0, -1]) < 2.5  # stopped just outside, not e^6
    torch.testing.assert_close(states[1:, :, 0], torch.exp(growth[1:] * times), rtol=1e-6, atol=1e-9)


def test_a_floor_resolves_a_state_that_falls_far_below_its_start():
    """A depot emptied at rate 2 is measured down to 1e-9 of its dose: compared in logarithms (relative noise), the
    solve must resolve it there. At the fitting tolerances alone its logarithm is off by more than 0.1 (a 5 % noise
    is 0.05); with its smallest measured value as ``floor``, to 1e-3."""
    from torchmisspec._ode import FITTING_TOLERANCES, solve

    times = torch.linspace(0.0, 10.0, 21, dtype=torch.float64)
    y0 = torch.tensor([[4.5, 0.0]], dtype=torch.float64)
    exact = (4.5 * torch.exp(-2.0 * times)).log()

    def depot(y):
        return torch.stack([-2.0 * y[..., 0], 2.0 * y[..., 0] - 0.1 * y[..., 1]], -1)

    rtol, atol = FITTING_TOLERANCES
    loose, _ = solve(depot, y0, times, rtol=rtol, atol=atol)
    floor = torch.tensor([float(exact[-1].exp()), float("nan")], dtype=torch.float64)
    tight, _ = solve(depot, y0, times, rtol=rtol, atol=atol, floor=floor)
    assert float((loose[0, :, 0].clamp_min(1e-300).log() - exact).abs().max()) > 0.1
    assert float((tight[0, :, 0].log() - exact).abs().max()) < 1e-3
