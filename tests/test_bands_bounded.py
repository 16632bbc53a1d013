"""Bands in seconds, always finite (issue 41 item 5): posterior draws that diverge stop at a bounded region in one
batched solve (never integrated to the step limit, never isolated one by one), the bands come from the draws that
remain (the fraction reported, a warning naming the draws), and a forecast whose solve fails late returns what it
has, flagged."""

from __future__ import annotations

import dataclasses
import math
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.prediction._bands import band_quantiles
from torchmisspec.systems import MisspecifiedSystem

DT = torch.float64


class _Counted:
    """G = 0 that counts its evaluations: every right-hand-side evaluation of every solve (failed ones too)."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, y: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        return torch.zeros_like(y)


@pytest.fixture
def quadratic():
    """Quadratic draws of F (polynomial kernel of degree 2, a large prior, data near 0 only): under many draws the
    path from 1 or 2 blows up in finite time, while the posterior mean (near 0) does not."""
    G = _Counted()
    system = MisspecifiedSystem(G, 1, name="zero")
    X = torch.linspace(-0.1, 0.1, 5, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(kernel="polynomial", degree=2, outputscale=25.0, noise_variance=1e-2)
    gp.fit(X, torch.zeros(5, 1, dtype=DT))
    return G, tms.CorrectedODE(system, gp)


Y0 = torch.tensor([[1.0], [2.0]], dtype=DT)
TIMES = torch.linspace(0, 5, 6, dtype=DT)


def _posterior(ode, num_samples: int = 32):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        post = ode.posterior(Y0, TIMES, num_samples=num_samples, generator=torch.Generator().manual_seed(0), scale=1.0)
    return post, [str(w.message) for w in caught if issubclass(w.category, tms.TorchMisspecWarning)]


def test_diverging_draws_stop_at_the_region_in_bounded_evaluations(quadratic, one_thread):
    """Before: every diverging draw was integrated alone to the step limit (or a stall), by bisection over its output
    times: about 10^5 evaluations of G (100 s) for these 64 paths. Now one batched solve stops them at the region."""
    G, ode = quadratic
    post, _ = _posterior(ode)
    left = torch.isnan(post.samples).any(-1).any(-1)  # (S, B)
    assert bool(left.any()) and not bool(left.all())  # the case: some draws diverge, not all
    # the mean path and one batched solve of the draws, each far below one solve run to the step limit (7 x 10^4)
    assert G.calls < 3000, G.calls


def test_bands_come_from_the_draws_that_remain(quadratic, one_thread):
    G, ode = quadratic
    post, messages = _posterior(ode)
    S, B = post.samples.shape[:2]
    lo, hi = post.region
    assert lo.shape == hi.shape == (1,) and float(lo) < -0.1 and float(hi) > 2.0  # around the data and the paths
    left = torch.isnan(post.samples).any(-1).any(-1)  # (S, B): the draws that left the region
    # a draw that left is NaN from the first output outside the region on, and finite (inside it) before
    for s, b in left.nonzero().tolist():
        path = post.samples[s, b, :, 0]
        finite = torch.isfinite(path)
        assert bool(finite[: int(finite.sum())].all()) and bool(finite[0])
        assert bool(((path[finite] >= lo) & (path[finite] <= hi)).all())
    remaining = 1.0 - left.double().mean(0)
    assert torch.allclose(post.fraction_remaining, remaining)
    n_left = int(left.sum())
    [message] = [m for m in messages if "left the region" in m]
    assert f"{n_left} of {S * B} sampled paths left the region" in message
    assert "initial condition" in message and "fraction_remaining" in message
    # the band: the order statistics of all the draws at each time, at ranks (S + 1)(1 -/+ level) / 2, a draw that
    # left counted at the edge it crossed (censored: the quadratic draws blow up upwards); as the draws that remain
    # when the sides are not recorded (conditional on remaining, as before)
    crossed = post.escaped[torch.isnan(post.samples)]
    assert bool((crossed != 0).all())  # every draw that left crossed an edge in its one component
    censored = torch.where(post.escaped > 0, hi, torch.where(post.escaped < 0, lo, post.samples))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lower, upper = post.interval(0.5)
        kept_lower, kept_upper = dataclasses.replace(post, escaped=None).interval(0.5)
    for b in range(B):
        for t in range(TIMES.numel()):
            expected = torch.quantile(censored[:, b, t, 0], band_quantiles(0.5, S))
            assert torch.allclose(torch.stack([lower[b, t, 0], upper[b, t, 0]]), expected)
            values = post.samples[:, b, t, 0]
            values = values[torch.isfinite(values)]
            expected = torch.quantile(values, band_quantiles(0.5, values.numel()))
            assert torch.allclose(torch.stack([kept_lower[b, t, 0], kept_upper[b, t, 0]]), expected)
    assert bool((upper >= kept_upper).all())  # the draws that diverged upwards no longer pull the band down
    edge = bool(((lower <= lo) | (upper >= hi)).any())
    assert edge == any("reaches its edge" in str(w.message) for w in caught)
    assert bool(torch.isfinite(lower).all() & torch.isfinite(upper).all())
    assert bool(torch.isfinite(post.mean).all() & torch.isfinite(post.stddev).all())
    assert bool(torch.isfinite(post.quantile([0.1, 0.5, 0.9])).all())


def test_too_few_remaining_draws_reach_the_regions_edge_finite_with_a_warning(quadratic, one_thread):
    """More than the band's tail of the draws left upwards: the band's upper end is the region's edge there (finite,
    with a warning); without the sides recorded, those entries are NaN as before, with that warning."""
    G, ode = quadratic
    post, _ = _posterior(ode, num_samples=20)  # a 0.9 band needs 19 draws
    n = torch.isfinite(post.samples[..., 0]).sum(0)  # (B, T) draws remaining
    short = n < 19
    assert bool(short.any()) and not bool(short.all())
    with pytest.warns(tms.TorchMisspecWarning, match=r"interval: at \d+ of 12 entries so many draws left"):
        lower, upper = post.interval(0.9)
    assert bool(torch.isfinite(lower).all() & torch.isfinite(upper).all())
    assert bool((upper[..., 0][short] == post.region[1]).all())
    blind = dataclasses.replace(post, escaped=None)
    with pytest.warns(tms.TorchMisspecWarning, match=r"interval: at \d+ of 12 entries fewer than 19 draws") as rec:
        lower, upper = blind.interval(0.9)
    assert any("NaN" in str(w.message) and "num_samples" in str(w.message) for w in rec)
    assert torch.equal(torch.isnan(lower[..., 0]), short) and torch.equal(torch.isnan(upper[..., 0]), short)


def test_all_draws_remaining_is_unchanged(one_thread):
    """No draw leaves the region: every draw counts, the fraction is 1 and no warning names left draws."""
    system = tms.systems.paper_linear()
    y0 = torch.rand(8, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    traj = tms.simulate(system, y0, torch.linspace(0, 6, 11, dtype=DT))
    samples = tms.correction_samples(traj, system, derivative="oracle", noise_std=1e-3)
    ode = tms.CorrectedODE(system, tms.CorrectionGP().fit(samples))
    with warnings.catch_warnings():
        warnings.simplefilter("error", tms.TorchMisspecWarning)
        post = ode.posterior(y0[:2] * 0.5, torch.linspace(0, 2, 5, dtype=DT), num_samples=16, scale=1.0)
    assert torch.equal(post.fraction_remaining, torch.ones(2, dtype=DT))
    assert bool(torch.isfinite(post.samples).all())
    lower, upper = post.interval(0.5)
    expected = torch.quantile(post.samples, band_quantiles(0.5, 16), dim=0)
    assert torch.equal(lower, expected[0]) and torch.equal(upper, expected[1])


@pytest.fixture
def riccati():
    """dy/dt = y^2 (G) + F, F ~ 0.1 y^2 learned: from 0.5 the path blows up at t = 1 / (1.1 * 0.5) ~ 1.82; from -0.5
    it decays to 0."""
    system = MisspecifiedSystem(lambda y: y**2, 1, name="riccati")
    x = torch.linspace(-1, 3, 30, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1.0, noise_variance=1e-4).fit(x, 0.1 * x**2)
    return tms.CorrectedODE(system, gp)


def test_a_forecast_that_fails_late_returns_what_it_has_flagged(riccati, one_thread):
    times = torch.linspace(0, 2, 5, dtype=DT)
    y0 = torch.tensor([[0.5], [-0.5]], dtype=DT)
    match = r"1 of 2 forecast\(s\) stop early \(initial condition\(s\) \[0\], their last output reached at t = 1\.5\)"
    with pytest.warns(tms.TorchMisspecWarning, match=match + r".*model\.incomplete.*stalled at t = 1\.8"):
        states = riccati.predict(y0, times)
    assert states.shape == (2, 5, 1)
    assert riccati.incomplete.tolist() == [True, False]
    assert bool(torch.isfinite(states[0, :4]).all()) and bool(torch.isnan(states[0, 4:]).all())
    alone = riccati.predict(y0[1:], times)  # the row that does integrate: as solved without the failing one
    assert torch.allclose(states[1], alone[0], rtol=1e-6, atol=1e-9)
    assert riccati.incomplete.tolist() == [False]
    # the part it has agrees with the solve of the same row to the last time it reaches
    before = riccati.predict(y0[:1], times[:4])
    assert torch.allclose(states[0, :4], before[0], rtol=1e-6, atol=1e-9)


def test_a_quoted_message_is_cut_at_a_clause_not_mid_word():
    """A solver's failure quoted in a warning is cut at the end of a clause (a Soybean trial's ended "shorten the
    time span, sta")."""
    from torchmisspec._errors import clipped

    text = "the solver gave up at t = 73.26 (underflow); the rows with the largest state: [26, 54]. " + "A path " * 40
    assert (
        clipped(text) == "the solver gave up at t = 73.26 (underflow); the rows with the largest state: [26, 54]. ..."
    )
    words = "word " * 100
    assert clipped(words, 50) == "word " * 9 + "word ..." and clipped("short", 50) == "short"


