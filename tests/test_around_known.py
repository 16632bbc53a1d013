"""Do no harm's second look with uncertain parameters (issue 42's held-out check): the candidates scored at theta's
closed-form mean lose to the known model with its own parameters fitted through the ODE, and the same candidates
learned around those parameters beat it. The chemostat of ``scripts/study_absorbed.py`` (thermal death missing, a
half-life F can stand in for), one realization whose default fit returned the known model before."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.paper import study_absorbed as study
from torchmisspec.paper.oracle import fitted_through_ode

DT = torch.float64


@pytest.fixture(scope="module")
def chemostat():
    g = torch.Generator().manual_seed(42_305)
    truth, declared = study.system(truth=True), study.system()
    t = torch.linspace(0, 24, 13, dtype=DT)
    y0, u = study.experiments(8, g)
    clean = tms.simulate(truth, y0, t, controls=u).states
    data = tms.Trajectories(t, clean * (1 + 0.01 * torch.randn(clean.shape, generator=g, dtype=DT)), controls=u)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = tms.fit_correction(data, declared, progress=False)
    return truth, declared, data, gp, [str(w.message) for w in caught]


@pytest.mark.slow
def test_the_correction_learned_around_the_known_models_parameters_is_kept(chemostat):
    truth, declared, data, gp, messages = chemostat
    cv = gp.cross_validation_
    assert not gp.known_model_ and not any("returning the known model" in m for m in messages)
    assert cv.known_fitted is not None and min(cv.scores) < cv.known_fitted and cv.significant
    # it predicts new inputs better than the classical answer (G's parameters fitted through the ODE, F = 0)
    classical = fitted_through_ode(declared, data, gp.noise_)
    y0, u = study.experiments(10, torch.Generator().manual_seed(5))
    t = torch.linspace(0, 24, 49, dtype=DT)
    true = tms.simulate(truth, y0, t, controls=u).states
    ours = tms.trajectory_rmse(tms.CorrectedODE(declared, gp).predict(y0, t, controls=u), true)
    theirs = tms.trajectory_rmse(tms.simulate(classical, y0, t, controls=u, known_only=True).states, true)
    assert float(ours) < 0.9 * float(theirs)
    # h stays reported as one F can stand in for
    assert not gp.parameters_.identified[0] and any("h: " in m and "not determined" in m for m in messages)
