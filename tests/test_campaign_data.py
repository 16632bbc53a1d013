"""A campaign started from fit_correction holds the fit's data and refits with its options (issue 42, item 1): the
README's ``tell(observed)`` adds nothing, a new tell refits by ``fit_correction`` on every experiment (each sample
once, the same model a direct fit gives), and saving keeps both. Also ``Trajectories.concatenate`` and the
recognition of experiments held already."""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.data._join import known_experiments
from torchmisspec.noise import Additive

DT = torch.float64
TIMES = torch.linspace(0, 6, 21, dtype=DT)


def _lab(n: int = 6, seed: int = 0, names=("a", "b")):
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(seed)
    y0 = design.candidates.uniform_box(n, system.domain, generator=g)
    states = tms.simulate(system, y0, TIMES).states
    noisy = states * (1 + 0.005 * torch.randn(states.shape, generator=g, dtype=DT))
    return system, tms.Trajectories(TIMES, noisy, state_names=names)


def test_concatenate_keeps_every_experiment_in_order_matching_states_by_name():
    system, lab = _lab(3)
    short = tms.simulate(system, lab.initial_conditions[:2], TIMES[:9])  # unnamed: takes the names in order
    joined = tms.Trajectories.concatenate([lab, short])
    assert joined.state_names == ("a", "b") and joined.lengths == (21, 21, 21, 9, 9)
    torch.testing.assert_close(joined.experiments()[3][1], short.states[0])
    swapped = lab.reordered(["b", "a"])  # named in another order: reordered by name, not by position
    again = tms.Trajectories.concatenate([lab, swapped])
    torch.testing.assert_close(again.states[3], lab.states[0])
    with pytest.raises(tms.InputError, match=r"expected the states \['a', 'b'\] \(in any order, or unnamed\), got"):
        tms.Trajectories.concatenate([lab, lab.with_state_names(["x", "y"])])
    with pytest.raises(tms.InputError, match="expected a non-empty list of Trajectories"):
        tms.Trajectories.concatenate([])


def test_experiments_held_already_are_recognised_by_their_times_and_values():
    _, lab = _lab(3)
    assert known_experiments(lab[[2, 0]], lab) == [True, True]
    changed = lab.with_states(lab.states + torch.tensor([0.0, 1e-9], dtype=DT))
    assert known_experiments(changed, lab) == [False, False, False]
    assert known_experiments(lab.reordered(["b", "a"]), lab) == [True, True, True]
    assert known_experiments(lab, None) == [False, False, False]


