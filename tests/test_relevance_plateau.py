"""The feature weights' fixed point on nearly exact samples ends where the evidence stops rising (a cycle of about
300 iterations ran to the cap of 2,000, a golden-section search of the noise floor in each: 15 s per fit)."""

from __future__ import annotations

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp import _relevance
from torchmisspec.gp._features import monomial_powers, monomials

DT = torch.float64


def _known(y):
    return torch.stack([-0.1 * y[..., 0] - y[..., 1], y[..., 0] - 0.1 * y[..., 1]], dim=-1)


@pytest.fixture(scope="module")
def exact():
    """21 exact states of paper 5.1's system against a linear G of another shape: samples with known noise about
    1e-12 of their second moment; the cubic monomials and the price of the default fit."""
    traj = tms.simulate(tms.systems.paper_linear(), torch.tensor([[0.8, -0.5]], dtype=DT), torch.linspace(0, 6, 21))
    samples = tms.correction_samples(traj, tms.MisspecifiedSystem(_known, 2))
    Phi = monomials(samples.inputs, monomial_powers(2, 3))
    options = dict(floor=None, max_iter=600, min_gain=0.5 * math.log(samples.num_samples))  # two cycles
    return Phi, samples.targets[:, :1], samples.noise[:, :1], options


def _penalised(case, w, s):
    Phi, Y, known, options = case
    return _relevance._penalised(Phi, Y, known, w, s, options["min_gain"])


def test_a_cycle_ends_at_its_plateau_with_the_same_terms(exact, monkeypatch):
    Phi, Y, known, options = exact
    assert float(known.mean()) < 1e-10 * float(Y.pow(2).mean())  # nearly exact, as the case needs
    w, s, iterations = _relevance.fit_relevance(Phi, Y, known, **options)
    monkeypatch.setattr(_relevance, "_PLATEAU_ITERATIONS", 10**9)  # the rule off: to the cap, as before
    w_cap, s_cap, at_cap = _relevance.fit_relevance(Phi, Y, known, **options)
    assert at_cap == options["max_iter"] and iterations < 0.3 * at_cap
    assert torch.equal(w > 0, w_cap > 0)  # the same terms
    # the state kept is within a hundredth of a nat of the best the capped run found (evidence less price)
    assert _penalised(exact, w, s) == pytest.approx(_penalised(exact, w_cap, s_cap), abs=1e-2)
