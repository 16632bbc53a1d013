"""Tests of torchmisspec.design: proxies, information gain, greedy / lazy / naive selection, baselines, bounds."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchmisspec import design
from torchmisspec._errors import BudgetError, InputError, ShapeError
from torchmisspec.data import simulate
from torchmisspec.gp import CorrectionGP
from torchmisspec.systems import paper_gravity, paper_linear

DT = torch.float64
NOISE = 1e-4
TIMES = torch.linspace(0, 6, 11, dtype=DT)


def grid13() -> torch.Tensor:
    g = torch.linspace(-1, 1, 13, dtype=DT)
    return torch.cartesian_prod(g, g)


def make_gp(outputscale: float = 4e-5, lengthscale: float = 1.0, noise: float = NOISE) -> CorrectionGP:
    return CorrectionGP(lengthscale=lengthscale, outputscale=outputscale, noise_variance=noise)


def rbf(x: torch.Tensor, y: torch.Tensor, outputscale: float, lengthscale: float) -> torch.Tensor:
    """Independent RBF formula (not the package's kernel): s * exp(-|x - y|^2 / (2 l^2))."""
    d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    return outputscale * torch.exp(-0.5 * d2 / lengthscale**2)


def brute_gain(
    points: torch.Tensor, outputscale: float, lengthscale: float, d_out: int = 2, noise: float = NOISE
) -> float:
    """(d_out / 2) logdet(I + K / sigma^2) with torch.logdet on an independently built K."""
    if points.shape[0] == 0:
        return 0.0
    K = rbf(points, points, outputscale, lengthscale)
    return 0.5 * d_out * float(torch.logdet(torch.eye(K.shape[0], dtype=DT) + K / noise))


def set_gain(proxies: torch.Tensor, idx, outputscale: float, lengthscale: float = 1.0) -> float:
    idx = list(idx)
    return brute_gain(proxies[idx].reshape(-1, proxies.shape[-1]), outputscale, lengthscale)


# --------------------------------------------------------------------------------------------------- proxies
def test_proxy_linear_matches_simulate_and_closed_form():
    system = paper_linear()
    cand = grid13()[::7]
    prox = design.proxy_trajectories(system, cand, TIMES)
    assert prox.shape == (cand.shape[0], TIMES.shape[0], 2)
    sim = simulate(system, cand, TIMES, known_only=True).states
    torch.testing.assert_close(prox, sim, atol=1e-8, rtol=0)
    A = system.known_matrix
    for i, t in enumerate(TIMES):
        expected = cand @ torch.linalg.matrix_exp(A * t).T
        torch.testing.assert_close(prox[:, i], expected, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(prox[:, 0], cand)


def test_proxy_time_origin_and_true_dynamics():
    system = paper_linear()
    cand = torch.tensor([[0.5, -0.3], [1.0, 1.0]], dtype=DT)
    shifted = design.proxy_trajectories(system, cand, TIMES + 2.0)
    torch.testing.assert_close(shifted, design.proxy_trajectories(system, cand, TIMES))
    true = design.proxy_trajectories(system, cand, TIMES, known_only=False)
    torch.testing.assert_close(true, simulate(system, cand, TIMES).states, atol=1e-7, rtol=0)


def test_proxy_nonlinear_gravity_matches_simulate():
    system = paper_gravity()
    cand = torch.tensor([[1.0, 0.0, 0.0, 0.45], [0.0, -1.5, 0.3, 0.0], [-1.2, 0.8, 0.1, -0.2]], dtype=DT)
    times = torch.linspace(0, 3, 20, dtype=DT)
    prox = design.proxy_trajectories(system, cand, times)
    sim = simulate(system, cand, times, known_only=True).states
    torch.testing.assert_close(prox, sim, atol=1e-6, rtol=0)


# --------------------------------------------------------------------------------------------- the criterion
@pytest.mark.parametrize("outputscale", [4e-5, 1e-2])
def test_information_gain_matches_independent_formula(outputscale):
    gp = make_gp(outputscale)
    pts = torch.rand(30, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    got = design.information_gain(pts, gp, d_out=2)
    assert got == pytest.approx(brute_gain(pts, outputscale, 1.0), rel=1e-10)
    assert design.information_gain(pts, gp, d_out=1) == pytest.approx(got / 2, rel=1e-12)
    assert design.information_gain(pts[:0], gp, d_out=2) == 0.0
    # repeated points are fine: I + K / sigma^2 stays positive definite
    rep = torch.cat([pts, pts, pts[:3]])
    assert design.information_gain(rep, gp, d_out=2) == pytest.approx(brute_gain(rep, outputscale, 1.0), rel=1e-9)


def test_information_gain_needs_d_out_before_fit():
    with pytest.raises(InputError, match="d_out"):
        design.information_gain(torch.zeros(3, 2, dtype=DT), make_gp())


def test_monotone_and_submodular_on_random_subsets():
    system, gp = paper_linear(), make_gp(1e-2)
    cand = torch.rand(25, 2, generator=torch.Generator().manual_seed(3), dtype=DT) * 2 - 1
    prox = design.proxy_trajectories(system, cand, TIMES)

    def f(idx):
        return design.information_gain(prox[list(idx)].reshape(-1, 2), gp, d_out=2) if idx else 0.0

    gen = torch.Generator().manual_seed(4)
    for _ in range(40):
        perm = torch.randperm(25, generator=gen).tolist()
        nb = int(torch.randint(1, 10, (1,), generator=gen))
        na = int(torch.randint(0, nb + 1, (1,), generator=gen))
        B, x = perm[:nb], perm[nb]
        A = B[:na]
        da, db = f(A + [x]) - f(A), f(B + [x]) - f(B)
        assert da >= db - 1e-9  # submodular
        assert db >= -1e-12 and f(B) >= f(A) - 1e-12  # monotone


# --------------------------------------------------------------------------------------------------- greedy
def problems():
    """Several random problems: the 13 x 13 grid, a jittered grid, uniform draws."""
    g = grid13()
    gen = torch.Generator().manual_seed(11)
    yield "grid", g
    yield "jittered", (g + 0.04 * torch.randn(g.shape, generator=gen, dtype=DT)).clamp(-1, 1)
    yield "uniform", torch.rand(150, 2, generator=gen, dtype=DT) * 2 - 1


@pytest.mark.parametrize("outputscale", [4e-5, 1e-2])
def test_lazy_greedy_and_naive_pick_identical_sets(outputscale):
    system, gp = paper_linear(), make_gp(outputscale)
    for name, cand in problems():
        res = {
            m: design.greedy(cand, 9, system=system, times=TIMES, gp=gp, method=m) for m in ("lazy", "plain", "naive")
        }
        ref = res["naive"].indices.tolist()
        for m, r in res.items():
            assert r.indices.tolist() == ref, (name, m)
            torch.testing.assert_close(r.gains, res["naive"].gains, atol=1e-9, rtol=1e-9)
            assert r.method == m
        # the total is the log-determinant of the whole chosen proxy set, computed independently
        prox = simulate(system, cand[ref], TIMES, known_only=True).states
        assert res["lazy"].information_gain == pytest.approx(set_gain(prox, range(9), outputscale), rel=1e-8)
        assert res["lazy"].evaluations < res["plain"].evaluations  # lazy skips evaluations


@pytest.mark.parametrize("outputscale", [4e-5, 1e-2])
def test_incremental_gains_equal_bruteforce_logdets(outputscale):
    system, gp = paper_linear(), make_gp(outputscale)
    cand = grid13()
    res = design.greedy(cand, 9, system=system, times=TIMES, gp=gp)
    prox = simulate(system, cand[res.indices], TIMES, known_only=True).states  # independent proxies
    idx = list(range(9))
    for k in range(1, 10):
        brute = set_gain(prox, idx[:k], outputscale)
        assert float(res.gains[:k].sum()) == pytest.approx(brute, rel=1e-8, abs=1e-10)
    assert res.information_gain == pytest.approx(set_gain(prox, idx, outputscale), rel=1e-8)
    assert bool((res.gains[1:] <= res.gains[:-1] + 1e-12).all())  # greedy gains never increase
    torch.testing.assert_close(res.points, cand[res.indices])
    torch.testing.assert_close(res.proxies, prox, atol=1e-8, rtol=0)
    torch.testing.assert_close(design.marginal_gains(res, cand, system=system, times=TIMES, gp=gp), res.gains)


def test_screened_lazy_greedy_identical_to_plain_greedy():
    """The low-rank bounds only skip work: same picks as plain greedy, with the screening really used."""
    system, gp = paper_linear(), make_gp(1e-2)
    cand = torch.rand(300, 2, generator=torch.Generator().manual_seed(5), dtype=DT) * 2 - 1
    times = torch.linspace(0, 6, 20, dtype=DT)
    plain = design.greedy(cand, 14, system=system, times=times, gp=gp, method="plain")
    screened = design.greedy(
        cand,
        14,
        system=system,
        times=times,
        gp=gp,
        engine=design.Engine(screen=True),
    )
    unscreened = design.greedy(
        cand,
        14,
        system=system,
        times=times,
        gp=gp,
        engine=design.Engine(screen=False),
    )
    assert screened.diagnostics["screening"] and screened.diagnostics["bounds"] > 0
    assert screened.indices.tolist() == plain.indices.tolist() == unscreened.indices.tolist()
    torch.testing.assert_close(screened.gains, plain.gains, atol=1e-9, rtol=1e-9)
    for bs in (1, 64):
        assert (
            design.greedy(
                cand,
                14,
                system=system,
                times=times,
                gp=gp,
                engine=design.Engine(batch_size=bs, screen=True),
            ).indices.tolist()
            == plain.indices.tolist()
        )
    # too few features for useful bounds: screening switches itself off, same picks
    weak = design.greedy(
        cand,
        14,
        system=system,
        times=times,
        gp=gp,
        engine=design.Engine(screen=True, max_rank=8),
    )
    assert not weak.diagnostics["screening"] and weak.indices.tolist() == plain.indices.tolist()


@pytest.mark.parametrize("max_rank", [6, 12, 40])
def test_low_rank_bounds_are_upper_bounds(max_rank):
    """g(c | S) <= g~(c | S) + (d_out / 2)(|S| T + T) e_max / sigma^2 for features of any rank."""
    from torchmisspec.design._greedy import _Problem
    from torchmisspec.design._screening import LowRank as _LowRank

    system, outputscale = paper_linear(), 1e-2
    cand = torch.rand(60, 2, generator=torch.Generator().manual_seed(8), dtype=DT) * 2 - 1
    prob = _Problem(cand, 6, system, TIMES, make_gp(outputscale), None, None, None, 1e-9)
    low = _LowRank(prob, max_rank)
    if not low.useful:  # the bounds are valid anyway; build them regardless for the test
        low = _LowRank.__new__(_LowRank)
        import torchmisspec.design._screening as G

        old, G.SLACK_USELESS = G.SLACK_USELESS, math.inf
        try:
            low.__init__(prob, max_rank)
        finally:
            G.SLACK_USELESS = old
    prox = simulate(system, cand, TIMES, known_only=True).states
    S = [3, 17, 41]
    for k, n in enumerate(S):
        others = [c for c in range(60) if c not in S[:k]]
        bnd = low.bounds(torch.tensor(others), k * TIMES.shape[0])
        for j, c in enumerate(others):
            exact = set_gain(prox, S[:k] + [c], outputscale) - set_gain(prox, S[:k], outputscale)
            assert exact <= float(bnd[j]) + 1e-9
        low.add(n)


def test_greedy_within_1_minus_1_over_e_of_bruteforce(capsys):
    system = paper_linear()
    ratios = []
    for seed, outputscale in itertools.product(range(3), (4e-5, 1e-2)):
        cand = torch.rand(12, 2, generator=torch.Generator().manual_seed(seed), dtype=DT) * 2 - 1
        prox = simulate(system, cand, TIMES, known_only=True).states
        best = max(set_gain(prox, s, outputscale) for s in itertools.combinations(range(12), 3))
        res = design.greedy(cand, 3, system=system, times=TIMES, gp=make_gp(outputscale))
        got = set_gain(prox, res.indices.tolist(), outputscale)
        assert got == pytest.approx(res.information_gain, rel=1e-8)
        assert got >= (1 - 1 / math.e) * best
        ratios.append(got / best)
    with capsys.disabled():
        print(
            f"\ngreedy / brute-force optimum on 12 candidates, K = 3: min {min(ratios):.6f}, "
            f"mean {sum(ratios) / len(ratios):.6f}"
        )
    assert min(ratios) > 0.9  # in practice far above the guarantee


def test_partition_matroid_capacities_and_half_guarantee():
    system, outputscale = paper_linear(), 1e-2
    gp = make_gp(outputscale)
    cand = torch.rand(12, 2, generator=torch.Generator().manual_seed(7), dtype=DT) * 2 - 1
    labels = torch.tensor([5, 5, 5, 5, 7, 7, 7, 7, 9, 9, 9, 9])
    caps = {5: 1, 7: 0, 9: 3}
    prox = simulate(system, cand, TIMES, known_only=True).states
    res = {
        m: design.greedy(cand, 4, system=system, times=TIMES, gp=gp, partition=design.Partition(labels, caps), method=m)
        for m in ("lazy", "plain", "naive")
    }
    picks = res["lazy"].indices.tolist()
    assert res["plain"].indices.tolist() == picks == res["naive"].indices.tolist()
    counts = {lbl: sum(int(labels[i]) == lbl for i in picks) for lbl in caps}
    assert all(counts[lbl] <= caps[lbl] for lbl in caps) and len(set(picks)) == 4
    feasible = [
        s
        for s in itertools.combinations(range(12), 4)
        if all(sum(int(labels[i]) == lbl for i in s) <= c for lbl, c in caps.items())
    ]
    best = max(set_gain(prox, s, outputscale) for s in feasible)
    assert set_gain(prox, picks, outputscale) >= 0.5 * best
    # sequence capacities indexed by label, and a binding capacity changes the design
    seq = design.greedy(
        cand,
        3,
        system=system,
        times=TIMES,
        gp=gp,
        partition=design.Partition(labels % 2, [0, 3]),
    )
    assert set(seq.indices.tolist()) <= {i for i in range(12) if int(labels[i]) % 2 == 1}


def test_duplicate_candidates():
    system, outputscale = paper_linear(), 1e-2
    gp = make_gp(outputscale)
    base = torch.tensor([[0.9, 0.1], [-0.5, 0.7], [0.2, -0.8]], dtype=DT)
    cand = torch.cat([base, base, base[:1]])  # 7 candidates, several identical
    res = {m: design.greedy(cand, 7, system=system, times=TIMES, gp=gp, method=m) for m in ("lazy", "plain", "naive")}
    assert res["lazy"].indices.tolist() == res["plain"].indices.tolist() == res["naive"].indices.tolist()
    r = res["lazy"]
    assert sorted(r.indices.tolist()) == list(range(7))
    assert bool(torch.isfinite(r.gains).all()) and bool((r.gains > 0).all())
    first = {}
    for k, i in enumerate(r.indices.tolist()):
        key = tuple(cand[i].tolist())
        if key in first:
            assert float(r.gains[k]) < first[key]  # a repeat is worth less than the first copy
        else:
            first[key] = float(r.gains[k])
    prox = simulate(system, cand[r.indices], TIMES, known_only=True).states
    assert r.information_gain == pytest.approx(set_gain(prox, range(7), outputscale), rel=1e-8)


def test_gravity_system_uses_correction_inputs():
    system = paper_gravity()
    gen = torch.Generator().manual_seed(2)
    pos = torch.rand(24, 2, generator=gen, dtype=DT) * 3 - 1.5
    pos = pos[pos.norm(dim=1) > 0.8]
    vel = 0.3 * torch.randn(pos.shape, generator=gen, dtype=DT)
    cand = torch.cat([pos, vel], dim=1)
    times = torch.linspace(0, 3, 8, dtype=DT)
    gp = make_gp(1e-3)
    res = {m: design.greedy(cand, 5, system=system, times=times, gp=gp, method=m) for m in ("lazy", "plain", "naive")}
    assert res["lazy"].indices.tolist() == res["plain"].indices.tolist() == res["naive"].indices.tolist()
    prox = simulate(system, cand[res["lazy"].indices], times, known_only=True).states[..., :2]
    assert res["lazy"].information_gain == pytest.approx(set_gain(prox, range(5), 1e-3), rel=1e-7)


def test_progress_bar_shows_picks_and_changes_nothing(capsys, one_thread):
    quiet = design.greedy(grid13(), 3, system=paper_linear(), times=TIMES, gp=make_gp())
    shown = design.greedy(grid13(), 3, system=paper_linear(), times=TIMES, gp=make_gp(), progress=True)
    assert shown.indices.tolist() == quiet.indices.tolist()
    torch.testing.assert_close(shown.gains, quiet.gains, rtol=0, atol=0)
    err = capsys.readouterr().err
    assert "lazy greedy (N=169)" in err and "3/3" in err


# ------------------------------------------------------------------------------------------------ baselines
def test_random_design():
    system, gp, cand = paper_linear(), make_gp(1e-2), grid13()
    a = design.random(cand, 9, generator=torch.Generator().manual_seed(0))
    b = design.random(cand, 9, generator=torch.Generator().manual_seed(0))
    assert a.indices.tolist() == b.indices.tolist() and len(set(a.indices.tolist())) == 9
    assert bool(torch.isnan(a.gains).all()) and math.isnan(a.information_gain)
    c = design.random(cand, 9, generator=torch.Generator().manual_seed(0), system=system, times=TIMES, gp=gp)
    assert c.indices.tolist() == a.indices.tolist()
    prox = simulate(system, cand[c.indices], TIMES, known_only=True).states
    assert c.information_gain == pytest.approx(set_gain(prox, range(9), 1e-2), rel=1e-8)
    greedy = design.greedy(cand, 9, system=system, times=TIMES, gp=gp)
    assert greedy.information_gain > c.information_gain
    labels = torch.arange(169) % 3
    d = design.random(
        cand,
        5,
        generator=torch.Generator().manual_seed(1),
        partition=design.Partition(labels, {0: 0, 1: 2, 2: 3}),
    )
    counts = torch.bincount(labels[d.indices], minlength=3).tolist()
    assert counts == [0, 2, 3]


def test_agnostic_design_uses_constant_proxies():
    system, gp, cand = paper_linear(), make_gp(1e-2), grid13()
    res = design.agnostic(cand, 6, system=system, times=TIMES, gp=gp)
    const = cand.unsqueeze(1).expand(-1, TIMES.shape[0], -1)
    ref = design.greedy(cand, 6, system=system, gp=gp, proxy=design.Proxy(paths=const), method="naive")
    assert res.indices.tolist() == ref.indices.tolist() and res.method == "agnostic-lazy"
    T = TIMES.shape[0]
    assert float(res.gains[0]) == pytest.approx(math.log1p(T * 1e-2 / NOISE), rel=1e-10)  # d_out / 2 = 1
    assert res.indices.tolist() != design.greedy(cand, 6, system=system, times=TIMES, gp=gp).indices.tolist()


# --------------------------------------------------------------------------------------------- proxy vs truth
def test_true_information_gain_and_theorem1_bound():
    system, gp, cand = paper_linear(), make_gp(1e-2), grid13()
    res = design.greedy(cand, 4, system=system, times=TIMES, gp=gp)
    true = simulate(system, cand[res.indices], TIMES).states
    exact = design.true_information_gain(res, cand, system=system, times=TIMES, gp=gp)
    assert exact == pytest.approx(brute_gain(true.reshape(-1, 2), 1e-2, 1.0), rel=1e-8)
    check = design.proxy_check(res.indices, cand, system=system, times=TIMES, gp=gp)
    assert check.proxy_gain == pytest.approx(res.information_gain, rel=1e-8)
    assert check.exact_gain == pytest.approx(exact, rel=1e-10)
    Kt = rbf(true.reshape(-1, 2), true.reshape(-1, 2), 1e-2, 1.0)
    Kp = rbf(res.proxies.reshape(-1, 2), res.proxies.reshape(-1, 2), 1e-2, 1.0)
    assert check.delta == pytest.approx(float((Kt - Kp).abs().max()), rel=1e-6)
    assert check.bound == math.inf  # 4 experiments x 11 times: delta n^1.5 > sigma^2, the theorem is silent
    # a short, small design where the theorem bites: the bound holds
    short = torch.linspace(0, 0.3, 3, dtype=DT)
    small = design.proxy_check([84], cand, system=system, times=short, gp=make_gp(1e-4))
    assert math.isfinite(small.bound) and small.gap <= small.bound
    n = 2 * 1 * 3
    assert small.bound == pytest.approx(-0.5 * n * math.log1p(-small.delta * n**1.5 / NOISE), rel=1e-12)
    blockwise = design.proxy_gap_bound([84], cand, system=system, times=short, gp=make_gp(1e-4), blockwise=True)
    assert small.gap <= blockwise <= small.bound
    # observed states instead of a simulation
    given = design.true_information_gain(res, cand, system=system, times=TIMES, gp=gp, states=true)
    assert given == pytest.approx(exact, rel=1e-12)


# ------------------------------------------------------------------------------------------------ bad inputs
def test_bad_inputs_raise():
    system, gp, cand = paper_linear(), make_gp(), grid13()[:10]
    kw = {"system": system, "times": TIMES, "gp": gp}
    with pytest.raises(BudgetError, match=r"at most the number of candidates \(10\), got budget = 11"):
        design.greedy(cand, 11, **kw)
    with pytest.raises(BudgetError, match="at least 1"):
        design.greedy(cand, 0, **kw)
    labels = torch.tensor([0] * 5 + [1] * 5)
    with pytest.raises(BudgetError, match="at most 3 experiments.*got budget = 4"):
        design.greedy(cand, 4, partition=design.Partition(labels, {0: 1, 1: 2}), **kw)
    with pytest.raises(InputError, match=r"missing \[1\]"):
        design.greedy(cand, 2, partition=design.Partition(labels, {0: 2}), **kw)
    with pytest.raises(InputError, match="non-negative"):
        design.greedy(cand, 2, partition=design.Partition(labels, {0: 2, 1: -1}), **kw)
    with pytest.raises(ShapeError, match=r"partition.*\(10,\)"):
        design.greedy(cand, 2, partition=design.Partition(labels[:4], {0: 2, 1: 2}), **kw)
    with pytest.raises(ShapeError, match=r"expected shape \(N, 2\).*got \(10, 3\)"):
        design.greedy(torch.zeros(10, 3, dtype=DT), 2, **kw)
    with pytest.raises(ShapeError, match="candidates"):
        design.proxy_trajectories(system, torch.zeros(2, dtype=DT), TIMES)
    bad = cand.clone()
    bad[3, 1] = math.nan
    with pytest.raises(InputError, match="candidates: expected finite"):
        design.greedy(bad, 2, **kw)
    with pytest.raises(InputError, match="strictly increasing"):
        design.greedy(cand, 2, system=system, times=torch.tensor([0.0, 1.0, 1.0, 2.0], dtype=DT), gp=gp)
    with pytest.raises(ShapeError, match=r"times: expected shape \(T,\)"):
        design.proxy_trajectories(system, cand, TIMES.reshape(1, -1))
    with pytest.raises(InputError, match="noise_variance"):
        design.greedy(cand, 2, system=system, times=TIMES, gp=CorrectionGP(lengthscale=1.0, outputscale=1.0))
    with pytest.raises(InputError, match="per_output"):
        design.greedy(
            cand,
            2,
            system=system,
            times=TIMES,
            gp=CorrectionGP(lengthscale=1.0, outputscale=1.0, noise_variance=1e-4, per_output=True),
        )
    with pytest.raises(InputError, match="method"):
        design.greedy(cand, 2, method="fast", **kw)
    with pytest.raises(ShapeError, match="proxies"):
        design.greedy(
            cand,
            2,
            system=system,
            gp=gp,
            proxy=design.Proxy(paths=torch.zeros(10, 4, 3, dtype=DT)),
        )
    with pytest.raises(InputError, match="times"):
        design.greedy(cand, 2, system=system, gp=gp)
    with pytest.raises(InputError, match="no true correction"):
        design.true_information_gain([0], cand, system=paper_linear_without_f(), times=TIMES, gp=gp)


def paper_linear_without_f():
    from torchmisspec.systems import MisspecifiedSystem

    base = paper_linear()
    return MisspecifiedSystem(base.known, 2, known_matrix=base.known_matrix, name="no_f")


# ------------------------------------------------------------------------------------------------ larger checks
def test_screened_lazy_identical_on_larger_problem():
    system, gp = paper_linear(), make_gp(4e-5)
    cand = torch.rand(1500, 2, generator=torch.Generator().manual_seed(9), dtype=DT) * 2 - 1
    times = torch.linspace(0, 6, 20, dtype=DT)
    lazy = design.greedy(cand, 25, system=system, times=times, gp=gp)
    assert lazy.diagnostics.get("screening")
    plain = design.greedy(cand, 25, system=system, times=times, gp=gp, method="plain")
    assert lazy.indices.tolist() == plain.indices.tolist()
    torch.testing.assert_close(lazy.gains, plain.gains, atol=1e-9, rtol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("outputscale,lengthscale", [(4e-5, 1.0), (1e-2, 1.0), (1e-2, 0.5), (1e-2, 0.2)])
def test_lazy_identical_to_plain_greedy_many_candidates(outputscale, lengthscale):
    system, gp = paper_linear(), make_gp(outputscale, lengthscale)
    cand = torch.rand(3000, 2, generator=torch.Generator().manual_seed(10), dtype=DT) * 2 - 1
    times = torch.linspace(0, 6, 20, dtype=DT)
    lazy = design.greedy(cand, 30, system=system, times=times, gp=gp)
    plain = design.greedy(cand, 30, system=system, times=times, gp=gp, method="plain")
    assert lazy.indices.tolist() == plain.indices.tolist()
    torch.testing.assert_close(lazy.gains, plain.gains, atol=1e-9, rtol=1e-9)


# ----------------------------------------------------------------------------------------- stochastic greedy
def test_stochastic_greedy_meets_its_expected_guarantee():
    """E[f] >= (1 - 1/e - eps) f(optimum) (Mirzasoleiman et al. 2015): 12 candidates, K = 3, eps = 0.5 (a draw of 3
    per pick, so the draws matter), 60 seeds against the brute-force optimum; every reported gain is the exact
    set's (independent log-determinants) and the marginal gains add up to it."""
    system, outputscale, eps = paper_linear(), 1e-2, 0.5
    cand = torch.rand(12, 2, generator=torch.Generator().manual_seed(3), dtype=DT) * 2 - 1
    prox = simulate(system, cand, TIMES, known_only=True).states
    best = max(set_gain(prox, s, outputscale) for s in itertools.combinations(range(12), 3))
    got = []
    for seed in range(60):
        res = design.greedy(
            cand, 3, system=system, times=TIMES, gp=make_gp(outputscale), method="stochastic",
            engine=design.Engine(epsilon=eps, generator=torch.Generator().manual_seed(seed)),
        )  # fmt: skip
        assert res.diagnostics["sample_size"] == 3
        exact = set_gain(prox, res.indices.tolist(), outputscale)
        assert exact == pytest.approx(res.information_gain, rel=1e-8)
        assert float(res.gains.sum()) == pytest.approx(exact, rel=1e-8)
        got.append(exact / best)
    mean = sum(got) / len(got)
    se = (sum((g - mean) ** 2 for g in got) / (len(got) - 1) / len(got)) ** 0.5
    assert mean - 3 * se >= 1 - 1 / math.e - eps
    assert len({round(g, 9) for g in got}) > 1, "the draws never changed the picks"


def test_stochastic_greedy_with_a_draw_of_every_candidate_is_lazy_greedy():
    system, cand = paper_linear(), grid13()
    gp = make_gp(1e-2)
    lazy = design.greedy(cand, 6, system=system, times=TIMES, gp=gp)
    full = design.greedy(
        cand,
        6,
        system=system,
        times=TIMES,
        gp=gp,
        method="stochastic",
        engine=design.Engine(epsilon=1e-12),
    )
    assert full.diagnostics["sample_size"] == cand.shape[0]
    assert full.indices.tolist() == lazy.indices.tolist()


def test_stochastic_greedy_is_reproducible_and_close_to_lazy_greedy():
    """A seeded generator gives the same picks; with the default eps on 3,000 candidates (screening on) the gain is
    within 2 % of lazy greedy's (measured: 1.1 % below for seed 0 at this small size; the benchmark measures 10^4 and
    10^5 candidates, where the goal is 1 %)."""
    system = paper_linear()
    cand = design.candidates.uniform_box(3000, system.domain, generator=torch.Generator().manual_seed(0))
    gp = make_gp(4e-5)
    lazy = design.greedy(cand, 20, system=system, times=TIMES, gp=gp)
    runs = [
        design.greedy(cand, 20, system=system, times=TIMES, gp=gp, method="stochastic",
                      engine=design.Engine(generator=torch.Generator().manual_seed(s)), )
        for s in (0, 0, 1)
    ]  # fmt: skip
    assert runs[0].indices.tolist() == runs[1].indices.tolist()
    assert runs[0].indices.tolist() != runs[2].indices.tolist()
    assert runs[0].diagnostics["screening"] and runs[0].evaluations < lazy.evaluations
    for run in runs:
        assert run.information_gain >= 0.98 * lazy.information_gain


def test_stochastic_greedy_refuses_what_its_guarantee_does_not_cover():
    system, cand, gp = paper_linear(), grid13(), make_gp()
    common = dict(system=system, times=TIMES, gp=gp)
    with pytest.raises(InputError, match="expected a cardinality budget"):
        design.greedy(
            cand,
            2,
            **common,
            method="stochastic",
            partition=design.Partition([0] * 169, [2]),
        )
    with pytest.raises(InputError, match=r"epsilon: expected a number in \(0, 1\), got 1.0"):
        design.greedy(
            cand,
            2,
            **common,
            method="stochastic",
            engine=design.Engine(epsilon=1.0),
        )
    with pytest.raises(InputError, match="epsilon: expected a positive finite number, got 'x'"):
        design.greedy(
            cand,
            2,
            **common,
            method="stochastic",
            engine=design.Engine(epsilon="x"),
        )
    with pytest.raises(InputError, match="expected method='stochastic' with them, got method='lazy'"):
        design.greedy(
            cand,
            2,
            **common,
            engine=design.Engine(generator=torch.Generator()),
        )
    with pytest.raises(InputError, match="generator: expected a torch.Generator, got int"):
        design.greedy(
            cand,
            2,
            **common,
            method="stochastic",
            engine=design.Engine(generator=0),
        )
