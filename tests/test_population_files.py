"""A fitted population saved and loaded (``PopulationFit.save`` / ``PopulationFit.load``): the same values, the
same next subject's design and prediction, nothing but tensors and plain values in the file, and clear errors for
a wrong system or a damaged file."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._calibration import BandCalibration
from torchmisspec.noise import Additive
from torchmisspec.population import Normal, Population
from torchmisspec.population._subjects import fitted_system
from torchmisspec.population.calibration import SubjectCalibration, calibrate_subjects
from torchmisspec.population.design import design_subject
from torchmisspec.population.fit import PopulationFit
from torchmisspec.population.nlme import fit_nlme
from torchmisspec.population.predict import predict_subject

DT = torch.float64


def slope(y, theta):
    return theta[0] * torch.ones_like(y)


def linear_system(name="linear"):
    return tms.MisspecifiedSystem(slope, 1, parameters={"c": (1.0, 0.5)}, state_names=["y"], name=name)


def _population(with_f: bool) -> PopulationFit:
    """A population of 8 linear experiments (y = 2 + c t, c ~ N(1, 0.3^2)); ``with_f``: a correction F(y) fitted
    on samples of a small term (what the population's fit would hold), with F's shifts of the standard errors."""
    g = torch.Generator().manual_seed(3)
    times = torch.linspace(0, 1, 6, dtype=DT)
    c = 1.0 + 0.3 * torch.randn(8, generator=g, dtype=DT)
    states = 2.0 + c[:, None, None] * times[None, :, None] + 0.05 * torch.randn(8, 6, 1, generator=g, dtype=DT)
    states[:, 0] = 2.0
    data = tms.Trajectories(times, states, state_names=["y"])
    system, population = linear_system(), Population(["c"], distribution=Normal())
    nlme = fit_nlme(system, data, population, Additive())
    sub = fitted_system(system, nlme)
    if not with_f:
        fit = PopulationFit(system, population, Additive(), nlme, nlme, None, sub, data)
        return dataclasses.replace(fit, calibration=calibrate_subjects(fit), calibration_alone=calibrate_subjects(
            fit, first=0))  # fmt: skip
    X = torch.linspace(1.0, 6.0, 12, dtype=DT)[:, None]
    gp = tms.CorrectionGP().fit(X, 0.1 * torch.sin(X) + 0.01 * torch.randn(12, 1, generator=g, dtype=DT))
    from torchmisspec.population._f_uncertainty import Shifts

    shifted = nlme.with_shifts(Shifts([0.02 * torch.randn(16, 1, generator=g, dtype=DT)]))
    band = BandCalibration(1.5, 0.9, 0.7, 0.91, (1.0, 1.5), (0.7, 0.91), 5, False, 40, held_out="subjects")
    calibration = SubjectCalibration(band, False, 2, 0.1, 0.3)  # the band under F's mean, widened 1.5 times
    alone = SubjectCalibration(dataclasses.replace(band, scale=0.7), True, 0, 0.2, 0.4)  # F's draws, narrowed
    return PopulationFit(
        system, population, Additive(), nlme, shifted, gp, sub, data, held_out=(1.0, 2.0), calibration=calibration,
        calibration_alone=alone,
    )  # fmt: skip


@pytest.mark.parametrize("with_f", [False, True])
def test_a_saved_population_designs_and_predicts_the_next_subject_as_the_fit_did(tmp_path, with_f):
    fit = _population(with_f)
    path = fit.save(tmp_path / "population.pt")
    raw = torch.load(path, weights_only=True)  # tensors and plain values only: loading runs no code
    assert raw["format"] == "torchmisspec.PopulationFit" and (raw["gp"] is None) != with_f
    back = PopulationFit.load(path, linear_system())
    assert back.known_model == fit.known_model and back.held_out == fit.held_out
    assert back.calibration == fit.calibration and fit.calibration is not None
    assert back.calibration_alone == fit.calibration_alone and fit.calibration_alone.first == 0
    assert back.population == fit.population and type(back.noise) is type(fit.noise)
    for a, b in ((fit.nlme, back.nlme), (fit.classical, back.classical)):
        for k in ("mean", "spread", "effects"):
            torch.testing.assert_close(getattr(b.values, k), getattr(a.values, k), rtol=0, atol=0)
        torch.testing.assert_close(b.modes.eta, a.modes.eta, rtol=0, atol=0)
        for sa, sb in zip(a.standard_errors, b.standard_errors, strict=True):
            torch.testing.assert_close(sb, sa, rtol=0, atol=0)
    torch.testing.assert_close(back.nlme.intervals().mean, fit.nlme.intervals().mean, rtol=0, atol=0)
    grid = torch.linspace(0, 2, 9, dtype=DT)
    designs = [design_subject(f, grid, 2, initial_states=[2.0], generator=torch.Generator().manual_seed(1))
               for f in (fit, back)]  # fmt: skip
    torch.testing.assert_close(designs[1].times, designs[0].times, rtol=0, atol=0)
    assert designs[1].score == designs[0].score
    first = fit.data[0]
    paths = [predict_subject(f, None, grid, first=first, num_samples=8, generator=torch.Generator().manual_seed(2))
             for f in (fit, back)]  # fmt: skip
    torch.testing.assert_close(paths[1].posterior.samples, paths[0].posterior.samples, rtol=0, atol=0)
    torch.testing.assert_close(back.data.states, fit.data.states, rtol=0, atol=0)


def test_a_population_file_refuses_another_system_and_damaged_files(tmp_path):
    fit = _population(False)
    path = fit.save(tmp_path / "population.pt")
    with pytest.raises(tms.InputError, match=r"system: expected the system the population was fitted with"):
        PopulationFit.load(path, linear_system(name="other"))
    other = tms.MisspecifiedSystem(slope, 1, parameters={"k": (1.0, 0.5)}, state_names=["y"], name="linear")
    with pytest.raises(tms.InputError, match=r"'parameters': \['c'\]"):
        PopulationFit.load(path, other)
    with pytest.raises(tms.InputError, match="system: expected the MisspecifiedSystem"):
        PopulationFit.load(path, "linear")
    csv = tmp_path / "lab.csv"
    csv.write_text("time,y\n0,1\n")
    with pytest.raises(tms.InputError, match="expected a PopulationFit file written by PopulationFit.save"):
        PopulationFit.load(csv, linear_system())
    blob = torch.load(path, weights_only=True)
    del blob["classical"]["modes"]["eta"]
    torch.save(blob, tmp_path / "damaged.pt")
    with pytest.raises(tms.InputError, match=r"damaged.pt: a damaged PopulationFit file \(KeyError"):
        PopulationFit.load(tmp_path / "damaged.pt", linear_system())
    torch.save({"format": "torchmisspec.Campaign"}, tmp_path / "campaign.pt")
    with pytest.raises(tms.InputError, match="expected a torchmisspec PopulationFit file"):
        PopulationFit.load(tmp_path / "campaign.pt", linear_system())
    with pytest.raises(tms.InputError, match="path: expected an existing PopulationFit file"):
        PopulationFit.load(tmp_path / "missing.pt", linear_system())
    from torchmisspec.noise import Relative

    class Mine(Relative):  # a user's noise model: code, refused with the fix named
        pass

    with pytest.raises(tms.InputError, match=r"save: expected a population fitted with one of the package's noise"):
        dataclasses.replace(fit, noise=Mine()).save(tmp_path / "mine.pt")
    assert not (tmp_path / "mine.pt").exists()
