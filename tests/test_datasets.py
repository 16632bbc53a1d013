"""The packaged public data sets load offline, with their models (issue 41, item 1)."""

import dataclasses

import pytest
import torch

import torchmisspec as tms
from torchmisspec import datasets

EXPECTED = {  # name: (experiments, state names, measured states, rows of the CSV)
    "orange": (5, ("circumference",), ("circumference",), 35),
    "loblolly": (14, ("height",), ("height",), 84),
    "chickweight": (50, ("weight",), ("weight",), 578),
    "theoph": (12, ("gut", "conc"), ("conc",), 132),
    "lynx": (1, ("hare", "lynx"), ("lynx",), 114),
    "hare_lynx": (1, ("hare", "lynx"), ("hare", "lynx"), 21),
    "influenza": (1, ("S", "I", "R"), ("I",), 15),
}


def test_names_lists_every_data_set():
    assert datasets.names() == list(EXPECTED)


@pytest.mark.parametrize("name", list(EXPECTED))
def test_each_data_set_loads_with_its_model(name):
    data = datasets.load(name)
    K, states, measured, rows = EXPECTED[name]
    trajs = data.trajectories
    assert isinstance(trajs, tms.Trajectories) and trajs.dtype == torch.float64
    assert trajs.num_experiments == K and trajs.state_names == states
    assert sum(len(t) for t, _ in trajs.experiments()) == rows
    seen = trajs.measured.any(dim=0).tolist()
    assert tuple(n for n, m in zip(states, seen, strict=True) if m) == measured
    assert data.system.state_names == states and data.system.parameters is not None
    assert data.citation.strip() and data.description.strip() and data.noise in ("relative", "counts")
    # positive measurements (the log-scale comparisons of the real-data study need them)
    values = torch.cat([y[~torch.isnan(y)] for _, y in trajs.experiments()])
    assert bool((values >= 0).all())
    # G is finite on the data (a state never measured, the lynx model's hares, set to 1 for the check)
    for _, y in trajs.experiments():
        rhs = data.system.known_rhs(torch.nan_to_num(y, nan=1.0))
        assert rhs.shape == y.shape and bool(torch.isfinite(rhs).all())
    with pytest.raises(dataclasses.FrozenInstanceError):
        data.name = "other"


def test_values_match_the_published_tables():
    flu = datasets.load("influenza").trajectories
    assert flu.states[0, :, 1].tolist() == [1, 3, 8, 26, 76, 225, 298, 258, 233, 189, 128, 68, 29, 14, 4]
    assert flu.states[0, 0].tolist() == [762, 1, 0]
    pelts = datasets.load("hare_lynx").trajectories
    assert pelts.states[0, 0].tolist() == [30.0, 4.0] and pelts.states[0, -1].tolist() == [24.7, 8.6]
    theoph = datasets.load("theoph").trajectories
    assert theoph.states[0, 0].tolist() == [4.02, 0.74]  # subject 1: the dose (mg/kg) is the gut's initial state


def test_unknown_name_is_refused_with_the_list():
    with pytest.raises(tms.InputError, match=r"expected one of \['orange'.*got 'iris'"):
        datasets.load("iris")