@pytest.fixture(scope="module")
def fitted():
    system, lab = _lab(6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(lab, system, progress=False, derivative="central")
    return system, lab, gp


def test_telling_the_fits_own_data_adds_nothing(fitted):
    system, lab, gp = fitted
    camp = design.Campaign(system, design.candidates.grid(system.domain, 7), TIMES, gp)
    assert camp.num_samples == gp.train_inputs_.shape[0] and camp.data.num_experiments == 6
    assert camp.tell(lab) is gp and camp.num_samples == gp.train_inputs_.shape[0]
    assert camp.history[-1]["experiments"] == 0 and camp.history[-1]["already_held"] == 6
    assert "nothing new" in camp.history[-1]["note"]


def test_a_new_tell_refits_by_fit_correction_on_every_experiment_each_sample_once(fitted, tmp_path):
    system, lab, gp = fitted
    camp = design.Campaign(system, design.candidates.grid(system.domain, 7), TIMES, gp)
    asked = camp.ask(2)
    new = tms.simulate(system, asked, TIMES)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        after = camp.tell(tms.Trajectories.concatenate([lab[[0]], new]))  # one held already, two new
        every = tms.Trajectories.concatenate([lab, new])
        direct = tms.fit_correction(every, system, progress=False, derivative="central")
    assert camp.history[-1]["experiments"] == 2 and camp.history[-1]["already_held"] == 1
    assert camp.history[-1]["unrequested"] == 0 and camp.pending == []
    assert camp.data.num_experiments == 8 and after.derivative_.startswith("central")  # the fit's options
    X = after.train_inputs_
    assert torch.unique(X, dim=0).shape[0] == X.shape[0] == direct.train_inputs_.shape[0] == camp.num_samples
    torch.testing.assert_close(X, direct.train_inputs_)
    assert after.kernel == direct.kernel and after.cross_validation_.best == direct.cross_validation_.best
    again = design.Campaign.load(camp.save(tmp_path / "camp.pt"), system)
    assert again.data.num_experiments == 8 and again.pipeline.samples.derivative == "central"
    assert isinstance(again.pipeline.noise, Additive) and again.pipeline.choice == camp.pipeline.choice
    torch.testing.assert_close(again.data.states, camp.data.states)
    assert again.tell(new) is again.gp and again.history[-1]["already_held"] == 2


def test_a_fit_whose_options_are_code_cannot_be_saved_in_a_campaign(fitted, tmp_path):
    system, _, gp = fitted
    camp = design.Campaign(system, design.candidates.grid(system.domain, 5), TIMES, gp)
    samples = dataclasses.replace(camp.pipeline.samples, generator=torch.Generator())
    camp.pipeline = dataclasses.replace(camp.pipeline, samples=samples)
    with pytest.raises(tms.InputError, match="option generator=.*not a plain value and cannot be saved"):
        camp.save(tmp_path / "camp.pt")
    assert not (tmp_path / "camp.pt").exists()


def test_a_campaign_with_uncertain_parameters_designs_at_their_estimate_and_refits_them():
    """G with an uncertain damping c (issue 42: a Campaign refused such systems): started from fit_correction's
    result, the designs run on G at c's posterior mean and tell refits c with F; without an estimate of c the
    campaign refuses, saying how to start."""
    D = torch.float64

    def G(y, theta):
        return torch.stack([y[..., 1], -y[..., 0] - theta[0] * y[..., 1]], -1)

    truth = tms.MisspecifiedSystem(
        lambda y: G(y, torch.tensor([0.3], dtype=D)), 2, correction=lambda x: -0.5 * torch.sin(2 * x),
        correction_inputs=[0], correction_outputs=[1],
    )  # fmt: skip
    system = tms.MisspecifiedSystem(G, 2, correction_inputs=[0], correction_outputs=[1], parameters={"c": (0.4, 0.15)})
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 6, 25, dtype=D)
    clean = tms.simulate(truth, torch.rand(5, 2, generator=g, dtype=D) * 4 - 2, t)
    data = tms.Trajectories(t, clean.states + 0.01 * torch.randn(clean.states.shape, generator=g, dtype=D))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, system, progress=False)
        camp = design.Campaign(system, design.candidates.grid([(-2, 2), (-2, 2)], 9), t, gp)
        assert torch.equal(camp.designed_on.theta, gp.parameters_.mean)
        asked = camp.ask(2)
        after = camp.tell(tms.simulate(truth, asked, t))
    assert camp.data.num_experiments == 7 and after.parameters_ is not None
    assert abs(float(after.parameters_.mean[0]) - 0.3) < 3 * float(after.parameters_.stddev[0]) + 0.01
    assert float(after.parameters_.stddev[0]) <= float(gp.parameters_.stddev[0]) * 1.05
    assert torch.equal(camp.designed_on.theta, after.parameters_.mean)
    with pytest.raises(tms.InputError, match="holds no estimate of them; start the campaign from fit_correction"):
        design.Campaign(system, design.candidates.grid([(-2, 2), (-2, 2)], 5), t, tms.CorrectionGP(lengthscale=1.0))


def test_a_campaigns_data_are_saved_with_their_inputs_readout_and_ragged_lengths():
    from torchmisspec.data import Readout
    from torchmisspec.design import _campaign_data as plain
    from torchmisspec.signals import Controls

    t = [torch.linspace(0, 1, 4, dtype=DT), torch.linspace(0, 2, 6, dtype=DT)]
    y = [torch.rand(4, 2, dtype=DT), torch.rand(6, 2, dtype=DT)]
    readout = Readout([[1.0, 1.0]], ["total"], state_names=["a", "b"])
    controls = Controls([0.0, 1.0], torch.rand(2, 2, 1, dtype=DT))
    traj = tms.Trajectories(t, y, state_names=["a", "b"], controls=controls, readout=readout,
                            readings=[yk.sum(-1, keepdim=True) for yk in y])  # fmt: skip
    back = plain.data_from(plain.data_blob(traj), "camp.pt", DT, traj.device)
    assert back.lengths == (4, 6) and back.state_names == ("a", "b") and back.readout.names == ("total",)
    assert known_experiments(back, traj) == [True, True]
    torch.testing.assert_close(back.controls.at(torch.tensor([[0.5], [1.5]], dtype=DT)),
                               traj.controls.at(torch.tensor([[0.5], [1.5]], dtype=DT)))  # fmt: skip
    with pytest.raises(tms.InputError, match="camp.pt: field 'data' is damaged"):
        plain.data_from({"times": []}, "camp.pt", DT, traj.device)
