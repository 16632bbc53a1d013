"""Edge samples a derivative estimator cannot be trusted at (``torchmisspec.learning.samples._edges``)."""

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.learning.samples._edges import EDGE_ERROR_LIMIT, _positions, unreliable_edges

DT = torch.float64


def _oral_dose(K: int = 6, noise: float = 0.05) -> tuple[tms.MisspecifiedSystem, tms.Trajectories]:
    """A drug absorbed from a depot into the plasma, both measured every 30 min for 10 h: the concentration rises
    from 0 at 8 mg/L/h at the first sample (an edge the smoothers see one-sidedly); F a saturable elimination."""

    def known(y):
        gut, conc = y[..., 0], y[..., 1]
        return torch.stack([-1.2 * gut, 1.2 * gut / 0.45 - 0.1 * conc], -1)

    system = tms.MisspecifiedSystem(
        known,
        2,
        correction=lambda x: -0.4 * x / (2 + x),
        correction_inputs=["conc"],
        correction_outputs=["conc"],
        state_names=["gut", "conc"],
    )
    g = torch.Generator().manual_seed(0)
    times = torch.arange(21, dtype=DT) * 0.5
    y0 = torch.stack([3.0 + 3.0 * torch.rand(K, generator=g, dtype=DT), torch.zeros(K, dtype=DT)], -1)
    states = tms.simulate(system, y0, times).states.clone()
    states[:, 1:] *= torch.exp(noise * torch.randn(K, 20, 2, generator=g, dtype=DT))
    return system, tms.Trajectories(times, states, state_names=["gut", "conc"])


@pytest.mark.filterwarnings("ignore:correction_samples")  # the kept samples' own self-check: 0.76 (small F)
def test_auto_leaves_out_the_first_sample_where_the_path_bends_sharply():
    system, data = _oral_dose()
    samples = tms.correction_samples(data, system)
    assert samples.targets.shape[0] == 6 * 20
    assert "6 edge samples left out" in samples.derivative
    assert bool((samples.inputs[:, 0] > 0).all())  # the concentration-0 rows (t = 0) are the ones left out
    first = torch.ones(6 * 21, dtype=torch.bool)
    first[torch.arange(6) * 21] = False
    kept = tms.correction_samples(data, system, derivative="oracle")
    assert torch.equal(samples.inputs, kept.inputs[first])
    # what the edge samples would have taught: F near 0 far off the truth (-0.01 at 0.05 mg/L)
    name, options = samples.derivative.split(";")[0].split(" ", 1)
    opts = {k: int(v) for k, v in (o.split("=") for o in options.split())}
    every = tms.correction_samples(data, system, derivative=name, **opts)
    assert every.targets.shape[0] == 6 * 21  # an explicit estimator keeps every sample
    at_zero = every.targets[torch.arange(6) * 21, 0]
    assert float(at_zero.abs().mean()) > EDGE_ERROR_LIMIT * float(every.targets.pow(2).mean().sqrt())


def test_auto_keeps_every_sample_where_the_edges_do_not_stand_out():
    system = tms.MisspecifiedSystem(
        lambda y: -0.5 * y, 1, correction=lambda y: -0.1 * y**2, state_names=["x"], name="decay"
    )
    times = torch.linspace(0, 4, 21, dtype=DT)
    data = tms.simulate(system, torch.tensor([[1.0], [2.0], [3.0]], dtype=DT), times)
    samples = tms.correction_samples(data, system)
    assert samples.targets.shape[0] == 3 * 21
    assert "left out" not in samples.derivative


def test_positions_count_from_the_nearer_end():
    pos = _positions([5, 2, 7], reach=2, device="cpu")
    assert pos.tolist() == [0, 1, 2, -2, -1, 0, -1, 0, 1, 2, 2, 2, -2, -1]


def _errors(lengths, at, big, small=0.1):
    rows = []
    for n in lengths:
        e = torch.full((n, 1), small, dtype=DT)
        e[at if at >= 0 else n + at] = big
        rows.append(e)
    return torch.cat(rows)


@pytest.mark.parametrize("at", [0, 1, -1, -2])
def test_unreliable_edges_flags_exactly_the_position_that_stands_out(at):
    lengths = [9, 12, 10]
    out, _, worst = unreliable_edges(_errors(lengths, at, 3.0), torch.ones(20, 1, dtype=DT), lengths, [11, 9], 2)
    expected = torch.cat([torch.arange(n) == (at if at >= 0 else n + at) for n in (11, 9)])
    assert torch.equal(out, expected)  # pooled on the copy's lengths, applied at the data's own
    assert worst == pytest.approx(3.0)


def test_unreliable_edges_keeps_all_where_the_interior_is_poor_or_too_much_would_go():
    lengths = [9, 9]
    poor = _errors(lengths, 0, 3.0, small=0.8)
    assert not bool(unreliable_edges(poor, torch.ones(18, 1, dtype=DT), lengths, lengths, 2)[0].any())
    short = [3, 3]  # reach 1: every row but the middle is an edge, two thirds of the samples
    every_edge = torch.tensor([[3.0], [0.1], [3.0]] * 2, dtype=DT)
    assert not bool(unreliable_edges(every_edge, torch.ones(6, 1, dtype=DT), short, short, 1)[0].any())
    nan_rows = _errors(lengths, 0, 3.0)
    nan_rows[0] = math.nan  # a row that gives no sample on the copy is not counted
    out, _, _ = unreliable_edges(nan_rows, torch.ones(18, 1, dtype=DT), lengths, lengths, 2)
    assert out.tolist() == [True] + [False] * 8 + [True] + [False] * 8


def test_the_cli_says_what_auto_chose_and_left_out():
    from types import SimpleNamespace

    from torchmisspec.cli._fit import _derivative

    system, data = _oral_dose()
    with pytest.warns(tms.TorchMisspecWarning):
        samples = tms.correction_samples(data, system)
    gp = SimpleNamespace(derivative_=samples.derivative)
    assert _derivative(SimpleNamespace(derivative="auto"), gp) == f"'auto': {samples.derivative}"
    assert "6 edge samples left out" in _derivative(SimpleNamespace(derivative="auto"), gp)
    assert _derivative(SimpleNamespace(derivative="smooth"), gp) == "'smooth'"
