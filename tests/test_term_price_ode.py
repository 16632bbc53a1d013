"""The sparse rival of the feature kernel refined through the ODE (torchmisspec.learning.refinement._term_price)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchmisspec.learning.refinement._term_price import _whitened, bic, forward_selection, term_price

DT = torch.float64


def _brute_force(A, z, price):
    """The best BIC over every subset of columns (tiny problems only)."""
    q, best = A.shape[1], (math.inf, ())
    for size in range(q + 1):
        for cols in itertools.combinations(range(q), size):
            if cols:
                P = A[:, list(cols)]
                e = z - P @ torch.linalg.lstsq(P, z.unsqueeze(-1)).solution.squeeze(-1)
            else:
                e = z
            best = min(best, (bic(float(e @ e), size, price), cols))
    return best


def test_forward_selection_finds_the_true_sparse_set_as_brute_force_does():
    g = torch.Generator().manual_seed(0)
    n, q = 60, 7
    J = torch.randn(n, q, generator=g, dtype=DT)
    truth = torch.zeros(q, dtype=DT)
    truth[[1, 4]] = torch.tensor([2.0, -1.5], dtype=DT)
    y = J @ truth + 0.3 * torch.randn(n, generator=g, dtype=DT)
    beta = torch.randn(q, generator=g, dtype=DT)  # linearised anywhere: r = J beta - y
    r = J @ beta - y
    price = 0.5 * math.log(n)
    chosen = forward_selection(J, r, beta, price)
    assert chosen.nonzero().flatten().tolist() == [1, 4]
    A, z = _whitened(J, r, beta, None, None)
    assert _brute_force(A, z, price)[1] == (1, 4)


def test_the_initial_states_unit_prior_is_marginalised_exactly():
    g = torch.Generator().manual_seed(1)
    J, J_f = torch.randn(20, 3, generator=g, dtype=DT), torch.randn(20, 2, generator=g, dtype=DT)
    beta, f, r = (
        torch.randn(3, generator=g, dtype=DT),
        torch.randn(2, generator=g, dtype=DT),
        torch.randn(20, generator=g, dtype=DT),
    )
    A, z = _whitened(J, r, beta, J_f, f)
    C = torch.eye(20, dtype=DT) + J_f @ J_f.T  # ||A b - z||^2 = (J b - y)^T C^-1 (J b - y), y = J beta + J_f f - r
    y = J @ beta + J_f @ f - r
    b = torch.randn(3, generator=g, dtype=DT)
    e = J @ b - y
    assert float((A @ b - z).pow(2).sum()) == pytest.approx(float(e @ torch.linalg.solve(C, e)), rel=1e-10)


def test_the_price_is_the_samples_unless_the_user_set_one():
    class Template:
        min_gain = None

    assert term_price(Template(), 62) == pytest.approx(0.5 * math.log(62))
    Template.min_gain = 3.0
    assert term_price(Template(), 62) == 3.0


@pytest.mark.slow
def test_the_ude_lotka_volterra_terms_are_found_where_relevance_kept_fourteen(one_thread):
    """The UDE paper's protocol, realization 4 (issue 41): automatic relevance through the ODE ended with 14 of 20
    terms and F's error over the data's box at 2.04 of its size; the sparse rival is x y in both outputs."""
    import torchmisspec as tms
    from torchmisspec.paper import study_one_trajectory as protocol

    data = protocol.make_data("ude_lotka_volterra", 4)
    traj = tms.Trajectories(data["times"], data["noisy"].unsqueeze(0), state_names=["x", "y"])
    samples = tms.correction_samples(traj, data["system"])
    gp = tms.CorrectionGP(kernel="features", degree=3, per_output=True).fit(samples)
    refined = tms.fit_trajectories(gp, data["system"], traj)
    kept = sorted((t.output, t.name) for t in refined.terms(["x", "y"]) if t.weight > 0)
    assert kept == [(0, "x y"), (1, "x y")]
    assert refined.relevance_record_["terms"] == 2
    assert protocol.f_error(data, refined, 30) < 0.05
