"""One trajectory (issue 41): the feature kernel refined through the ODE is tested against the choice made on time
pieces, on the same held-out last piece, and kept when it forecasts it better. On the GP-ODE Van der Pol protocol
(seed 0) the pieces chose an RBF whose F was 0.91 of |F| off over the data's box, worse than G alone on new initial
conditions; the refined feature kernel finds F = (1 - x^2) y."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec._one_trajectory import _split
from torchmisspec.learning import time_pieces
from torchmisspec.paper import study_one_trajectory as protocol

DT = torch.float64


def test_the_split_is_the_pieces_before_the_last_and_the_last():
    t = torch.linspace(0, 3, 31, dtype=DT)
    y = torch.stack([t, t**2], dim=-1).unsqueeze(0)
    pieces = time_pieces(tms.Trajectories(t, y, state_names=["a", "b"]))
    early, last = _split(pieces)
    (te, ye), (tl, yl) = early.experiments()[0], last.experiments()[0]
    assert torch.equal(torch.cat([te, tl]), t) and torch.equal(torch.cat([ye, yl]), y[0])
    assert te.shape[0] == sum(p[0].shape[0] for p in pieces.experiments()[:-1])
    assert early.state_names == last.state_names == ("a", "b") or list(early.state_names) == ["a", "b"]


@pytest.mark.slow
def test_van_der_pol_one_trajectory_keeps_the_refined_feature_kernel(one_thread):
    data = protocol.make_data("gpode_van_der_pol", 0)
    trajectories = tms.Trajectories(data["times"], data["noisy"].unsqueeze(0), state_names=["x", "y"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(trajectories, data["system"], progress=False)
    rival = gp.one_trajectory_rival_
    assert rival["refined features"] < rival["chosen"]  # the held-out last piece decided
    assert gp.kernel_spec.terms and gp.kernel_spec.feature_space and not gp.known_model_
    assert protocol.f_error(data, gp, 30) < 0.3  # the RBF the pieces chose: 0.91
    model = tms.CorrectedODE(data["system"], gp)
    new = protocol.new_conditions(data, model, 20)
    assert new["corrected_rmse"] < new["known_rmse"]  # better than G alone off the one path (the RBF: worse)
