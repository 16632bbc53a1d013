"""The price of a feature term (``min_gain``) and the evidence score of ``kernel="auto"``: checked against brute
force on the exact evidence."""

from __future__ import annotations

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._features import monomial_powers, monomials
from torchmisspec.gp._relevance import _evidence, _penalised, fit_relevance, term_gain
from torchmisspec.gp._sum import _exact_mll, _least_valuable

DT = torch.float64


def _best_gain_by_scan(evidence, w: torch.Tensor, j: int) -> float:
    """max over w_j of evidence(w with w_j) - evidence(w with w_j = 0): a scan in log w_j (steps of 0.1), then a
    golden-section search on the two steps around the best grid point (the evidence is smooth and unimodal there)."""
    off = w.clone()
    off[j] = 0.0
    base = evidence(off)

    def at(t: float) -> float:
        v = w.clone()
        v[j] = math.exp(t)
        return evidence(v)

    grid = torch.linspace(-20, 8, 281, dtype=DT).tolist()
    values = [at(t) for t in grid]
    i = max(range(len(grid)), key=values.__getitem__)
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    r = (math.sqrt(5) - 1) / 2
    a, b = hi - r * (hi - lo), lo + r * (hi - lo)
    fa, fb = at(a), at(b)
    while hi - lo > 1e-7:
        if fa > fb:
            hi, b, fb = b, a, fa
            a = hi - r * (hi - lo)
            fa = at(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + r * (hi - lo)
            fb = at(b)
    return max(max(values[i], fa, fb) - base, 0.0)


@pytest.mark.parametrize("m", [1, 2])
def test_term_gain_is_the_best_evidence_gain(m):
    """The closed form m/2 (theta - 1 - log theta) equals the evidence gained by adding term j at its best weight,
    the others fixed (brute force over the weight on the exact evidence), for one output and two sharing it."""
    g = torch.Generator().manual_seed(0)
    X = torch.rand(80, 2, generator=g, dtype=DT) * 2 - 1
    Phi = monomials(X, monomial_powers(2, 2))
    Y = torch.stack([0.4 * X[:, 0] ** 2 + 0.1 * X[:, 1], 0.3 * X[:, 0] ** 2 - 0.05 * X[:, 1]], -1)[:, :m]
    Y = Y + 0.05 * torch.randn(Y.shape, generator=g, dtype=DT)
    s = 0.05**2
    D = torch.full_like(Y, s)
    w = torch.tensor([0.0, 0.02, 0.01, 0.1, 0.0, 0.003], dtype=DT)  # some terms in, some out

    def evidence(v):
        return _evidence(Phi, Y, D, v)

    for j in range(Phi.shape[1]):
        # sparsity and quality factors of term j with C built from the others (dense, independent of the code)
        others = w.clone()
        others[j] = 0.0
        C = (Phi * others) @ Phi.T + s * torch.eye(len(X), dtype=DT)
        Cinv_phi = torch.linalg.solve(C, Phi[:, j])
        S = float(Phi[:, j] @ Cinv_phi)
        Q2 = float((Cinv_phi @ Y).pow(2).sum())
        closed = float(term_gain(torch.tensor(Q2 / (m * S), dtype=DT), m))
        assert closed == pytest.approx(_best_gain_by_scan(evidence, w, j), abs=1e-6, rel=1e-6)


def test_least_valuable_matches_the_exact_evidence_with_an_rbf_term():
    """features+rbf: the gain of each kept term given all others, the RBF term included, from one factorization
    (Sherman-Morrison), equals the brute-force best gain on the exact N x N evidence."""
    g = torch.Generator().manual_seed(1)
    X = torch.rand(60, 2, generator=g, dtype=DT) * 2 - 1
    Phi = monomials(X, monomial_powers(2, 2))
    Y = (0.3 * X[:, :1] ** 2 + 0.2 * torch.sin(3 * X[:, 1:])) + 0.03 * torch.randn(60, 1, generator=g, dtype=DT)
    rbf = 0.05 * torch.exp(-0.5 * torch.cdist(X, X).pow(2) / 0.5**2)
    D = torch.full_like(Y, 0.03**2)
    w = torch.tensor([0.01, 0.02, 0.0, 0.09, 0.001, 0.004], dtype=DT)

    def evidence(v):
        return float(_exact_mll((Phi * v) @ Phi.T + rbf, Y, D))

    j, gain = _least_valuable(Phi, w, (Phi * w) @ Phi.T + rbf, Y, D)
    gains = {k: _best_gain_by_scan(evidence, w, k) for k in range(6) if w[k] > 0}
    assert j == min(gains, key=gains.get)
    assert gain == pytest.approx(gains[j], abs=1e-6, rel=1e-6)


def _spurious(min_gain, seeds):
    """Spurious terms kept over ``seeds`` fits of F = 0.5 y1^2 (one output) with noise, degree-3 library."""
    count, kept_true = 0, True
    for seed in seeds:
        g = torch.Generator().manual_seed(seed)
        X = torch.rand(300, 2, generator=g, dtype=DT) * 2 - 1
        y = 0.5 * X[:, :1] ** 2 + 0.1 * torch.randn(300, 1, generator=g, dtype=DT)
        gp = tms.CorrectionGP(kernel="features", degree=3, min_gain=min_gain).fit(X, y)
        kept = {t.name for t in gp.terms(["y1", "y2"])}  # the chosen subset
        kept_true &= "y1^2" in kept
        count += len(kept - {"y1^2"})
    return count, kept_true


def test_the_price_removes_spurious_terms_and_keeps_the_true_one():
    seeds = range(12)
    plain, plain_true = _spurious(0.0, seeds)
    priced, priced_true = _spurious(None, seeds)  # default: log(300) / 2 nats
    assert plain_true and priced_true
    assert plain >= 6  # plain automatic relevance keeps weak spurious terms (more than one fit in two)
    assert priced <= plain // 3


def test_collinear_terms_are_not_removed_together():
    """On a circle 1, y1^2 and y2^2 are collinear (y1^2 + y2^2 = r^2): each looks redundant given the others, and
    removing all of them at once lost the constant the data need. The fit keeps a model of the data: its noise is
    the samples' noise, not their whole variance."""
    t = torch.linspace(0, 2.5, 60, dtype=DT)
    X = 1.5 * torch.stack([t.cos(), t.sin()], -1)
    g = torch.Generator().manual_seed(3)
    y = 0.03 + 0.01 * X[:, 1:] + 1e-3 * torch.randn(60, 1, generator=g, dtype=DT)
    gp = tms.CorrectionGP(kernel="features", degree=2).fit(X, y)
    assert float(gp.noise_variance) < 4 * 1e-6
    assert float((gp.predict_mean(X) - y).pow(2).mean()) < 4 * 1e-6
    # the subset the price chose is no worse by evidence less price than plain relevance's (the fit's objective,
    # before the kept terms' slab and the removed terms' chance are set)
    Phi = monomials(X, monomial_powers(2, 2))
    price = 0.5 * math.log(60)
    w, s, _ = fit_relevance(Phi, y, None, floor=None, max_iter=2000, min_gain=price)
    w0, s0, _ = fit_relevance(Phi, y, None, floor=None, max_iter=2000, min_gain=0.0)
    assert _penalised(Phi, y, None, w, s, price) >= _penalised(Phi, y, None, w0, s0, price) - 1e-6
    assert {t.name for t in gp.terms()} == {gp.feature_names()[j] for j in range(6) if w[j] > 0}


def _curve_problem(seed):
    """Three random cubic terms on inputs near a curve (collinear features), noise, unit variance."""
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(100, generator=g, dtype=DT) * 3
    X = torch.stack([t.cos(), 0.7 * t.sin() + 0.3 * t.cos()], -1) + 0.05 * torch.randn(100, 2, generator=g, dtype=DT)
    Phi = monomials(X, monomial_powers(2, 3))
    coef = torch.zeros(Phi.shape[1], dtype=DT)
    coef[torch.randperm(Phi.shape[1], generator=g)[:3]] = torch.randn(3, generator=g, dtype=DT)
    y = (Phi @ coef)[:, None] + 0.05 * torch.randn(100, 1, generator=g, dtype=DT)
    return Phi, y / y.std()


@pytest.mark.parametrize("known", [False, True])
@pytest.mark.parametrize("seed", [5, 16, 22, 28, 32])
def test_priced_fit_is_a_fixed_point_of_the_price(seed, known):
    """At the end of a priced fit no removed term's gain exceeds the price and every kept term's does (gains by
    dense brute force given the final state), and the evidence less the price is at least plain relevance's. These
    seeds broke a first version that removed terms before the weights had settled."""
    Phi, y = _curve_problem(seed)
    price = 0.5 * math.log(len(y))
    noise = torch.full_like(y, 1e-3) if known else None
    w, s, _ = fit_relevance(Phi, y, noise, floor=None, max_iter=2000, min_gain=price)
    D = torch.full_like(y, s) if noise is None else noise + s
    for j in range(Phi.shape[1]):
        others = w.clone()
        others[j] = 0.0
        a = torch.linalg.solve((Phi * others) @ Phi.T + torch.diag(D[:, 0]), Phi[:, j])
        gain = float(term_gain(torch.tensor(float(a @ y[:, 0]) ** 2 / float(Phi[:, j] @ a), dtype=DT), 1))
        if w[j] > 0:
            assert gain > price - 1e-6, (j, gain)
        else:
            assert gain <= price + 1e-4, (j, gain)
    w0, s0, _ = fit_relevance(Phi, y, noise, floor=None, max_iter=2000)
    D0 = torch.full_like(y, s0) if noise is None else noise + s0
    penalised = _evidence(Phi, y, D, w) - price * int((w > 0).sum())
    assert penalised >= _evidence(Phi, y, D0, w0) - price * int((w0 > 0).sum()) - 1e-6


def test_no_term_left_means_the_noise_is_all_the_variance():
    g = torch.Generator().manual_seed(5)
    X = torch.rand(50, 2, generator=g, dtype=DT)
    y = 0.1 * torch.randn(50, 1, generator=g, dtype=DT)
    Phi = monomials(X, monomial_powers(2, 1))
    w, s, _ = fit_relevance(Phi, y, None, floor=None, max_iter=500, min_gain=1e6)
    assert bool((w == 0).all())
    assert s == pytest.approx(float(y.pow(2).mean()))


def test_min_gain_bad_input_and_persistence(tmp_path):
    with pytest.raises(tms.InputError, match="min_gain: expected a finite number >= 0"):
        tms.CorrectionGP(kernel="features", min_gain=-1.0)
    with pytest.raises(tms.InputError, match="min_gain: expected"):
        tms.CorrectionGP(kernel="features", min_gain="bic")
    with pytest.raises(tms.InputError, match="for the feature kernels or 'auto', got 'rbf'"):
        tms.CorrectionGP(kernel="rbf", min_gain=1.0)
    X = torch.rand(40, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    y = X[:, :1] ** 2
    gp = tms.CorrectionGP(kernel="features", min_gain=2.5).fit(X, y)
    assert tms.CorrectionGP.load(gp.save(tmp_path / "f.pt")).min_gain == 2.5
    auto = tms.CorrectionGP(kernel="auto", min_gain=1.5).fit(X, y)
    assert tms.CorrectionGP.load(auto.save(tmp_path / "a.pt")).min_gain == 1.5


def test_evidence_score_is_bic_corrected_evidence_and_auto_chooses_by_it():
    g = torch.Generator().manual_seed(2)
    X = torch.rand(120, 2, generator=g, dtype=DT) * 2 - 1
    y = 0.2 * torch.sin(2 * X) + 0.01 * torch.randn(120, 2, generator=g, dtype=DT)
    rbf = tms.CorrectionGP().fit(X, y)
    assert rbf.num_hyperparameters == 3  # lengthscale, output scale, noise
    assert rbf.evidence_score == pytest.approx(rbf.log_marginal_likelihood_ - 1.5 * math.log(120))
    feats = tms.CorrectionGP(kernel="features", per_output=True).fit(X, y)
    assert feats.num_hyperparameters == len(feats.terms()) + 2  # the chosen terms' weights and two noise floors
    auto = tms.CorrectionGP(kernel="auto").fit(X, y)
    table = {r["kernel"]: r for r in auto.model_selection_}
    from torchmisspec.gp._selection import auto_choice

    library_score = table["features+rbf"].get("library_score")
    scores = {k: r["score"] for k, r in table.items()}
    assert auto.kernel == auto_choice(scores, library_score=library_score, margin=auto.evidence_margin)[0]
    assert [r["kernel"] for r in table.values() if r["chosen"]] == [auto.kernel]
    for r in table.values():
        assert r["score"] == pytest.approx(r["log_marginal_likelihood"] - 0.5 * math.log(120) * r["hyperparameters"])


def test_noiseless_samples_fit_the_sum_kernel():
    """features+rbf on noiseless samples: L-BFGS's last step left the box its evaluations used (a noise floor of 0),
    and the final factorization failed with a bare torch error. Now the term is found."""
    X = torch.rand(40, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    gp = tms.CorrectionGP(kernel="features+rbf").fit(X, X[:, :1] ** 2)
    assert math.isfinite(gp.log_marginal_likelihood_) and gp.noise_variance > 0
    (term,) = [t for t in gp.terms(["x1", "x2"]) if abs(t.mean) > 1e-3]
    assert term.name == "x1^2" and term.mean == pytest.approx(1.0, abs=1e-4)


def test_least_valuable_with_different_noise_per_output_is_an_upper_bound():
    """Known noise that differs between the outputs: the gain is the sum of each output's own best gain (brute
    force per output), never below the best gain of the weight they share."""
    g = torch.Generator().manual_seed(4)
    X = torch.rand(50, 2, generator=g, dtype=DT) * 2 - 1
    Phi = monomials(X, monomial_powers(2, 1))
    Y = torch.stack([0.3 * X[:, 0], 0.2 * X[:, 0] + 0.1 * X[:, 1]], -1) + 0.05 * torch.randn(50, 2, generator=g)
    D = torch.stack([torch.full((50,), 0.05**2, dtype=DT), torch.full((50,), 0.08**2, dtype=DT)], -1)
    rbf = 0.01 * torch.exp(-0.5 * torch.cdist(X, X).pow(2))
    w = torch.tensor([0.01, 0.05, 0.02], dtype=DT)
    j, gain = _least_valuable(Phi, w, (Phi * w) @ Phi.T + rbf, Y, D)

    def one(o):
        return lambda v: float(_exact_mll((Phi * v) @ Phi.T + rbf, Y[:, o : o + 1], D[:, o : o + 1]))

    separate = sum(_best_gain_by_scan(one(o), w, j) for o in range(2))
    shared = _best_gain_by_scan(lambda v: float(_exact_mll((Phi * v) @ Phi.T + rbf, Y, D)), w, j)
    assert gain == pytest.approx(separate, abs=1e-6, rel=1e-6)
    assert gain >= shared - 1e-6