def test_a_forecast_with_nothing_computed_still_raises(riccati):
    with pytest.raises(tms.IntegrationError, match="blows up"):
        riccati.predict(torch.tensor([[2.0]], dtype=DT), torch.linspace(0, 2, 5, dtype=DT))


def test_the_posterior_of_a_forecast_that_fails_late_is_flagged_not_raised(riccati, one_thread):
    times = torch.linspace(0, 2, 5, dtype=DT)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        post = riccati.posterior(torch.tensor([[0.5]], dtype=DT), times, num_samples=8, scale=1.0)
    messages = [str(w.message) for w in caught]
    assert any("stop early" in m for m in messages)
    assert bool(torch.isnan(post.mean_path[0, 4:]).all()) and bool(torch.isfinite(post.mean_path[0, :4]).all())
    assert not math.isnan(float(post.fraction_remaining[0]))


def test_the_command_line_predicts_with_diverging_draws_and_says_so(tmp_path, capsys, one_thread):
    """``torchmisspec predict`` on a model whose draws diverge: the table is written, finite bands from the draws
    that remain, and one line on stdout says how many left (warnings one line each on stderr)."""
    from torchmisspec.cli import main

    (tmp_path / "zero.py").write_text(
        "import torch\nimport torchmisspec as tms\n\n\ndef zero():\n"
        "    return tms.MisspecifiedSystem(lambda y: torch.zeros_like(y), 1, name='zero', state_names=('x',))\n"
    )
    X = torch.linspace(-0.1, 0.1, 5, dtype=DT).unsqueeze(-1)
    gp = tms.CorrectionGP(kernel="polynomial", degree=2, outputscale=25.0, noise_variance=1e-2)
    gp.fit(X, torch.zeros(5, 1, dtype=DT))
    gp.save(tmp_path / "model.pt")
    (tmp_path / "initial.csv").write_text("x\n1.0\n2.0\n")
    out = tmp_path / "pred.csv"
    argv = ["predict", "--system", f"{tmp_path / 'zero.py'}:zero", "--model", str(tmp_path / "model.pt")]
    argv += ["--initial", str(tmp_path / "initial.csv"), "--times", "0:5:6", "--samples", "32", "--out", str(out)]
    argv += ["--level", "0.5"]  # enough draws remain everywhere for it
    assert main(argv) == 0
    captured = capsys.readouterr()
    [line] = [x for x in captured.out.splitlines() if x.startswith("predicted")]
    assert "draws of 2 initial condition(s) left the region" in line
    assert "left the region" in captured.err and "Traceback" not in captured.err
    rows = [r.split(",") for r in out.read_text().splitlines()[1:]]
    assert len(rows) == 12 and all(math.isfinite(float(v)) for r in rows for v in r[2:])


class _Growth(_Counted):
    """G(y) = y (exponential growth) that counts its evaluations."""

    def __call__(self, y: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        return y


def test_a_diverging_mean_path_does_not_carry_the_region_with_it(one_thread):
    """The UDE Lotka-Volterra case (699 s): the mean path itself grows without bound (the data saw y in [1, 2.7],
    the forecast goes to e^10), and the region widened around it let rough prior draws of F (lengthscale 0.2) wander
    over a box thousands wide. The region now stays within the data's box widened ten times, whatever the mean path
    does, and the draws stop there."""
    G = _Growth()
    system = MisspecifiedSystem(G, 1, name="growth")
    t = torch.linspace(0, 1, 11, dtype=DT)
    data = tms.Trajectories(t, torch.exp(t).reshape(1, -1, 1), state_names=["y"])
    samples = tms.correction_samples(data, system, derivative="central")
    gp = tms.CorrectionGP(lengthscale=0.2, outputscale=4.0, noise_variance=1e-4).fit(samples)
    gp.samples_ = samples
    ode = tms.CorrectedODE(system, gp)
    times = torch.linspace(0, 10, 41, dtype=DT)
    G.calls = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        post = ode.posterior(
            torch.ones(1, 1, dtype=DT), times, num_samples=32, generator=torch.Generator().manual_seed(0)
        )
    assert float(post.mean_path.max()) > 1e4  # the case: the forecast leaves the data far behind
    lo, hi = (float(b) for b in post.region)
    states = samples.states[:, 0]
    width = float(states.max() - states.min())
    assert hi <= float(states.max()) + 10 * width + 1e-9 and lo >= float(states.min()) - 10 * width - 1e-9
    assert float(post.fraction_remaining.max()) < 0.5  # most draws left with the mean path, and were stopped
    assert G.calls < 5000, G.calls


def test_a_draw_that_left_in_one_component_leaves_the_other_anywhere_in_the_region():
    """Two states; 15 of 20 draws left across the upper edge of the first: its band's upper end is that edge; the
    second component of those draws is unknown, and the 5 that remain are too few for a 0.9 band: its band is the
    whole region, finite. With 3 of 20 gone, the second component's 0.5 band is that of the 17 that remain."""
    from torchmisspec.prediction._bands import TrajectoryPosterior

    S = 20
    samples = torch.full((S, 1, 1, 2), math.nan, dtype=DT)
    samples[:5, 0, 0] = torch.tensor([[0.1, 0.2], [0.2, 0.1], [0.3, 0.3], [0.4, 0.5], [0.5, 0.4]], dtype=DT)
    escaped = torch.zeros(samples.shape, dtype=torch.int8)
    escaped[5:, 0, 0, 0] = 1
    region = (torch.tensor([-1.0, -2.0], dtype=DT), torch.tensor([1.0, 2.0], dtype=DT))
    post = TrajectoryPosterior(
        times=torch.zeros(1, 1, dtype=DT), samples=samples, mean_path=samples[0], support=torch.zeros(1, 1),
        extrapolating=torch.zeros(1, dtype=torch.bool), threshold=0.7, region=region, escaped=escaped,
    )  # fmt: skip
    with pytest.warns(tms.TorchMisspecWarning, match="reaches its edge"):
        lower, upper = post.interval(0.9)  # needs 19 draws
    first = torch.cat([samples[:5, 0, 0, 0], torch.ones(15, dtype=DT)])
    expected = torch.quantile(first, band_quantiles(0.9, S))
    assert torch.allclose(torch.stack([lower[0, 0, 0], upper[0, 0, 0]]), expected) and float(upper[0, 0, 0]) == 1.0
    assert float(lower[0, 0, 1]) == -2.0 and float(upper[0, 0, 1]) == 2.0
    few = samples.clone()
    few[:17, 0, 0] = torch.rand(17, 2, generator=torch.Generator().manual_seed(0), dtype=DT) - 0.5
    gone = escaped.clone()
    gone[:17] = 0
    lower, upper = dataclasses.replace(post, samples=few, escaped=gone).interval(0.5)
    expected = torch.quantile(few[:17, 0, 0, 1], band_quantiles(0.5, 17))
    assert torch.allclose(torch.stack([lower[0, 0, 1], upper[0, 0, 1]]), expected)
